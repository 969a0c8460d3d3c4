"""The paper's comparison figures, as PNG files written by the tables' ``--plots``.

- :func:`qualitative`: for chosen test frames, the 2D input, then each method's 3D and the ground truth from the
  front and from the side (the XY and YZ planes, as the paper's figures), every panel of a frame at one scale,
  left limbs red and right limbs blue.
- :func:`per_action_bars`: one group of bars per action, one bar per method, the paper's values as markers.
- :func:`training_curves`: the training loss of every learned row against the iteration (log scale).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

LEFT, RIGHT, CENTRE = "tab:red", "tab:blue", "0.3"


def pyplot():
    """matplotlib.pyplot on the Agg backend (files only)."""
    from nrsfm.plotting import _pyplot

    return _pyplot()


def save(fig, path: Path) -> None:
    """Write ``fig`` to ``path`` (PNG, replacing an earlier run's figure) atomically and close it."""
    from nrsfm.plotting import _save

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    _save(fig, path, overwrite=True)


def limb_colours(edges, joint_names=None) -> list[str]:
    """A matplotlib colour per edge: red for left limbs, blue for right, grey otherwise
    (:func:`nrsfm.datasets.render.limb_sides`)."""
    from nrsfm.datasets.render import limb_sides

    palette = {"L": LEFT, "R": RIGHT, "C": CENTRE}
    return [palette[x] for x in limb_sides(joint_names, edges)]


def qualitative(path: Path, inputs_2d: np.ndarray, shapes: dict[str, np.ndarray], edges, joint_names=None, *,
                title: str = "", images: np.ndarray | None = None) -> None:
    """Rows: test frames; columns: the 2D input (or the input image, ``images`` `(n, H, W, 3)` uint8), then for
    every entry of ``shapes`` (name -> `(n, P, 3)`, the ground truth among them, last by convention; millimetres,
    camera frame, x right, y down, z away) its front view (x, y) and its side view (z, y), as the paper's figures
    show the XY and YZ planes. Every panel of a row has the same scale and is filled by the largest shape of the
    row. Without ``edges`` the points are drawn as dots, coloured by depth."""
    plt = pyplot()
    n = len(inputs_2d)
    names = list(shapes)
    edges = [] if edges is None else [tuple(e) for e in edges]
    colours = limb_colours(edges, joint_names)
    dots = not edges  # a point cloud (dense surfaces): points instead of limbs
    cols = 1 + 2 * len(names)
    fig, axes = plt.subplots(n, cols, figsize=(1.6 * cols, 1.9 * n), squeeze=False)

    def draw(ax, u, v, depth):
        for (a, b), c in zip(edges, colours):
            ax.plot(u[[a, b]], v[[a, b]], color=c, lw=1.3)
        if dots:
            ax.scatter(u, v, s=1, c=depth, cmap="viridis")
        elif len(u) > 30:  # many points (faces): the landmarks too
            ax.scatter(u, v, s=0.8, c=CENTRE)

    for r in range(n):
        ax = axes[r, 0]
        if images is not None:
            ax.imshow(images[r])
        else:
            x = inputs_2d[r] - np.nanmean(inputs_2d[r], axis=0)
            draw(ax, x[:, 0], x[:, 1], np.zeros(len(x)))
            half = np.nanmax(np.abs(x)) * 1.08
            ax.set_xlim(-half, half)
            ax.set_ylim(half, -half)  # y down, as in the image
            ax.set_aspect("equal")
        if r == 0:
            ax.set_title("input image" if images is not None else "2D input", fontsize=7)
        frame = np.stack([shapes[k][r] - shapes[k][r].mean(axis=0) for k in names])  # (M, P, 3)
        half = np.abs(frame).max() * 1.08  # one scale for every panel of this frame
        for j, name in enumerate(names):
            s = frame[j]
            for k, (u, label) in enumerate(((s[:, 0], "front"), (s[:, 2], "side"))):
                ax = axes[r, 1 + 2 * j + k]
                draw(ax, u, s[:, 1], s[:, 2])
                ax.set_xlim(-half, half)
                ax.set_ylim(half, -half)
                ax.set_aspect("equal")
                if r == 0:
                    ax.set_title(f"{name}\n{label}" if k == 0 else label, fontsize=7)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
        for spine in ax.spines.values():
            spine.set_linewidth(0.4)
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout(pad=0.3, w_pad=0.2, h_pad=0.4)
    save(fig, path)


def per_action_bars(path: Path, results: dict[str, dict[str, float]], actions: list[str],
                    paper: dict[str, dict[str, float]] | None = None, *, ylabel: str = "MPJPE (mm)",
                    title: str = "") -> None:
    """``results``: method -> action -> error (``actions`` in order, "Avg" last if wanted); ``paper`` the same
    for the published values, drawn as black markers over the bars."""
    plt = pyplot()
    names = list(results)
    x = np.arange(len(actions))
    w = 0.8 / max(len(names), 1)
    fig, ax = plt.subplots(figsize=(max(6, 0.75 * len(actions) * max(1, len(names) / 3)), 3.6))
    for i, name in enumerate(names):
        pos = x - 0.4 + w * (i + 0.5)
        ax.bar(pos, [results[name].get(a, np.nan) for a in actions], w, label=name)
        if paper and name in paper:
            ax.plot(pos, [paper[name].get(a, np.nan) for a in actions], "k_", markersize=max(3, 40 * w), mew=1.5,
                    label="paper" if i == 0 else None)
    ax.set_xticks(x, actions, fontsize=7, rotation=30, ha="right")
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=9)
    ax.legend(fontsize=6, ncol=min(4, len(names) + 1))
    fig.tight_layout()
    save(fig, path)


