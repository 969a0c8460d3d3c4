"""300-VW face videos (68 landmarks) and their 3D landmarks.

Expected layout under the data folder (``root`` or ``$NRSFM_DATA``):

- ``300vw/NNN/annot/*.pts``: the public 300-VW release, one file per frame (``version: 1``, ``n_points: 68``,
  then the points between braces, one ``x y`` per line, 1-based pixels, y down).
- ``300vw-3d/NNN/*``: the 3D landmarks of the same videos (the re-annotation of Bulat & Tzimiropoulos, "How far
  are we from solving the 2D & 3D face alignment problem?", ICCV 2017), one file per frame, sorted by name:
  ``.pts`` with ``x y z`` per line, ``.npy`` `(68, 3)`, or ``.mat`` holding ``pts_3d``, ``pt3d_68`` or ``pt3d``
  (`(68, 3)` or `(3, 68)`). x and y are the image coordinates of the 2D annotation; z is depth.

:func:`load_300vw` reads one video, :func:`load_300vw_set` every video that has both. With the 3D present, the
2D input is the landmarks' xy (orthographic, the PRN paper's Table 3 input) and ``points_3d`` the landmarks
centred per frame.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from nrsfm.datasets.paths import find_dataset
from nrsfm.datasets.synthetic import FACE_EDGES
from nrsfm.errors import DataFormatError
from nrsfm.sequence import Sequence

N_LANDMARKS = 68
_EXTENSIONS_3D = (".pts", ".npy", ".mat")


def read_pts(path: str | os.PathLike, dims: int = 2) -> np.ndarray:
    """One ``.pts`` landmark file: `(n_points, dims)` floats."""
    text = Path(path).read_text()
    m = re.search(r"\{(.*)\}", text, re.S)
    n = re.search(r"n_points\s*:\s*(\d+)", text)
    if m is None or n is None:
        raise DataFormatError(f"{path}: expected a .pts file ('n_points: N' and the points between braces)")
    try:
        rows = [[float(v) for v in line.split()] for line in m.group(1).strip().splitlines() if line.strip()]
    except ValueError:
        raise DataFormatError(f"{path}: expected numbers between the braces") from None
    pts = np.array(rows, dtype=np.float64) if rows else np.zeros((0, dims))
    if pts.shape != (int(n.group(1)), dims):
        raise DataFormatError(f"{path}: expected {n.group(1)} points of {dims} coordinates, got shape {pts.shape}")
    return pts


def _read_3d(path: Path) -> np.ndarray:
    if path.suffix == ".pts":
        return read_pts(path, 3)
    if path.suffix == ".npy":
        x = np.load(path)
    else:
        from scipy.io import loadmat

        mat = loadmat(path)
        key = next((k for k in ("pts_3d", "pt3d_68", "pt3d") if k in mat), None)
        if key is None:
            raise DataFormatError(f"{path}: expected a variable pts_3d, pt3d_68 or pt3d, found "
                                  f"{sorted(k for k in mat if not k.startswith('__'))}")
        x = mat[key]
    x = np.asarray(x, dtype=np.float64)
    if x.shape == (3, N_LANDMARKS):
        x = x.T
    if x.shape != (N_LANDMARKS, 3):
        raise DataFormatError(f"{path}: expected ({N_LANDMARKS}, 3) landmarks, got shape {x.shape}")
    return x


def _frames(folder: Path, suffixes: tuple[str, ...]) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix in suffixes)


def _frame_number(path: Path, index: int) -> int:
    """The 1-based frame number in a file's name (``000123.pts`` -> 123), else its position + 1."""
    digits = re.findall(r"\d+", path.stem)
    return int(digits[-1]) if digits else index + 1


def load_300vw(video: str, root: str | os.PathLike | None = None, *, require_3d: bool = True) -> Sequence:
    """One 300-VW video ``NNN``: its 3D landmarks (``300vw-3d/NNN``) as the ground truth and their xy as the
    2D input; without 3D (``require_3d=False``) the 2D annotations of ``300vw/NNN/annot``."""
    base = Path(root) if root is not None else None
    folder_3d = None
    d3 = find_dataset("300vw-3d", base, required=require_3d)
    if d3 is not None and (d3 / video).is_dir():
        folder_3d = d3 / video
    elif require_3d:
        raise DataFormatError(f"300-VW video {video}: expected its 3D landmarks in {d3 / video}")
    meta = {"dataset": "300vw", "video": video}
    if folder_3d is not None:
        files = _frames(folder_3d, _EXTENSIONS_3D)
        if not files:
            raise DataFormatError(f"{folder_3d}: expected one {'/'.join(_EXTENSIONS_3D)} file per frame, found none")
        x3 = np.stack([_read_3d(f) for f in files])
        x3 = x3 - x3.mean(axis=1, keepdims=True)
        return Sequence(points_2d=x3[..., :2].copy(), points_3d=x3, name=f"300vw-{video}",
                        edges=np.array(FACE_EDGES), fps=30.0, meta={**meta, "input": "3d-xy"})
    folder = find_dataset("300vw", base) / video / "annot"
    if not folder.is_dir():
        raise DataFormatError(f"300-VW video {video}: expected the annotation folder {folder}")
    files = _frames(folder, (".pts",))
    if not files:
        raise DataFormatError(f"{folder}: expected one .pts file per frame, found none")
    return Sequence(points_2d=np.stack([read_pts(f) for f in files]), name=f"300vw-{video}",
                    edges=np.array(FACE_EDGES), fps=30.0, meta={**meta, "input": "annot"})


def landmark_frames(video: str, root: str | os.PathLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where the 3D landmarks of ``video`` sit in its frames: `(F,)` 1-based frame numbers (from the files' names,
    else their order) and `(F, 2)` image positions of the landmarks' mean, frame for frame with :func:`load_300vw`."""
    folder = find_dataset("300vw-3d", root) / video
    files = _frames(folder, _EXTENSIONS_3D) if folder.is_dir() else []
    if not files:
        raise DataFormatError(f"300-VW video {video}: expected its 3D landmarks in {folder}")
    centres = np.stack([_read_3d(f)[:, :2].mean(axis=0) for f in files])
    return np.array([_frame_number(f, i) for i, f in enumerate(files)]), centres


def list_300vw(root: str | os.PathLike | None = None) -> list[str]:
    """The videos with 3D landmarks, sorted by number."""
    d3 = find_dataset("300vw-3d", root)
    return sorted((p.name for p in d3.iterdir() if p.is_dir()), key=lambda v: (len(v), v))


def split_300vw(videos: list[str], n_train: int = 32, n_test: int = 32) -> tuple[list[str], list[str]]:
    """A fixed train/test split of the videos: alternate videos in numeric order (even positions train, odd
    test), at most ``n_train`` and ``n_test`` (the PRN paper's 32 and 32; it does not list its videos)."""
    return videos[0::2][:n_train], videos[1::2][:n_test]
