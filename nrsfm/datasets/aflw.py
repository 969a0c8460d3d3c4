"""AFLW2000-3D: 68 face landmarks of real face images over a wide range of head poses (Zhu, Lei, Liu, Shi & Li,
"Face alignment across large poses: a 3D solution", CVPR 2016), as released with the 3DDFA code.

Expected layout under the data folder (``root`` or ``$NRSFM_DATA``), the release's files:

- ``aflw2000/AFLW2000-3D.pts68.npy``: `(N, 3, 68)`, the fitted 3D landmarks: x, y in image pixels (y down) and
  the depth z; orthographic, so (x, y) is the 3D shape's 2D projection;
- ``aflw2000/AFLW2000-3D-Reannotated.pts68.npy``: `(N, 2, 68)`, the same faces' 2D landmarks corrected by hand
  (real 2D that is not the 3D's projection, as a detector's would be);
- ``aflw2000/AFLW2000-3D.pose.npy``: `(N,)`, each face's yaw in degrees.

The landmark order is the usual 68-point one (iBUG / 300-W / 300-VW). The faces are an image collection, not a
video: one face per frame of the returned sequence, in the file's order, and nothing here assumes temporal order.
Every face is one frame of one :class:`~nrsfm.sequence.Sequence`; :func:`split_aflw2000` cuts it by index.
"""

from __future__ import annotations

import os

import numpy as np

from nrsfm.datasets.paths import find_dataset
from nrsfm.datasets.synthetic import FACE_EDGES
from nrsfm.errors import DataFormatError
from nrsfm.sequence import Sequence

FILES = {"3d": "AFLW2000-3D.pts68.npy", "reannotated": "AFLW2000-3D-Reannotated.pts68.npy",
         "yaw": "AFLW2000-3D.pose.npy"}
#: The 2D inputs: ``fitted``, the 3D landmarks' own (x, y); ``reannotated``, the hand-corrected 2D.
INPUTS = ("fitted", "reannotated")
#: The share of the faces, in the file's order, that trains (the rest tests).
TRAIN_FRACTION = 0.75
#: Yaw bands (degrees of absolute yaw) for the per-band errors; the last band takes everything beyond 60.
YAW_BANDS = ((0.0, 30.0), (30.0, 60.0), (60.0, 90.0))
N_LANDMARKS = 68


def _load(path, shape_tail: tuple[int, ...], what: str) -> np.ndarray:
    try:
        x = np.load(path)
    except (OSError, ValueError) as exc:
        raise DataFormatError(f"{path}: expected a NumPy .npy file of {what}: {exc}") from None
    if x.ndim != 1 + len(shape_tail) or x.shape[1:] != shape_tail:
        raise DataFormatError(f"{path}: expected {what} of shape (N, {', '.join(map(str, shape_tail))}), got "
                              f"{x.shape}")
    return np.asarray(x, dtype=np.float64)


