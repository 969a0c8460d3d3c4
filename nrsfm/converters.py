"""Converters from the classic NRSfM layouts to :class:`~nrsfm.sequence.Sequence`.

- Akhter et al. (``W`` 2F x P interleaved, ``S`` 3F x P world frame, ``Rs``
  2F x 3 camera rows): :func:`from_akhter`.
- Lee et al. PND (``X`` 3 x P x F camera frame): :func:`from_pnd`.
- A bare measurement matrix ``W`` (2F x P): :func:`from_measurement_matrix`.
"""

from __future__ import annotations

import numpy as np

from nrsfm.errors import ValidationError, shape_error
from nrsfm.geometry import complete_rotation, nearest_rotation
from nrsfm.sequence import Sequence, as_float_array


def _interleaved_to_frames(mat: np.ndarray, rows: int, field: str) -> np.ndarray:
    """`(rows*F, P)` -> `(F, P, rows)`."""
    mat = as_float_array(field, mat)
    if mat.ndim != 2 or mat.shape[0] % rows:
        raise shape_error(field, f"({rows}F, P)", mat.shape, f"rows {rows}f..{rows}f+{rows - 1} hold frame f")
    n_frames = mat.shape[0] // rows
    return mat.reshape(n_frames, rows, mat.shape[1]).transpose(0, 2, 1)


def from_measurement_matrix(w: np.ndarray, *, name: str = "sequence", **kwargs) -> Sequence:
    """Build a sequence from a `(2F, P)` matrix (rows 2f, 2f+1 = x, y of frame f)."""
    return Sequence(points_2d=_interleaved_to_frames(w, 2, "W"), name=name, **kwargs)


def from_akhter(w: np.ndarray, s: np.ndarray | None = None, rs: np.ndarray | None = None, *,
                name: str = "sequence", scale: float | None = None, edges: np.ndarray | None = None,
                **kwargs) -> Sequence:
    """Convert the Akhter layout, bringing the ground truth into each camera frame.

    Args:
        w: `(2F, P)` orthographic measurements, x and y rows interleaved per frame.
        s: `(3F, P)` world-frame ground truth, rows 3f..3f+2 = X, Y, Z of frame f.
        rs: `(2F, 3)` camera rows with ``W_f = Rs_f S_f``. When absent (dance),
            each frame's rows are fitted to the ground truth by least squares
            and orthonormalised.
        scale: the file's ``scale`` (S and W were divided by it); kept in
            ``meta`` for conversion to millimetres.
        edges: `(E, 2)` **1-based** bone pairs as stored in the file's ``list``.

    Returns:
        A sequence whose ``points_3d[f] = (R_f S_f)^T + t_f`` with ``R_f`` the
        completed rotation (third row by cross product) and ``t_f`` the 2D offset
        between ``W_f`` and ``Rs_f S_f`` (zero depth offset), so that the
        orthographic projection of ``points_3d`` equals ``points_2d``.
        ``camera_rotations`` holds ``R_f``.
    """
    points_2d = _interleaved_to_frames(w, 2, "W")  # (F, P, 2)
    n_frames, n_points, _ = points_2d.shape
    points_3d = rotations = None
    if s is not None:
        world = _interleaved_to_frames(s, 3, "S")  # (F, P, 3)
        if world.shape[:2] != (n_frames, n_points):
            raise shape_error("S", f"(3F, P) = ({3 * n_frames}, {n_points})", np.shape(s),
                              "S must have the same frames and points as W")
        if rs is not None:
            rs = as_float_array("Rs", rs)
            if rs.shape != (2 * n_frames, 3):
                raise shape_error("Rs", f"(2F, 3) = ({2 * n_frames}, 3)", rs.shape)
            rows = rs.reshape(n_frames, 2, 3)
        else:
            rows = _fit_camera_rows(points_2d, world)
        rotations = complete_rotation(rows)  # (F, 3, 3)
        cam = np.einsum("fij,fpj->fpi", rotations, world)  # (F, P, 3)
        offset = (points_2d - cam[..., :2]).mean(axis=1, keepdims=True)  # (F, 1, 2)
        cam[..., :2] += offset
        points_3d = cam
    if edges is not None:
        edges = np.asarray(edges, dtype=np.int64) - 1
    meta = dict(kwargs.pop("meta", {}))
    meta["source_layout"] = "akhter"
    if scale is not None:
        value = as_float_array("scale", scale).ravel()
        if value.size != 1:
            raise shape_error("scale", "one number", value.shape)
        meta["scale"] = repr(float(value[0]))
    return Sequence(points_2d=points_2d, points_3d=points_3d, camera_rotations=rotations, name=name,
                    edges=edges, meta=meta, **kwargs)


def _fit_camera_rows(points_2d: np.ndarray, world: np.ndarray) -> np.ndarray:
    """Least-squares `(F, 2, 3)` orthonormal rows M_f with ``W_f ~ M_f S_f`` (centred)."""
    wc = points_2d - points_2d.mean(axis=1, keepdims=True)  # (F, P, 2)
    sc = world - world.mean(axis=1, keepdims=True)  # (F, P, 3)
    # M_f = Wc_f^T Sc_f (Sc_f^T Sc_f)^-1, solved per frame in one batched call
    gram = np.einsum("fpi,fpj->fij", sc, sc)  # (F, 3, 3)
    cross = np.einsum("fpi,fpj->fij", wc, sc)  # (F, 2, 3)
    m = np.linalg.solve(gram, cross.transpose(0, 2, 1)).transpose(0, 2, 1)
    return nearest_rotation(m, allow_reflection=True)


def from_pnd(x: np.ndarray, *, name: str = "sequence", **kwargs) -> Sequence:
    """Convert the PND layout: ``X`` `(3, P, F)` camera-frame shapes, 2D = ``X[:2]``."""
    x = as_float_array("X", x)
    if x.ndim != 3 or x.shape[0] != 3:
        raise shape_error("X", "(3, P, F)", x.shape, "the PND layout stores x, y, z along the first axis")
    points_3d = x.transpose(2, 1, 0)  # (F, P, 3)
    meta = dict(kwargs.pop("meta", {}))
    meta["source_layout"] = "pnd"
    return Sequence(points_2d=points_3d[..., :2], points_3d=points_3d, name=name, meta=meta, **kwargs)


def to_pnd(seq: Sequence) -> np.ndarray:
    """The `(3, P, F)` PND array of a sequence's ground truth."""
    if seq.points_3d is None:
        raise ValidationError(f"{seq.name}: expected ground truth (points_3d) for the PND layout, got none")
    return seq.points_3d.transpose(2, 1, 0).copy()
