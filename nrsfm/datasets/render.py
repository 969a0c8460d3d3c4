"""Images of 3D point sets, for the image-input tables on synthetic data (PRN Table 2, supplementary Table 2).

Every edge of a skeleton (limbs of a body, contours of a face) is drawn as a shaded capsule, a cylinder with
round caps, seen by an orthographic camera looking along +z (smaller z is nearer; the nearest surface wins per
pixel). Each frame is cropped around the bounding box of its projected points and scaled to fill the image, as
the PRN supplementary material crops Human3.6M frames with the ground-truth bounding box. Left and right limbs
get different colours so the image carries the cue a person would use to tell them apart.
"""

from __future__ import annotations

import numpy as np

from nrsfm.errors import ValidationError

#: RGB in [0, 1]: left limbs, right limbs, the rest.
LEFT, RIGHT, CENTRE = (0.85, 0.2, 0.15), (0.15, 0.35, 0.9), (0.75, 0.75, 0.7)


def limb_sides(joint_names, edges) -> list[str]:
    """``"L"``, ``"R"`` or ``"C"`` per edge: left where one end is a left joint (named ``L...``/``left...``) and the
    other left or central, right alike, central otherwise (the spine, and any edge without names)."""

    def side(name: str) -> str:
        n = name.lower()
        if n.startswith("left") or (name[:1] == "L" and name[1:2].isupper()):
            return "L"
        if n.startswith("right") or (name[:1] == "R" and name[1:2].isupper()):
            return "R"
        return "C"

    out = []
    for i, j in np.asarray(edges, int):
        a, b = (side(joint_names[i]), side(joint_names[j])) if joint_names is not None else ("C", "C")
        out.append(a if a == b or b == "C" else b if a == "C" else "C")
    return out


def limb_colours(joint_names: tuple[str, ...] | list[str] | None, edges: np.ndarray) -> np.ndarray:
    """`(E, 3)` colours: left limbs red, right blue, the rest grey (:func:`limb_sides`); without names, edges are
    coloured along a hue wheel by index (faces: jaw, brows, nose, eyes and mouth differ)."""
    edges = np.asarray(edges, int)
    if joint_names is None:
        import matplotlib

        return np.asarray(matplotlib.colormaps["hsv"](np.linspace(0, 0.85, len(edges)))[:, :3])
    palette = {"L": LEFT, "R": RIGHT, "C": CENTRE}
    return np.array([palette[x] for x in limb_sides(joint_names, edges)])


def crop_boxes(points_2d: np.ndarray, margin: float = 0.12) -> tuple[np.ndarray, np.ndarray]:
    """`(F, 2)` box centres and `(F,)` sides of the square crops around `(F, P, 2)` points (NaN ignored), with
    ``margin`` of the side left free on each edge."""
    lo, hi = np.nanmin(points_2d, axis=1), np.nanmax(points_2d, axis=1)
    side = np.max(hi - lo, axis=1) / (1 - 2 * margin)
    return (lo + hi) / 2, np.maximum(side, 1e-9)


def render_capsules(points_3d: np.ndarray, edges: np.ndarray, colours: np.ndarray, *, size: int = 64,
                    radius: float = 0.035, background: float = 0.12, chunk: int = 32) -> np.ndarray:
    """Render `(F, P, 3)` camera-frame points (x right, y down the image, z depth) as capsules.

    Args:
        edges: `(E, 2)` point indices; colours: `(E, 3)` RGB in [0, 1].
        size: image side in pixels; radius: capsule radius as a fraction of the side.
        background: grey level of the background.
        chunk: frames rendered at once (memory ~ chunk * E * size^2 * 40 bytes).

    Returns:
        `(F, size, size, 3)` uint8 images.
    """
    pts = np.asarray(points_3d, float)
    edges = np.asarray(edges, int)
    colours = np.asarray(colours, float)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValidationError(f"render_capsules: expected (F, P, 3) points, got {pts.shape}")
    if edges.ndim != 2 or edges.shape[1] != 2 or not len(edges) or edges.max() >= pts.shape[1] or edges.min() < 0:
        raise ValidationError(f"render_capsules: expected (E, 2) edges indexing {pts.shape[1]} points, got "
                              f"{edges.shape} with indices {edges.min() if edges.size else '-'}.."
                              f"{edges.max() if edges.size else '-'}")
    if colours.shape != (len(edges), 3):
        raise ValidationError(f"render_capsules: expected ({len(edges)}, 3) colours, got {colours.shape}")
    centre, side = crop_boxes(pts[..., :2])
    scale = size / side  # pixels per unit
    grid = np.stack(np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5, indexing="xy"), -1).reshape(-1, 2)
    grid = grid.astype(np.float32)  # single precision: a pixel's position needs no more, and it halves the time
    r = radius * size
    out = np.empty((len(pts), size, size, 3), np.uint8)
    for s in range(0, len(pts), chunk):
        p = pts[s:s + chunk]
        xy = ((p[..., :2] - centre[s:s + chunk, None]) * scale[s:s + chunk, None, None] + size / 2).astype(np.float32)
        z = (p[..., 2] * scale[s:s + chunk, None]).astype(np.float32)  # (f, P, 2), (f, P): pixels
        a, b = xy[:, edges[:, 0]], xy[:, edges[:, 1]]  # (f, E, 2)
        za, zb = z[:, edges[:, 0]], z[:, edges[:, 1]]
        ab = b - a
        den = np.maximum((ab ** 2).sum(-1), 1e-12)[..., None]  # (f, E, 1)
        rel = grid[None, None] - a[:, :, None]  # (f, E, HW, 2)
        t = np.clip((rel * ab[:, :, None]).sum(-1) / den, 0.0, 1.0)  # (f, E, HW)
        d2 = ((rel - t[..., None] * ab[:, :, None]) ** 2).sum(-1)
        inside = d2 < r * r
        h = np.sqrt(np.clip(1 - d2 / (r * r), 0, 1))  # the surface's height over the axis, / r
        depth = np.where(inside, za[..., None] + t * (zb - za)[..., None] - r * h, np.inf)
        k = depth.argmin(axis=1)  # (f, HW): the nearest capsule per pixel
        hit = np.take_along_axis(inside, k[:, None], 1)[:, 0]
        shade = 0.35 + 0.65 * np.take_along_axis(h, k[:, None], 1)[:, 0]
        img = np.where(hit[..., None], colours.astype(np.float32)[k] * shade[..., None], np.float32(background))
        out[s:s + chunk] = np.round(255 * img).astype(np.uint8).reshape(-1, size, size, 3)
    return out


def render_sequence(seq, *, size: int = 64, radius: float | None = None) -> np.ndarray:
    """`(F, size, size, 3)` uint8 images of a :class:`~nrsfm.sequence.Sequence` with camera-frame ``points_3d``
    and ``edges`` (limbs coloured by :func:`limb_colours`; faces, with no joint names, along a hue wheel)."""
    if seq.points_3d is None or seq.edges is None:
        raise ValidationError(f"{seq.name}: rendering needs points_3d (camera frame) and edges; this sequence has "
                              f"{'no points_3d' if seq.points_3d is None else 'no edges'}")
    names = seq.joint_names if seq.joint_names is not None and len(seq.joint_names) == seq.n_points else None
    if radius is None:
        radius = 0.035 if len(seq.edges) < 30 else 0.015
    return render_capsules(seq.points_3d, seq.edges, limb_colours(names, seq.edges), size=size, radius=radius)
