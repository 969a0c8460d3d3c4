"""SURREAL bodies (Varol et al., CVPR 2017) as NRSfM sequences: dense SMPL meshes (6,890 vertices) or the 24
SMPL joints of SURREAL's own annotation files.

Expected layout under the data folder (``root`` or ``$NRSFM_DATA``): ``surreal/<split>/`` (``<split>`` is
``train`` or ``test``) holding one file per clip, either

- ``<clip>.npz`` with ``vertices`` `(F, V, 3)` (metres, y up, as SMPL writes them; V = 6,890 for SMPL) and
  optionally ``faces`` `(T, 3)`: SURREAL ships SMPL parameters, not vertices; one way to write them is to run
  SMPL (with a model file you obtained from its authors) on the ``pose``, ``shape`` and ``gender`` of each
  clip's ``*_info.mat``; or
- ``<clip>_info.mat``, SURREAL's own annotation file (MATLAB v5): ``joints3D`` `(3, 24, F)` world metres,
  ``joints2D`` `(2, 24, F)` pixels, ``camLoc`` `(3, 1)` the camera's position, ``zrot``, ``pose``, ``shape``...
  Without an SMPL model these give skeletons of 24 joints (:func:`load_surreal_info`).

The PRN paper's input (Table 4): each frame seen by an orthographic camera turned at random about the vertical
axis (:func:`surreal_sequence`); :func:`load_surreal_info` gives a clip as SURREAL's perspective camera saw it.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from nrsfm.datasets.paths import find_dataset
from nrsfm.errors import DataFormatError
from nrsfm.sequence import Sequence

SPLITS = ("train", "test")
#: The 24 SMPL joints of ``joints3D`` / ``joints2D``, in their order, and each one's parent (-1: the root).
SMPL_JOINTS = ("hips", "leftUpLeg", "rightUpLeg", "spine", "leftLeg", "rightLeg", "spine1", "leftFoot", "rightFoot",
               "spine2", "leftToeBase", "rightToeBase", "neck", "leftShoulder", "rightShoulder", "head", "leftArm",
               "rightArm", "leftForeArm", "rightForeArm", "leftHand", "rightHand", "leftHandIndex1",
               "rightHandIndex1")
SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
SMPL_EDGES = tuple((p, j) for j, p in enumerate(SMPL_PARENTS) if p >= 0)
#: SURREAL's camera (its ``getIntrinsicBlender``): 320 x 240 pixels, a 60 mm lens on a 32 mm sensor.
INTRINSICS = np.array([[600.0, 0.0, 160.0], [0.0, 600.0, 120.0], [0.0, 0.0, 1.0]])
#: World to Blender camera (the first three columns of the camera's ``matrix_world``, transposed), and Blender's
#: camera to the computer-vision camera (x right, y down, z forward): SURREAL's ``getExtrinsicBlender``.
_WORLD_TO_BLENDER = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]]).T
_BLENDER_TO_CV = np.diag([1.0, -1.0, -1.0])


def surreal_camera(cam_loc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SURREAL's world-to-camera transform for a camera at ``cam_loc`` `(3,)` (``camLoc``): `(3, 3)` rotation R
    and `(3,)` translation t, so that a world point X is ``R X + t`` in the computer-vision camera frame."""
    t_blender = -_WORLD_TO_BLENDER @ np.asarray(cam_loc, dtype=np.float64).reshape(3)
    return _BLENDER_TO_CV @ _WORLD_TO_BLENDER, _BLENDER_TO_CV @ t_blender