def load_aflw2000(root: str | os.PathLike | None = None, *, input: str = "fitted") -> Sequence:
    """Every face of the release as one sequence (a frame per face, in the file's order).

    Args:
        root: the data folder holding ``aflw2000/`` (default: ``$NRSFM_DATA``).
        input: ``"fitted"``: the 2D input is the fitted 3D landmarks' (x, y); ``"reannotated"``: the
            hand-corrected 2D, with each 3D face moved so that its landmarks' (x, y) mean is the 2D's.

    Returns:
        A :class:`Sequence`: ``points_2d`` `(N, 68, 2)` pixels, ``points_3d`` `(N, 68, 3)` (x, y pixels, z depth,
        orthographic camera frame), ``meta["yaw"]`` each face's yaw in degrees (comma-separated, as a
        sequence's metadata are text; :func:`face_yaw` reads it), ``meta["collection"]`` ``"true"``.
    """
    if input not in INPUTS:
        raise DataFormatError(f"input: expected one of {INPUTS}, got {input!r}")
    folder = find_dataset("aflw2000", root)
    missing = [f for f in FILES.values() if not (folder / f).is_file()]
    if missing:
        raise DataFormatError(f"{folder}: expected the AFLW2000-3D files {list(FILES.values())}, missing {missing}")
    x3 = _load(folder / FILES["3d"], (3, N_LANDMARKS), "3D landmarks").transpose(0, 2, 1)  # (N, 68, 3)
    yaw = _load(folder / FILES["yaw"], (), "yaw angles")
    if len(yaw) != len(x3):
        raise DataFormatError(f"{folder / FILES['yaw']}: expected one yaw per face ({len(x3)}), got {len(yaw)}")
    if input == "fitted":
        x2 = x3[..., :2].copy()
    else:
        x2 = _load(folder / FILES["reannotated"], (2, N_LANDMARKS), "2D landmarks").transpose(0, 2, 1)
        if len(x2) != len(x3):
            raise DataFormatError(f"{folder / FILES['reannotated']}: expected one face per 3D face ({len(x3)}), "
                                  f"got {len(x2)}")
        x3 = x3.copy()
        x3[..., :2] += (x2.mean(axis=1) - x3[..., :2].mean(axis=1))[:, None]
    return Sequence(points_2d=x2, points_3d=x3, name=f"aflw2000-{input}", edges=np.array(FACE_EDGES),
                    meta={"dataset": "aflw2000", "input": input, "collection": "true", "yaw": _yaw_text(yaw),
                          "faces": str(len(x3)), "first_face": "0"})


def _yaw_text(yaw) -> str:
    return ",".join(f"{v:.6g}" for v in yaw)


def face_yaw(seq: Sequence) -> np.ndarray:
    """`(F,)` yaw in degrees of each face of ``seq`` (from :func:`load_aflw2000`'s metadata)."""
    text = seq.meta.get("yaw")
    if text is None:
        raise DataFormatError(f"{seq.name}: expected the faces' yaw in meta['yaw'] (load_aflw2000 writes it)")
    yaw = np.array([float(v) for v in text.split(",")]) if text else np.zeros(0)
    if len(yaw) != seq.n_frames:
        raise DataFormatError(f"{seq.name}: meta['yaw'] holds {len(yaw)} angles for {seq.n_frames} faces")
    return yaw


def split_aflw2000(seq: Sequence, train_fraction: float = TRAIN_FRACTION) -> tuple[Sequence, Sequence]:
    """The fixed split by index: the first ``floor(train_fraction * N)`` faces train, the rest test, whatever N."""
    n = seq.n_frames
    k = int(np.floor(train_fraction * n))
    if not 0 < k < n:
        raise DataFormatError(f"{seq.name}: expected at least two faces to split {train_fraction:g} / "
                              f"{1 - train_fraction:g}, got {n}")
    yaw = face_yaw(seq) if "yaw" in seq.meta else None
    first = int(seq.meta.get("first_face", 0))
    parts = []
    for name, idx in (("train", np.arange(k)), ("test", np.arange(k, n))):
        meta = {**seq.meta, "faces": str(len(idx)), "first_face": str(first + int(idx[0]))}
        if yaw is not None:
            meta["yaw"] = _yaw_text(yaw[idx])
        parts.append(seq.select_frames(idx).replace(name=f"{seq.name}-{name}", meta=meta))
    return parts[0], parts[1]


def yaw_band(yaw: np.ndarray) -> np.ndarray:
    """`(N,)` band labels (``"0-30"``, ``"30-60"``, ``"60-90"``) of yaw angles in degrees: the absolute yaw
    wrapped to [0, 180], the last band taking everything from 60 on (the release has a few faces beyond 90)."""
    a = np.abs((np.asarray(yaw, dtype=np.float64) + 180.0) % 360.0 - 180.0)
    labels = np.array([f"{lo:g}-{hi:g}" for lo, hi in YAW_BANDS])
    return labels[np.clip(np.searchsorted([hi for _, hi in YAW_BANDS[:-1]], a, side="right"), 0, len(labels) - 1)]
