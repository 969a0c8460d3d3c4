"""Human3.6M loaders: the 3d-pose-baseline h5 layout and the VideoPose3D npz layout.

3d-pose-baseline layout (Martinez et al., ICCV 2017)::

    <root>/cameras.h5                      subject{N}/camera{1..4}/{R,T,f,c,k,p,Name}
    <root>/S{N}/MyPoses/3D_positions/<Action>[ <n>].h5        dataset 3D_positions (96, F), world mm
    <root>/S{N}/StackedHourglass/<Action>[_<n>].<camera id>.h5  dataset poses (F, 16, 2), pixels

The public files are 50 fps (``stride=5`` gives PRN's 10 fps); some copies
are already subsampled (``stride=1``). ``R`` is stored transposed:
camera coordinates are ``Xc = R_stored.T @ (Xw - T)``.

VideoPose3D layout (Pavllo et al., CVPR 2019): ``data_3d_h36m.npz`` with a
pickled dict ``positions_3d[subject][action]`` `(F, 32, 3)` in world metres,
and ``data_2d_h36m_<kind>.npz`` with ``positions_2d[subject][action][camera]``
`(F, 17, 2)` pixels. These are the user's own files and need
``allow_pickle=True``; the cameras come from ``cameras.h5``.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nrsfm.errors import DataFormatError, ValidationError
from nrsfm.geometry import project_perspective
from nrsfm.sequence import Sequence

#: 0-based indices of PRN's 17 joints among the 32 of Human3.6M.
JOINTS_32_TO_17 = (0, 1, 2, 3, 6, 7, 8, 12, 13, 14, 15, 17, 18, 19, 25, 26, 27)
JOINT_NAMES = ("Hip", "RHip", "RKnee", "RFoot", "LHip", "LKnee", "LFoot", "Spine", "Thorax", "Neck/Nose", "Head",
               "LShoulder", "LElbow", "LWrist", "RShoulder", "RElbow", "RWrist")
#: Parent of each of the 17 joints (-1 for the root).
PARENTS = (-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 9, 8, 11, 12, 8, 14, 15)
EDGES = tuple((p, j) for j, p in enumerate(PARENTS) if p >= 0)
#: Joint order of the Stacked Hourglass detections of 3d-pose-baseline.
SH_JOINT_NAMES = ("RFoot", "RKnee", "RHip", "LHip", "LKnee", "LFoot", "Hip", "Spine", "Thorax", "Head", "RWrist",
                  "RElbow", "RShoulder", "LShoulder", "LElbow", "LWrist")
#: For each of the 17 joints, its index among the 16 SH joints, -1 for Neck/Nose (not detected).
SH_TO_17 = tuple(SH_JOINT_NAMES.index(n) if n in SH_JOINT_NAMES else -1 for n in JOINT_NAMES)
ACTIONS = ("Directions", "Discussion", "Eating", "Greeting", "Phoning", "Photo", "Posing", "Purchases", "Sitting",
           "SittingDown", "Smoking", "Waiting", "WalkDog", "WalkTogether", "Walking")
CAMERA_IDS = ("54138969", "55011271", "58860488", "60457274")
TRAIN_SUBJECTS = ("S1", "S5", "S6", "S7", "S8")
TEST_SUBJECTS = ("S9", "S11")
INPUTS = ("gt-ortho", "gt-persp", "sh")


@dataclass(frozen=True)
class Camera:
    """A Human3.6M camera.

    Attributes:
        rotation: `(3, 3)` world-to-camera rotation (the stored R, transposed).
        centre: `(3,)` camera centre in world millimetres (the stored T).
        focal: `(2,)` focal lengths in pixels; principal: `(2,)` principal point.
    """

    rotation: np.ndarray
    centre: np.ndarray
    focal: np.ndarray
    principal: np.ndarray
    name: str = ""

    @property
    def intrinsics(self) -> np.ndarray:
        """`(3, 3)` calibration matrix K."""
        return np.array([[self.focal[0], 0, self.principal[0]], [0, self.focal[1], self.principal[1]], [0, 0, 1.0]])

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """`(..., 3)` world points -> `(..., 3)` camera-frame points ``R (X - T)``."""
        return (points - self.centre) @ self.rotation.T


def _subject_key(subject: str | int) -> str:
    s = str(subject)
    if not re.fullmatch(r"S?\d+", s):
        raise ValidationError(f"subject: expected a Human3.6M subject like 'S9' or 9, got {subject!r}")
    return s if s.startswith("S") else f"S{s}"


def load_cameras(path: str | os.PathLike) -> dict[tuple[str, int], Camera]:
    """Read ``cameras.h5`` into ``{(subject, camera 1..4): Camera}``."""
    import h5py

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file (expected the 3d-pose-baseline cameras.h5)")
    cams: dict[tuple[str, int], Camera] = {}
    with h5py.File(path, "r") as h5:
        for subj in h5:
            m = re.fullmatch(r"subject(\d+)", subj)
            if not m:
                continue
            for cam in h5[subj]:
                c = re.fullmatch(r"camera(\d+)", cam)
                if not c:
                    continue
                g = h5[subj][cam]
                name = "".join(chr(int(x)) for x in np.ravel(g["Name"][()])) if "Name" in g else ""
                cams[(f"S{m.group(1)}", int(c.group(1)))] = Camera(
                    rotation=np.asarray(g["R"][()], dtype=np.float64).T,
                    centre=np.asarray(g["T"][()], dtype=np.float64).ravel(),
                    focal=np.asarray(g["f"][()], dtype=np.float64).ravel(),
                    principal=np.asarray(g["c"][()], dtype=np.float64).ravel(),
                    name=name,
                )
    if not cams:
        raise DataFormatError(f"{path}: expected groups subject<N>/camera<1..4>, found none")
    return cams


def list_actions(root: str | os.PathLike, subject: str | int) -> list[str]:
    """File stems of the 3D-position files of one subject, e.g. ``['Directions', 'Directions 1', ...]``."""
    folder = Path(root) / _subject_key(subject) / "MyPoses" / "3D_positions"
    if not folder.is_dir():
        return []
    return sorted(p.stem for p in folder.glob("*.h5"))


def action_of(file_stem: str) -> str:
    """``'Walking 1'`` -> ``'Walking'``; ``'WalkDog'`` -> ``'WalkDog'``."""
    return file_stem.split(" ")[0].split("_")[0]


def load_h36m_sequence(root: str | os.PathLike, subject: str | int, action: str, camera: int, *,
                       input: str = "gt-ortho", stride: int = 5, source_fps: float = 50.0,
                       cameras: dict[tuple[str, int], Camera] | None = None) -> Sequence:
    """One subject / sub-action / camera of Human3.6M as a 17-joint :class:`Sequence`.

    Args:
        root: folder in the 3d-pose-baseline layout (holds ``cameras.h5`` and ``S*``).
        subject: ``'S9'`` or ``9``.
        action: file stem of the sub-action, e.g. ``'Walking'`` or ``'Walking 1'``.
        camera: 1..4 (ids 54138969, 55011271, 58860488, 60457274).
        input: ``'gt-ortho'`` (orthographic projection of the camera-frame 3D, mm),
            ``'gt-persp'`` (perspective projection, pixels) or ``'sh'`` (Stacked
            Hourglass detections, pixels; Neck/Nose is not detected and gets
            visibility 0).
        stride: keep every ``stride``-th frame (5 for the public 50 fps files).
        source_fps: frame rate of the files.

    Returns:
        A sequence with ``points_3d`` `(F, 17, 3)` in camera millimetres.
    """
    if input not in INPUTS:
        raise ValidationError(f"input: expected one of {INPUTS}, got {input!r}")
    if camera not in (1, 2, 3, 4):
        raise ValidationError(f"camera: expected 1, 2, 3 or 4, got {camera!r}")
    if stride < 1:
        raise ValidationError(f"stride: expected a positive integer, got {stride}")
    root = Path(root)
    subj = _subject_key(subject)
    cams = cameras if cameras is not None else load_cameras(root / "cameras.h5")
    if (subj, camera) not in cams:
        raise DataFormatError(f"cameras.h5: expected subject{subj[1:]}/camera{camera}, not present")
    cam = cams[(subj, camera)]
    world = load_h36m_world(root, subj, action, stride=stride)  # (F, 17, 3)
    cam3d = cam.world_to_camera(world)  # (F, 17, 3)
    return _make_sequence(cam3d, cam, input, lambda: _read_sh(root, subj, action, camera, stride),
                          name=f"{subj}/{action}/cam{camera}", subject=subj, action=action, camera=camera,
                          fps=source_fps / stride)


def load_h36m_world(root: str | os.PathLike, subject: str | int, action: str, *, stride: int = 5) -> np.ndarray:
    """The 17 joints of one subject / sub-action in Human3.6M's world frame: `(F, 17, 3)` mm, z up, every
    ``stride``-th frame."""
    import h5py

    root, subj = Path(root), _subject_key(subject)
    f3d = root / subj / "MyPoses" / "3D_positions" / f"{action}.h5"
    if not f3d.exists():
        raise FileNotFoundError(f"{f3d}: no such file (known for {subj}: {list_actions(root, subj)})")
    with h5py.File(f3d, "r") as h5:
        raw = np.asarray(h5["3D_positions"][()], dtype=np.float64)  # (96, F)
    if raw.ndim != 2 or raw.shape[0] != 96:
        raise DataFormatError(f"{f3d}: 3D_positions: expected (96, F), got {raw.shape}")
    return raw.T.reshape(-1, 32, 3)[::stride][:, JOINTS_32_TO_17]


def _read_sh(root: Path, subj: str, action: str, camera: int, stride: int) -> np.ndarray:
    import h5py

    fsh = root / subj / "StackedHourglass" / f"{action.replace(' ', '_')}.{CAMERA_IDS[camera - 1]}.h5"
    if not fsh.exists():
        raise FileNotFoundError(f"{fsh}: no such file (Stacked Hourglass detections for {subj} {action})")
    with h5py.File(fsh, "r") as h5:
        poses = np.asarray(h5["poses"][()], dtype=np.float64)  # (F, 16, 2)
    if poses.ndim != 3 or poses.shape[1:] != (16, 2):
        raise DataFormatError(f"{fsh}: poses: expected (F, 16, 2), got {poses.shape}")
    return poses[::stride]


def sh_to_17(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map `(F, 16, 2)` Stacked Hourglass joints to the 17-joint order.

    Returns:
        `(F, 17, 2)` points (Neck/Nose filled with the Thorax-Head midpoint, for
        drawing only) and `(F, 17)` visibility (0 for Neck/Nose).
    """
    idx = np.array(SH_TO_17)
    out = poses[:, np.maximum(idx, 0)].copy()
    neck = JOINT_NAMES.index("Neck/Nose")
    out[:, neck] = 0.5 * (poses[:, SH_JOINT_NAMES.index("Thorax")] + poses[:, SH_JOINT_NAMES.index("Head")])
    vis = np.ones(out.shape[:2])
    vis[:, idx < 0] = 0.0
    return out, vis