def read_surreal_info(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The arrays of one SURREAL ``*_info.mat`` that the loaders use: ``joints3D`` `(F, 24, 3)` world metres,
    ``joints2D`` `(F, 24, 2)` pixels, ``camLoc`` `(3,)` and ``zrot`` `(F,)`."""
    from scipy.io import loadmat

    try:
        mat = loadmat(str(path))
    except (OSError, ValueError, NotImplementedError) as exc:
        raise DataFormatError(f"{path}: expected a SURREAL *_info.mat (MATLAB v5): {exc}") from None
    missing = [k for k in ("joints3D", "joints2D", "camLoc") if k not in mat]
    if missing:
        raise DataFormatError(f"{path}: expected SURREAL's joints3D, joints2D and camLoc, missing {missing}")
    j3, j2 = np.asarray(mat["joints3D"], np.float64), np.asarray(mat["joints2D"], np.float64)
    if j3.ndim == 2:  # a one-frame clip, saved without its frame axis
        j3, j2 = j3[..., None], j2[..., None]
    n = len(SMPL_JOINTS)
    if j3.shape[:2] != (3, n) or j2.shape[:2] != (2, n) or j3.shape[2] != j2.shape[2]:
        raise DataFormatError(f"{path}: expected joints3D (3, {n}, F) and joints2D (2, {n}, F), got {j3.shape} and "
                              f"{j2.shape}")
    zrot = np.asarray(mat.get("zrot", np.zeros(j3.shape[2])), np.float64).reshape(-1)
    return {"joints3D": j3.transpose(2, 1, 0), "joints2D": j2.transpose(2, 1, 0),
            "camLoc": np.asarray(mat["camLoc"], np.float64).reshape(3), "zrot": zrot}


def load_surreal_info(path: str | os.PathLike, *, units: float = 1000.0) -> Sequence:
    """One clip's 24 SMPL joints as SURREAL's camera saw them: ``points_3d`` `(F, 24, 3)` in the camera frame
    (world to camera by :func:`surreal_camera`, millimetres with ``units`` per metre), ``points_2d`` the file's
    ``joints2D`` pixels, perspective with :data:`INTRINSICS`."""
    info = read_surreal_info(path)
    rot, t = surreal_camera(info["camLoc"])
    cam = (info["joints3D"] @ rot.T + t) * units  # (F, 24, 3)
    stem = Path(path).name.removesuffix("_info.mat")
    return Sequence(points_2d=info["joints2D"], points_3d=cam, projection="perspective", intrinsics=INTRINSICS,
                    joint_names=SMPL_JOINTS, edges=np.array(SMPL_EDGES), name=f"surreal-{stem}", fps=30.0,
                    meta={"dataset": "surreal", "clip": stem, "input": "joints2D"})


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
    """Every clip of ``split``, sorted by name, as :func:`surreal_sequence` (the paper's Table 4 input): the
    exported meshes ``surreal/<split>/*.npz`` where there are any, else the 24 joints of SURREAL's own
    ``*_info.mat`` files (their world frame turned to y up); ``units`` converts metres to millimetres."""
    if split not in SPLITS:
        raise DataFormatError(f"split: expected one of {SPLITS}, got {split!r}")
    folder = find_dataset("surreal", root) / split
    meshes = sorted(folder.glob("*.npz")) if folder.is_dir() else []
    infos = sorted(folder.glob("*_info.mat")) if folder.is_dir() and not meshes else []
    if not meshes and not infos:
        raise DataFormatError(f"{folder}: expected exported clips <clip>.npz with 'vertices' (F, V, 3) or SURREAL's "
                              "<clip>_info.mat files; see nrsfm.datasets.surreal for the layout")
    out = []
    for i, f in enumerate(meshes[:max_clips]):
        with np.load(f) as z:
            if "vertices" not in z:
                raise DataFormatError(f"{f}: expected an array 'vertices' (F, V, 3), found {sorted(z.files)}")
            v = z["vertices"]
        out.append(surreal_sequence(v * units, seed=seed + i, name=f"surreal-{split}-{f.stem}", clip=f.stem))
    for i, f in enumerate(infos[:max_clips]):
        world = read_surreal_info(f)["joints3D"] * np.array([1.0, -1.0, -1.0])  # SURREAL's y points down: y up
        stem = f.name.removesuffix("_info.mat")
        seq = surreal_sequence(world * units, seed=seed + i, name=f"surreal-{split}-{stem}", clip=stem,
                               points="joints")
        out.append(seq.replace(joint_names=SMPL_JOINTS, edges=np.array(SMPL_EDGES)))
    return out
