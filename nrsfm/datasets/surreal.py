"""SURREAL dense bodies (SMPL meshes, 6,890 vertices) as NRSfM sequences.

SURREAL ships SMPL parameters, not vertices; this loader reads vertex sequences exported from them. Expected
layout under the data folder (``root`` or ``$NRSFM_DATA``): ``surreal/<split>/<clip>.npz``, each holding
``vertices`` `(F, V, 3)` (metres, y up, as SMPL writes them; V = 6,890 for SMPL) and optionally ``faces``
`(T, 3)`. ``<split>`` is ``train`` or ``test``. One way to write them: run SMPL (with a model file you obtained
from its authors) on the ``pose``, ``shape`` and ``gender`` of each clip's ``*_info.mat`` and save the vertices.

The PRN paper's input (Table 4): each frame seen by an orthographic camera turned at random about the vertical
axis (:func:`surreal_sequence`).
"""

from __future__ import annotations

import os

import numpy as np
from scipy.spatial.transform import Rotation

from nrsfm.datasets.paths import find_dataset
from nrsfm.errors import DataFormatError
from nrsfm.sequence import Sequence

SPLITS = ("train", "test")


def surreal_sequence(vertices: np.ndarray, *, seed: int = 0, name: str = "surreal", **meta) -> Sequence:
    """World-frame vertices `(F, V, 3)` (y up) seen per frame by an orthographic camera turned at random about
    the vertical axis; ``points_3d`` in the camera frame, centred per frame; millimetres."""
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 3 or v.shape[2] != 3 or len(v) < 1:
        raise DataFormatError(f"{name}: expected vertices of shape (F, V, 3), got {v.shape}")
    rng = np.random.default_rng([seed, len(v), v.shape[1]])
    rot = Rotation.from_euler("y", rng.uniform(-np.pi, np.pi, (len(v), 1))).as_matrix()  # (F, 3, 3)
    cam = np.einsum("fij,fpj->fpi", rot, v - v.mean(axis=1, keepdims=True))
    cam[..., 1] *= -1  # image y points down, as in the other datasets' 2D
    cam[..., 2] *= -1  # keep a right-handed camera frame
    return Sequence(points_2d=cam[..., :2].copy(), points_3d=cam, camera_rotations=rot, name=name, fps=30.0,
                    meta={"dataset": "surreal", **meta})


def load_surreal(split: str, root: str | os.PathLike | None = None, *, max_clips: int | None = None,
                 seed: int = 0, units: float = 1000.0) -> list[Sequence]:
    """Every exported clip of ``split`` (``surreal/<split>/*.npz``), sorted by name, as :func:`surreal_sequence`;
    ``units`` converts the files' metres to millimetres."""
    if split not in SPLITS:
        raise DataFormatError(f"split: expected one of {SPLITS}, got {split!r}")
    folder = find_dataset("surreal", root) / split
    files = sorted(folder.glob("*.npz")) if folder.is_dir() else []
    if not files:
        raise DataFormatError(f"{folder}: expected exported clips <clip>.npz with 'vertices' (F, V, 3); see "
                              "nrsfm.datasets.surreal for the layout")
    out = []
    for i, f in enumerate(files[:max_clips]):
        with np.load(f) as z:
            if "vertices" not in z:
                raise DataFormatError(f"{f}: expected an array 'vertices' (F, V, 3), found {sorted(z.files)}")
            v = z["vertices"]
        out.append(surreal_sequence(v * units, seed=seed + i, name=f"surreal-{split}-{f.stem}", clip=f.stem))
    return out
