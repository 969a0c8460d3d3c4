"""Headless plots: input / reconstruction / ground truth side by side, and error curves.

Uses matplotlib's Agg backend; every function writes a PNG (atomically) and
returns its path.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from nrsfm.errors import ValidationError, shape_error
from nrsfm.geometry import nearest_rotation
from nrsfm.io import atomic_write
from nrsfm.sequence import Sequence


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _align_for_display(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Rotate/reflect ``pred`` `(F, P, 3)` onto ``gt`` with the global e3D alignment, for drawing."""
    a = (pred - pred.mean(axis=1, keepdims=True)).reshape(-1, 3)
    b = (gt - gt.mean(axis=1, keepdims=True)).reshape(-1, 3)
    q_ls = np.linalg.lstsq(a, b, rcond=None)[0].T
    return (pred - pred.mean(axis=1, keepdims=True)) @ nearest_rotation(q_ls, allow_reflection=True).T


def _draw(ax, pts: np.ndarray, edges: np.ndarray | None, *, three_d: bool, colour: str,
          vis: np.ndarray | None = None) -> None:
    """Points `(P, 2 or 3)` and their ``edges`` `(E, 2)` (pairs of point indices; one line collection) on ``ax``."""
    from matplotlib.collections import LineCollection
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    shown = np.ones(len(pts), bool) if vis is None else vis > 0
    if three_d:
        # draw with y pointing up (camera y points down)
        x, y, z = pts[:, 0], pts[:, 2], -pts[:, 1]
        ax.scatter(x[shown], y[shown], z[shown], s=6, c=colour)
        if edges is not None and len(edges):
            ends = np.stack([x, y, z], axis=1)[edges]  # (E, 2, 3)
            ax.add_collection3d(Line3DCollection(ends, colors=colour, linewidths=1))
        mid = np.array([x.mean(), y.mean(), z.mean()])
        half = 0.5 * max(np.ptp(x), np.ptp(y), np.ptp(z), 1e-9)
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(mid[2] - half, mid[2] + half)
    else:
        x, y = pts[:, 0], -pts[:, 1]
        ax.scatter(x[shown], y[shown], s=6, c=colour)
        ax.scatter(x[~shown], y[~shown], s=10, c="red", marker="x")
        if edges is not None and len(edges):
            pairs = edges[shown[edges[:, 0]] & shown[edges[:, 1]]]
            ax.add_collection(LineCollection(np.stack([x, y], axis=1)[pairs], colors=colour, linewidths=1))
        ax.set_aspect("equal", adjustable="datalim")


def plot_reconstruction(seq: Sequence, points_3d: np.ndarray | None, path: str | os.PathLike, *,
                        frames: list[int] | None = None, title: str | None = None, overwrite: bool = True) -> Path:
    """2D input, reconstruction and ground truth side by side for chosen frames.

    Args:
        seq: the input sequence (2D, visibility, optional ground truth, edges).
        points_3d: `(F, P, 3)` reconstruction in the camera frame, or None.
        frames: frame indices (default: 4 evenly spaced frames).

    Returns:
        The written PNG path. Missing 2D points are drawn as red crosses; the
        reconstruction is globally rotated onto the ground truth for display.
    """
    if points_3d is not None:
        points_3d = np.asarray(points_3d, dtype=np.float64)
        if points_3d.shape != (seq.n_frames, seq.n_points, 3):
            raise shape_error("points_3d", f"(F, P, 3) = ({seq.n_frames}, {seq.n_points}, 3) like the sequence",
                              points_3d.shape)
    if frames is None:
        frames = sorted(set(np.linspace(0, seq.n_frames - 1, min(4, seq.n_frames)).astype(int).tolist()))
    bad = [f for f in frames if not -seq.n_frames <= f < seq.n_frames]
    if not frames or bad:
        raise ValidationError(f"frames: expected indices in [0, {seq.n_frames - 1}], got {list(frames)}")
    plt = _pyplot()
    cols = ["2D input"]
    rec = None
    if points_3d is not None:
        rec = points_3d
        if seq.points_3d is not None:
            rec = _align_for_display(points_3d, seq.points_3d)
        cols.append("reconstruction")
    if seq.points_3d is not None:
        cols.append("ground truth")
    fig = plt.figure(figsize=(3.2 * len(cols), 3.0 * len(frames)))
    for r, f in enumerate(frames):
        ax = fig.add_subplot(len(frames), len(cols), r * len(cols) + 1)
        _draw(ax, seq.points_2d[f], seq.edges, three_d=False, colour="tab:blue",
              vis=None if seq.visibility is None else seq.visibility[f])
        ax.set_title(f"frame {f}: {cols[0]}", fontsize=8)
        c = 2
        for label, data, colour in (("reconstruction", rec, "tab:orange"), ("ground truth", seq.points_3d, "k")):
            if data is None:
                continue
            ax = fig.add_subplot(len(frames), len(cols), r * len(cols) + c, projection="3d")
            _draw(ax, data[f] - data[f].mean(axis=0), seq.edges, three_d=True, colour=colour)
            ax.set_title(label, fontsize=8)
            for axis in (ax.xaxis, ax.yaxis, ax.zaxis):  # arbitrary units; their ticks cost most of the drawing
                axis.set_ticks([])
            c += 1
    fig.suptitle(title or seq.name, fontsize=10)
    return _save(fig, path, overwrite)


def plot_error_curve(curves: dict[str, np.ndarray], path: str | os.PathLike, *, ylabel: str = "error",
                     title: str = "", overwrite: bool = True) -> Path:
    """Per-frame error curves, one line per entry of ``curves`` (`(F,)` arrays)."""
    if not curves:
        raise ValidationError("curves: expected at least one named curve, got none")
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 3))
    for label, values in curves.items():
        ax.plot(np.asarray(values), label=f"{label} (mean {np.mean(values):.4g})", lw=1)
    ax.set_xlabel("frame")
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7)
    return _save(fig, path, overwrite)


def _save(fig, path: str | os.PathLike, overwrite: bool) -> Path:
    """Write ``fig`` as PNG atomically (never replacing a file unless ``overwrite``) and close it."""
    plt = _pyplot()
    fig.tight_layout()
    path = Path(path)
    try:
        with atomic_write(path, overwrite=overwrite) as tmp:
            fig.savefig(tmp, dpi=90, format="png")
    finally:
        plt.close(fig)
    return path
