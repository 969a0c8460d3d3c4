"""Rotations from a rank-3K factorisation by rank-3 PSD rectification, and the EM-PND start built on them.

This is the initialisation of Lee, Cho and Oh's EM-PND2 (PAMI 2016), a modification of the camera recovery of
Gotardo & Martinez (CVPR 2011):

1. Each frame of the centred tracks is scaled to unit norm and the `(2F, P)` matrix (rows ``x_f, y_f``
   interleaved) is factorised by SVD; ``K`` columns ``U`` of its left factor are kept, ``K`` the smallest
   multiple of 3 holding all but ``1 - energy`` of its energy.
2. A `(K, K)` PSD matrix ``GG`` of rank at most 3 and unit trace is sought with
   ``a_f^T GG a_f = b_f^T GG b_f`` and ``a_f^T GG b_f = 0`` for every frame (``a_f, b_f`` the rows of ``U``):
   the camera rows ``[a_f; b_f] G`` are then orthogonal with equal norms. The residual of those constraints is
   minimised by accelerated projected gradient for ``K = 3`` and projected gradient with a rank-3 projection for
   ``K = 6, 9, ...`` (each started from the previous ``G``), stopping at the first ``K`` that satisfies them.
3. Each frame's rotation is the polar factor of its two rows, its scale ``2 / (sigma_1 + sigma_2)``.
4. Reflections: a frame whose lifted 2D shape points away from the mean is flipped, until none changes.
5. Depths: the per-frame depths that minimise the trace of the sample covariance of the lifted shapes, in
   closed form.

The result starts :func:`nrsfm.solvers.empnd.solve_empnd` (``init="factorisation"``).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
from scipy.linalg.lapack import dsyevr

from nrsfm.errors import SolverError

_EPS = float(np.finfo(np.float64).eps)


class OrthonormalityConstraints:
    """The per-frame orthonormality constraints on ``GG`` for a `(2F, K)` factor ``u`` (rows ``a_f, b_f``).

    The constraint residual of a symmetric `(K, K)` ``GG`` is the `(2F,)` vector
    ``A(GG) = [a_f^T GG a_f - b_f^T GG b_f ; 2 a_f^T GG b_f]``, linear in ``GG``: ``E vec(GG)`` for a `(2F, K^2)`
    matrix ``E``. The solvers below only need its squared norm and gradient, i.e. products with ``H = E^T E``, scaled
    to unit operator norm (``lipschitz`` is the scale removed). The iterations number in the tens of thousands, so
    each product is one matrix-vector product: with ``H`` itself `(K^2, K^2)` when ``K^2 <= 4F``, else as
    ``E^T (E x)``.
    """

    def __init__(self, u: np.ndarray) -> None:
        a, b = u[0::2], u[1::2]  # (F, K) each
        k = u.shape[1]
        diff = (a[:, :, None] * a[:, None, :] - b[:, :, None] * b[:, None, :]).reshape(-1, k * k)
        cross = a[:, :, None] * b[:, None, :]
        cross = (cross + cross.transpose(0, 2, 1)).reshape(-1, k * k)
        self._gram = self._factor = None
        if k * k <= 4 * diff.shape[0]:  # the cheaper product: K^4 against 2 (2F) K^2
            self._gram = diff.T @ diff + cross.T @ cross
            self.lipschitz = float(scipy.linalg.eigh(self._gram, eigvals_only=True,
                                                     subset_by_index=[k * k - 1] * 2)[0])
        else:
            self._factor = np.concatenate([diff, cross])  # (2F, K^2)
            self.lipschitz = float(np.linalg.norm(self._factor, 2)) ** 2
        if self.lipschitz <= 0:
            raise SolverError("factorisation start: the orthonormality constraints vanish (degenerate tracks)")
        if self._factor is None:
            self._gram /= self.lipschitz
        else:
            self._factor /= np.sqrt(self.lipschitz)

    def cost(self, gg: np.ndarray) -> tuple[float, np.ndarray]:
        """Scaled squared residual of `(K, K)` ``gg`` and its half-gradient `(K, K)`."""
        if self._factor is None:
            grad = (self._gram @ gg.ravel()).reshape(gg.shape)
        else:
            grad = (self._factor.T @ (self._factor @ gg.ravel())).reshape(gg.shape)
        return float((grad * gg).sum()), grad


def project_unit_trace_psd(m: np.ndarray, rank: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Nearest (Frobenius) PSD matrix of unit trace and at most ``rank`` nonzero eigenvalues to symmetric ``m``.

    Returns ``GG`` `(K, K)` and its factor ``G`` `(K, r)` with ``GG = G G^T``.
    """
    m = (m + m.T) / 2
    k = m.shape[0]
    if rank is not None and rank < k:
        # the top ``rank`` eigenpairs by LAPACK's dsyevr, the routine scipy.linalg.eigh(m, subset_by_index=...) calls
        # (the same numbers), without its argument checks, which cost twice the decomposition at these sizes
        if not np.isfinite(m).all():
            raise SolverError("factorisation start: the rectification diverged (non-finite values)")
        ev, vec, _, _, info = dsyevr(m, compute_v=1, range="I", lower=1, il=k - rank + 1, iu=k)
        if info:
            raise SolverError(f"factorisation start: the eigendecomposition failed (LAPACK dsyevr info {info})")
        ev = ev[:rank]
    else:
        ev, vec = np.linalg.eigh(m)
    order = np.argsort(ev)[::-1]
    ev, vec = ev[order], vec[:, order]
    gaps = np.cumsum(ev) - ev * np.arange(1, ev.size + 1)  # projection of the eigenvalues onto the simplex
    n = int((gaps < 1).sum())
    s = np.maximum(ev[:n] - ev[n - 1] + (1 - gaps[n - 1]) / n, 0.0)
    g = vec[:, :n] * np.sqrt(s)
    return g @ g.T, g