def _make_sequence(cam3d: np.ndarray, cam: Camera, input: str, read_sh, *, name: str, subject: str, action: str,
                   camera: int, fps: float) -> Sequence:
    visibility = None
    intrinsics = None
    if input == "gt-ortho":
        points_2d, projection = cam3d[..., :2], "orthographic"
    else:
        projection, intrinsics = "perspective", cam.intrinsics
        if input == "gt-persp":
            points_2d = project_perspective(cam3d, intrinsics)
        else:
            poses = read_sh()
            if poses.shape[0] != cam3d.shape[0]:
                raise DataFormatError(f"{name}: Stacked Hourglass has {poses.shape[0]} frames, 3D has "
                                      f"{cam3d.shape[0]}; check the stride")
            points_2d, visibility = sh_to_17(poses)
    return Sequence(points_2d=points_2d, visibility=visibility, points_3d=cam3d, projection=projection,
                    intrinsics=intrinsics, name=name, joint_names=JOINT_NAMES, edges=np.array(EDGES), fps=fps,
                    meta={"dataset": "h36m", "subject": subject, "action": action_of(action), "subaction": action,
                          "camera": str(camera), "input": input})


def load_h36m(root: str | os.PathLike, subjects: tuple[str, ...] | list[str], *, input: str = "gt-ortho",
              actions: tuple[str, ...] | None = None, cameras: tuple[int, ...] = (1, 2, 3, 4), stride: int = 5,
              source_fps: float = 50.0) -> list[Sequence]:
    """Every sub-action and camera of ``subjects`` present under ``root``.

    Subjects absent from ``root`` are skipped (the caller reports which were
    found); when nothing at all matches, a :class:`DataFormatError` lists
    what is there. S11 "Directions" has corrupt detections upstream and is
    skipped for ``input='sh'``, as in 3d-pose-baseline.
    """
    root = Path(root)
    cams = load_cameras(root / "cameras.h5")
    out = []
    for subj in subjects:
        subj = _subject_key(subj)
        for stem in list_actions(root, subj):
            if actions is not None and action_of(stem) not in actions:
                continue
            if input == "sh" and subj == "S11" and action_of(stem) == "Directions":
                continue
            for c in cameras:
                out.append(load_h36m_sequence(root, subj, stem, c, input=input, stride=stride,
                                              source_fps=source_fps, cameras=cams))
    if not out:
        present = sorted(p.name for p in root.iterdir() if p.is_dir() and list_actions(root, p.name))
        wanted = f"subjects {list(subjects)}" + (f", actions {list(actions)}" if actions is not None else "")
        raise DataFormatError(f"{root}: expected Human3.6M files of {wanted}, found none; subjects present: "
                              f"{present}" + ("" if cameras else "; no cameras asked for"))
    return out


