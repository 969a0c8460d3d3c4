"""Rigid factorisation (Tomasi-Kanade) with metric upgrade: the rank-3 baseline.

Model: the centred measurement matrix ``W`` `(2F, P)` is ``M S`` with ``M``
`(2F, 3)` stacked (scaled) orthographic camera rows and ``S`` `(3, P)` one
rigid shape. The affine factors from the SVD are upgraded by ``Q`` with
``L = Q Q^T`` fitted to the camera constraints (unit, orthogonal rows for
orthographic data; equal-norm, orthogonal rows for weak perspective).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nrsfm.errors import SolverError, ValidationError
from nrsfm.geometry import complete_rotation
from nrsfm.sequence import Sequence
from nrsfm.reconstruction import Reconstruction
from nrsfm.solvers.registry import register


@dataclass(frozen=True)
class Rank3Params:
    """Parameters of :func:`solve_rank3`.

    Attributes:
        min_eigenvalue: relative floor for the eigenvalues of ``L = Q Q^T``
            when noise makes it indefinite.
    """

    min_eigenvalue: float = 1e-9

    def __post_init__(self) -> None:
        if not 0 < self.min_eigenvalue < 1:
            raise ValidationError(f"min_eigenvalue: expected a value in (0, 1), got {self.min_eigenvalue}")


def _sym_coeffs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rows `(N, 6)` with ``row @ l = a L b^T`` for symmetric L, l = (L00, L01, L02, L11, L12, L22)."""
    return np.stack([a[:, 0] * b[:, 0], a[:, 0] * b[:, 1] + a[:, 1] * b[:, 0], a[:, 0] * b[:, 2] + a[:, 2] * b[:, 0],
                     a[:, 1] * b[:, 1], a[:, 1] * b[:, 2] + a[:, 2] * b[:, 1], a[:, 2] * b[:, 2]], axis=1)


def metric_upgrade(m: np.ndarray, *, scaled: bool = False, min_eigenvalue: float = 1e-9) -> np.ndarray:
    """The `(3, 3)` corrective matrix Q for affine camera rows ``m`` `(F, 2, 3)`.

    Solves the linear least-squares problem for ``L = Q Q^T`` from
    ``a L a^T = b L b^T = 1, a L b^T = 0`` (``scaled=False``) or
    ``a L a^T - b L b^T = 0, a L b^T = 0`` with mean row norm 1 (``scaled=True``).
    """
    a, b = m[:, 0], m[:, 1]
    caa, cbb, cab = _sym_coeffs(a, a), _sym_coeffs(b, b), _sym_coeffs(a, b)
    if scaled:
        n = len(a)
        lhs = np.concatenate([caa - cbb, cab, (caa + cbb).mean(axis=0, keepdims=True) * n])
        rhs = np.concatenate([np.zeros(2 * n), [2.0 * n]])
    else:
        lhs = np.concatenate([caa, cbb, cab])
        rhs = np.concatenate([np.ones(2 * len(a)), np.zeros(len(a))])
    l6 = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    l_mat = np.array([[l6[0], l6[1], l6[2]], [l6[1], l6[3], l6[4]], [l6[2], l6[4], l6[5]]])
    w, v = np.linalg.eigh(l_mat)
    if w.max() <= 0:
        raise SolverError("rank3: the metric upgrade failed (no positive-definite solution); the input may not "
                          "come from an orthographic camera")
    w = np.maximum(w, min_eigenvalue * w.max())
    return v * np.sqrt(w)


@register("rank3", Rank3Params, "rigid rank-3 factorisation with metric upgrade (Tomasi-Kanade)",
          handles_perspective=True)
def solve_rank3(seq: Sequence, params: Rank3Params) -> Reconstruction:
    """Rigid factorisation of a complete sequence.

    Args:
        seq: `(F, P, 2)` tracks, complete. Perspective data is treated as weak
            perspective on intrinsics-normalised coordinates.

    Returns:
        A reconstruction with one rigid shape seen by per-frame rotations;
        ``points_3d[f] = (R_f S)^T`` (centred).
    """
    p2 = seq.points_2d
    scaled = seq.projection == "perspective"
    if scaled and seq.intrinsics is not None:
        k = np.broadcast_to(seq.intrinsics, (seq.n_frames, 3, 3))
        p2 = (p2 - k[:, None, :2, 2]) / k[:, None, [0, 1], [0, 1]]
    pc = p2 - p2.mean(axis=1, keepdims=True)  # (F, P, 2)
    w = pc.transpose(0, 2, 1).reshape(2 * seq.n_frames, seq.n_points)  # (2F, P)
    if seq.n_points < 3:
        raise SolverError(f"rank3: expected at least 3 points, got {seq.n_points}")
    u, s, vt = np.linalg.svd(w, full_matrices=False)
    if s[0] <= 0:
        raise SolverError(f"rank3: all points coincide in '{seq.name}'; nothing to reconstruct")
    r = 3
    sq = np.sqrt(s[:r])
    m = (u[:, :r] * sq).reshape(seq.n_frames, 2, r)  # (F, 2, 3)
    shape = sq[:, None] * vt[:r]  # (3, P)
    q = metric_upgrade(m, scaled=scaled, min_eigenvalue=params.min_eigenvalue)
    m = m @ q
    shape = np.linalg.solve(q, shape)  # (3, P)
    scales = np.linalg.norm(m, axis=2).mean(axis=1)  # (F,)
    rot = complete_rotation(m / scales[:, None, None])  # (F, 3, 3)
    points = np.einsum("fij,jp->fpi", rot, shape)  # (F, P, 3)
    residual = np.linalg.norm(np.einsum("fij,jp->fip", m, shape).reshape(w.shape) - w) / max(np.linalg.norm(w), 1e-300)
    return Reconstruction(points_3d=points, rotations=rot, method="rank3", iterations=1, converged=True,
                          info={"relative_residual": float(residual), "singular_values": s[:4].tolist()})