def rectify_fista(con: OrthonormalityConstraints, gg: np.ndarray, tol: float = 1e-12,
                  max_iter: int = 100_000) -> tuple[np.ndarray, np.ndarray]:
    """Accelerated projected gradient over unit-trace PSD ``GG`` (no rank limit), from `(K, K)` ``gg``.

    Stops when the majorisation gap ``|GG - T|^2 + c(GG) - |A(T - GG)|^2`` exceeds the cost ``c`` by a relative
    ``tol`` or less (the authors' rule), ``T`` the extrapolated point.
    """
    cost, h_gg = con.cost(gg)
    t, t_gg, h_t = 1.0, gg.copy(), h_gg.copy()  # H applied to the iterate and to the extrapolated point, tracked
    g = None
    bound = np.inf
    for _ in range(max_iter):
        if not (bound / max(cost, 1e-300) - 1 > tol and bound > _EPS):
            break
        p_gg, p_h, p_t = gg, h_gg, t
        gg, g = project_unit_trace_psd(t_gg - h_t)
        cost, h_gg = con.cost(gg)  # the only product with H per iteration
        step = gg - t_gg
        bound = (step**2).sum() + cost - float((step * (h_gg - h_t)).sum())
        t = (1 + np.sqrt(1 + 4 * p_t * p_t)) / 2
        t_gg = gg + (p_t - 1) / t * (gg - p_gg)
        h_t = h_gg + (p_t - 1) / t * (h_gg - p_h)
    if g is None:
        gg, g = project_unit_trace_psd(gg)
    return gg, g


def rectify_rank(con: OrthonormalityConstraints, g: np.ndarray, rank: int = 3, tol: float = 1e-6,
                 floor: float = 0.0, max_iter: int = 50_000) -> tuple[np.ndarray, np.ndarray]:
    """Projected gradient over unit-trace PSD ``GG`` of rank at most ``rank``, from `(K, r)` factor ``g``;
    stops when the cost falls by a relative ``tol`` or less in one step (the authors' rule), when the unscaled squared
    residual is below ``floor`` or after ``max_iter`` steps (a cap the authors do not have: on short noisy tracks
    convergence is sublinear and slow).
    """
    g = g[:, :rank] / np.linalg.norm(g[:, :rank])
    gg = g @ g.T
    cost, grad = con.cost(gg)
    previous = np.inf
    for _ in range(max_iter):
        if not previous / max(cost, 1e-300) - 1 > tol or cost * con.lipschitz < floor:
            break
        previous = cost
        gg, g = project_unit_trace_psd(gg - grad, rank)
        cost, grad = con.cost(gg)
    return gg, g