def load_videopose3d(path_3d: str | os.PathLike, cameras: str | os.PathLike | dict, *,
                     path_2d: str | os.PathLike | None = None, subjects: tuple[str, ...] | None = None,
                     input: str = "gt-ortho", stride: int = 5, source_fps: float = 50.0) -> list[Sequence]:
    """Human3.6M from the VideoPose3D npz files.

    Args:
        path_3d: ``data_3d_h36m.npz`` (``positions_3d``: subject -> action ->
            `(F, 32, 3)` world metres).
        cameras: ``cameras.h5`` of 3d-pose-baseline, or the dict of
            :func:`load_cameras` (the npz files carry no extrinsics).
        path_2d: ``data_2d_h36m_<kind>.npz`` (``positions_2d``: subject ->
            action -> list of 4 `(F, 17, 2)` pixel arrays); needed for
            ``input='sh'`` (any detector), where all 17 joints are visible.
        input: ``'gt-ortho'``, ``'gt-persp'`` or ``'sh'`` (the 2D of ``path_2d``).

    These files hold pickled Python dicts: they are read with
    ``allow_pickle=True``, so load only files you trust.
    """
    if input not in INPUTS:
        raise ValidationError(f"input: expected one of {INPUTS}, got {input!r}")
    cams = cameras if isinstance(cameras, dict) else load_cameras(cameras)
    pos3d = _load_pickled_dict(path_3d, "positions_3d")
    pos2d = _load_pickled_dict(path_2d, "positions_2d") if input == "sh" else None
    if input == "sh" and pos2d is None:
        raise ValidationError("path_2d: expected the data_2d_h36m_<kind>.npz file for input='sh', got None")
    out = []
    for subj in sorted(pos3d):
        if subjects is not None and subj not in subjects:
            continue
        for action in sorted(pos3d[subj]):
            world = np.asarray(pos3d[subj][action], dtype=np.float64)
            if world.ndim != 3 or world.shape[1:] != (32, 3):
                raise DataFormatError(f"{path_3d}: positions_3d[{subj}][{action}]: expected (F, 32, 3), got "
                                      f"{world.shape}")
            world = world[::stride][:, JOINTS_32_TO_17] * 1000.0  # (F, 17, 3) mm
            for c in (1, 2, 3, 4):
                if (subj, c) not in cams:
                    raise DataFormatError(f"cameras: expected subject{subj[1:]}/camera{c}, not present")
                cam = cams[(subj, c)]
                cam3d = cam.world_to_camera(world)

                def read_2d(subj=subj, action=action, c=c):
                    kp = np.asarray(pos2d[subj][action][c - 1], dtype=np.float64)[::stride]
                    if kp.ndim != 3 or kp.shape[1:] != (17, 2):
                        raise DataFormatError(f"{path_2d}: positions_2d[{subj}][{action}][{c - 1}]: expected "
                                              f"(F, 17, 2), got {kp.shape}")
                    return kp

                seq = _make_sequence(cam3d, cam, "gt-persp" if input == "sh" else input, None,
                                     name=f"{subj}/{action}/cam{c}", subject=subj, action=action, camera=c,
                                     fps=source_fps / stride)
                if input == "sh":
                    kp = read_2d()
                    n = min(kp.shape[0], cam3d.shape[0])  # VideoPose3D trims detections to the 3D length
                    seq = seq.select_frames(slice(0, n)).replace(points_2d=kp[:n],
                                                                 meta={**seq.meta, "input": "sh"})
                out.append(seq)
    return out


def _load_pickled_dict(path, key: str) -> dict:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=True) as data:
            if key not in data.files:
                raise DataFormatError(f"{path}: expected an array '{key}' (VideoPose3D layout), got {data.files}")
            return data[key].item()
    except DataFormatError:
        raise
    except Exception as exc:
        raise DataFormatError(f"{path}: expected a VideoPose3D .npz file, could not read it ({exc})") from None


def detect_stride(root: str | os.PathLike, subject: str) -> int:
    """The frame stride that brings the copy under ``root`` to PRN's 10 fps: 5 for the public 50 fps files, 1
    for a copy that already holds every 5th frame; judged from the joints' root-relative motion per frame of
    ``subject``'s Walking (camera 1)."""
    seqs = load_h36m(root, [subject], actions=("Walking",), cameras=(1,), stride=1)
    if not seqs:
        return 5
    x = seqs[0].points_3d - seqs[0].points_3d[:, :1]
    return 1 if float(np.median(np.linalg.norm(np.diff(x, axis=0), axis=2))) > 12.0 else 5
