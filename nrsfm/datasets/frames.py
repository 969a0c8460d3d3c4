"""Video frames of the image-input tables (PRN Table 2, supplementary Table 2), read lazily and cropped.

Expected layouts (frames extracted from the videos as numbered JPEG or PNG files, 1-based, e.g. with
``ffmpeg -i VIDEO %06d.jpg``)::

    <root>/h36m/images/S9/Walking 1.54138969/000001.jpg   Human3.6M: <sub-action>.<camera id>/, frames at the
                                                          videos' 50 fps (the poses' stride picks every 5th)
    <root>/300vw/001/frames/000001.jpg                    300-VW: <video>/frames/, one per annotated frame

Human3.6M frames are cropped with the ground-truth bounding box of the projected joints (a square around it,
12% margin), 300-VW frames with a square centred on the mean of the landmarks (the paper's supplementary
material), and resized to ``size`` x ``size``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from nrsfm.errors import DataFormatError, ValidationError

EXTENSIONS = (".jpg", ".jpeg", ".png")


class FrameImages:
    """`(F, size, size, 3)` uint8 crops of image files, decoded on indexing (an image source of :mod:`prn.images`).

    Args:
        paths: one image file per frame.
        centres: `(F, 2)` crop centres in pixels; sides: `(F,)` square crop sides in pixels.
        size: output side.
    """

    def __init__(self, paths: list[Path], centres: np.ndarray, sides: np.ndarray, size: int = 224) -> None:
        centres, sides = np.asarray(centres, float), np.asarray(sides, float)
        if centres.shape != (len(paths), 2) or sides.shape != (len(paths),):
            raise ValidationError(f"FrameImages: expected ({len(paths)}, 2) centres and ({len(paths)},) sides, got "
                                  f"{centres.shape} and {sides.shape}")
        self.paths, self.centres, self.sides, self.size = list(paths), centres, sides, int(size)
        self.shape = (len(self.paths), self.size, self.size, 3)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, idx) -> np.ndarray:
        from PIL import Image

        idx = np.atleast_1d(np.asarray(idx, int))
        out = np.empty((len(idx), self.size, self.size, 3), np.uint8)
        for k, i in enumerate(idx):
            (cx, cy), half = self.centres[i], self.sides[i] / 2
            with Image.open(self.paths[i]) as im:
                crop = im.convert("RGB").crop((round(cx - half), round(cy - half), round(cx + half), round(cy + half)))
                out[k] = np.asarray(crop.resize((self.size, self.size), Image.BILINEAR))
        return out


def numbered_frames(folder: str | os.PathLike, numbers: np.ndarray) -> list[Path]:
    """The files ``<folder>/<n:06d>.<ext>`` of 1-based frame ``numbers``; a clear error names the first missing."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataFormatError(f"{folder}: expected a folder of extracted frames (000001.jpg, ...), not found")
    ext = next((e for e in EXTENSIONS if (folder / f"{int(numbers[0]):06d}{e}").exists()), None)
    if ext is None:
        raise DataFormatError(f"{folder}: expected frame {int(numbers[0]):06d} as one of {EXTENSIONS}, not found")
    paths = [folder / f"{int(n):06d}{ext}" for n in numbers]
    missing = [p for p in (paths[0], paths[-1]) if not p.exists()]
    if missing:
        raise DataFormatError(f"{missing[0]}: expected {len(paths)} frames in {folder}, this one is missing")
    return paths


def h36m_frames(root: str | os.PathLike, seq, *, stride: int = 5, size: int = 224, margin: float = 0.12,
                cameras: dict | None = None) -> FrameImages:
    """The frames of a Human3.6M :class:`~nrsfm.sequence.Sequence` (:func:`nrsfm.datasets.h36m.load_h36m`):
    ``<root>/images/<subject>/<sub-action>.<camera id>/``, frame ``1 + stride * i`` for pose ``i``, cropped
    around the joints' perspective projection."""
    from nrsfm.datasets.h36m import CAMERA_IDS, load_cameras
    from nrsfm.datasets.render import crop_boxes
    from nrsfm.geometry import project_perspective

    meta = seq.meta
    if meta.get("dataset") != "h36m" or seq.points_3d is None:
        raise ValidationError(f"{seq.name}: expected a Human3.6M sequence with points_3d (load_h36m)")
    root = Path(root)
    cams = cameras if cameras is not None else load_cameras(root / "cameras.h5")
    cam = cams[(meta["subject"], int(meta["camera"]))]
    pixels = project_perspective(seq.points_3d, cam.intrinsics)
    centres, sides = crop_boxes(pixels, margin)
    folder = root / "images" / meta["subject"] / f"{meta['subaction']}.{CAMERA_IDS[int(meta['camera']) - 1]}"
    return FrameImages(numbered_frames(folder, 1 + stride * np.arange(seq.n_frames)), centres, sides, size)


def vw300_frames(root: str | os.PathLike | None, video: str, seq, *, size: int = 224,
                 scale: float = 1.3) -> FrameImages:
    """The frames of 300-VW ``video`` (:func:`nrsfm.datasets.faces.load_300vw` read from the data folder ``root``):
    ``<root>/300vw/<video>/frames/``, one per annotated frame, cropped on a square centred on the landmarks' mean,
    ``scale`` times their extent."""
    from nrsfm.datasets.faces import landmark_frames
    from nrsfm.datasets.paths import find_dataset

    numbers, centres = landmark_frames(video, root)
    if len(numbers) != seq.n_frames:
        raise ValidationError(f"{seq.name}: {seq.n_frames} frames, but video {video} has {len(numbers)} annotated")
    xy = seq.points_2d
    sides = np.maximum(scale * np.max(np.nanmax(xy, axis=1) - np.nanmin(xy, axis=1), axis=1), 1.0)
    folder = find_dataset("300vw", root) / video / "frames"
    return FrameImages(numbered_frames(folder, numbers), centres, sides, size)