def factor_rotations(fd: np.ndarray, energy: float = 1 - 1e-5, floor: float = 1e-10
                     ) -> tuple[np.ndarray, np.ndarray, int]:
    """Camera rotations and scales from `(2F, P)` centred tracks (rows ``x_f, y_f`` interleaved).

    ``K`` grows until the squared constraint residual is below ``floor``. The authors use machine epsilon; projected
    gradient converges sublinearly on exact low-rank tracks, so we stop at 1e-10, far below the residual left on real
    tracks. On noisy tracks the residual stays above it and ``K`` grows to its cap (the energy rule); each ``K`` runs
    at most 50,000 steps (:func:`rectify_rank`).

    Returns ``R`` `(F, 3, 3)` (columns: the two camera rows, then their cross product up to sign), relative scales
    `(F,)` (smallest 1) and the ``K`` used.
    """
    u, sv, _ = np.linalg.svd(fd, full_matrices=False)
    if sv.size < 3:
        raise SolverError(f"factorisation start: expected at least 3 points and 2 frames, got a {fd.shape} matrix")
    cum = np.cumsum(sv[:-1] ** 2)
    if cum[-1] <= 0:
        raise SolverError("factorisation start: the tracks have rank < 2; there is no motion to factorise")
    k_max = int((cum / cum[-1] < energy).sum()) + 1
    k_max = max(3, min(int(np.ceil(k_max / 3)) * 3, sv.size))
    g = None
    for k in [*range(3, k_max, 3), k_max]:
        con = OrthonormalityConstraints(u[:, :k])
        if g is None:
            gg, g = rectify_fista(con, np.eye(k) / k)
        else:
            start = np.zeros((k, 3))
            start[: g.shape[0], : g.shape[1]] = g
            gg, g = rectify_rank(con, start, floor=floor)
        if con.cost(gg)[0] * con.lipschitz < floor:
            break
    pad = np.zeros((k, 3))
    pad[:, : g.shape[1]] = g
    rows = (u[:, :k] @ pad).reshape(-1, 2, 3).transpose(0, 2, 1)  # (F, 3, 2)
    uu, sg, vt = np.linalg.svd(np.concatenate([rows, np.zeros((rows.shape[0], 3, 1))], axis=2))
    scale = 2.0 / np.maximum(sg[:, :2].sum(axis=1), 1e-300)
    return uu @ vt, scale / scale.min(), k


def factorisation_start(w: np.ndarray, energy: float = 1 - 1e-5) -> np.ndarray:
    """`(F, P, 3)` camera-frame shapes from `(F, P, 2)` complete tracks: the EM-PND2 start (module docstring).

    Rows x and y are the centred tracks; the depths are the trace-minimising ones.
    """
    n, p, _ = w.shape
    d = w - w.mean(axis=1, keepdims=True)
    unit = np.sqrt(np.mean(d**2) * 3 * p)
    if unit <= 0:
        raise SolverError("factorisation start: every track is constant (no 2D motion to reconstruct)")
    d = d / unit
    norms = np.sqrt((d**2).sum(axis=(1, 2)))
    s = 1.0 / np.where(norms > 0, norms, 1.0)
    fd = d * s[:, None, None]
    rot, rel, _ = factor_rotations(fd.transpose(0, 2, 1).reshape(2 * n, p), energy)
    s = s * rel
    fd = fd * rel[:, None, None]
    y = np.einsum("fij,fpj->fip", rot[:, :, :2], fd)  # (F, 3, P) lifted, zero depth
    flipped = np.zeros(n, bool)
    for _ in range(100):
        turn = np.einsum("fip,ip->f", y, y.mean(axis=0)) < 0
        if not turn.any():
            break
        y[turn] = -y[turn]
        flipped ^= turn
    rot[flipped, :, :2] *= -1
    rot[np.linalg.det(rot) < 0, :, 2] *= -1
    axis = rot[:, :, 2]  # (F, 3) viewing directions
    proj = np.einsum("fi,fip->fp", axis, y - y.mean(axis=0))
    proj -= proj.mean(axis=1, keepdims=True)
    # depths minimising the trace of the sample covariance of y_f + axis_f z_f^T (closed form); singular when every
    # viewing direction is the same (a tiny sequence whose rectification collapsed: 3 x 4 points, K = 2), where the
    # minimum-norm solution leaves that direction's depth at zero
    lhs, rhs = axis.T @ axis - n * np.eye(3), axis.T @ proj
    try:
        coef = np.linalg.solve(lhs, rhs)
    except np.linalg.LinAlgError:
        coef = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    z = axis @ coef - proj  # (F, P)
    y = y + axis[:, :, None] * z[:, None, :]
    return np.einsum("fij,fip->fpj", rot, y) / s[:, None, None] * unit