def training_curves(path: Path, caches: dict[str, Path], *, title: str = "") -> int:
    """The loss of every row whose cache folder holds a ``train.json`` with a history (PRN's total loss; the
    supervised rows' 3D loss; C3DPO's reprojection plus canonicalisation). Returns the number of curves drawn."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    drawn = 0
    for name, folder in caches.items():
        f = Path(folder) / "train.json"
        if not f.exists():
            continue
        hist = json.loads(f.read_text()).get("history", [])
        if len(hist) < 2:
            continue
        it = [h["iteration"] for h in hist]
        loss = [h["loss"] if "loss" in h else h.get("reprojection", np.nan) + h.get("canonicalisation", 0.0)
                for h in hist]
        ax.plot(it, loss, label=name, lw=1)
        drawn += 1
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("training loss")
    if title:
        ax.set_title(title, fontsize=9)
    if drawn:
        ax.legend(fontsize=6)
    else:
        ax.text(0.5, 0.5, "no row logged two or more iterations", ha="center", transform=ax.transAxes)
    fig.tight_layout()
    save(fig, path)
    return drawn


def shapes_for_frames(predictions: dict[str, list[np.ndarray]], truth: list, frames) -> dict[str, np.ndarray]:
    """De-normalised, centred predictions of each method at ``frames`` (:func:`pick_frames`), each mirrored in
    depth where that is closer to the ground truth (as the metrics choose the sign), and the ground truth last."""
    from benchmarks.registry import millimetres

    out = {}
    for name, preds in predictions.items():
        rows = []
        mm = millimetres(preds, truth)
        for i, t in frames:
            gt = truth[i].points_3d[t] - truth[i].points_3d[t].mean(axis=0)
            p = mm[i][t]
            p = p - p.mean(axis=0)
            m = p * np.array([1.0, 1.0, -1.0])
            rows.append(m if np.linalg.norm(m - gt) < np.linalg.norm(p - gt) else p)
        out[name] = np.stack(rows)
    out["ground truth"] = np.stack([truth[i].points_3d[t] for i, t in frames])
    return out


def pick_frames(truth: list, n: int = 4) -> list[tuple[int, int]]:
    """``n`` (sequence, frame) pairs spread evenly over the test frames (each sequence's middle frame where there
    are at least ``n`` sequences)."""
    if len(truth) >= n:
        idx = np.linspace(0, len(truth) - 1, n).round().astype(int)
        return [(int(i), truth[i].n_frames // 2) for i in idx]
    flat = [(i, t) for i, s in enumerate(truth) for t in range(s.n_frames)]
    picks = np.linspace(0, len(flat) - 1, n + 2)[1:-1].round().astype(int)
    return [flat[k] for k in picks]
