"""CSF2: column space fitting with complementary rank-3 spaces (Gotardo & Martinez, CVPR 2011).

Model (orthographic, centred tracks): ``W = D (C kron I3) S`` with ``D`` `(2F, 3F)`
the block-diagonal camera rows, ``C = Omega_d X`` `(F, K)` shape coefficients on
the first ``d`` DCT vectors (smooth trajectories), and ``S`` `(3K, P)` the basis
shapes.

1. Cameras: the rank-3K factor ``Pi`` `(2F, 3K)` of W; a `(3K, 3)` corrective
   triple ``G`` makes every frame's block of ``Pi G`` two orthogonal rows of
   equal norm (scaled orthographic: ``Pi G = [c_f1 R_f]``). It is found by
   Levenberg-Marquardt on the scale-invariant orthonormality residual from
   several starts; the rows are then normalised and completed (cross product).
2. Shape: with D fixed, the coefficients ``X`` `(d, K)` and the basis ``S``
   minimise ``||W - D (Omega X kron I3) S||^2`` by alternating exact least
   squares (each sub-problem is linear), X orthonormalised (QR) after every
   step as in the authors' code; stop when the relative drop of the RMSE is
   below ``tol``. A small ridge on S (``ridge`` times the mean diagonal of the
   normal matrix) keeps the depth of the basis bounded when slowly turning
   cameras leave it weakly determined.

Missing points (the occlusion-aware variant): the residual counts visible
entries only; the factorisation in step 1 runs on a low-rank imputation of W.

Automatic K and d (``K=0``/``d=0``): K = the smallest k in [2, 8] whose first
3k singular values of W hold 99.5% of its energy; d = round(0.1 F) clamped to
[K + 1, 60] (the authors' demos use d of 0.1-0.3 F and K = 2-3 for smooth
sequences).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nrsfm.errors import SolverError, ValidationError
from nrsfm.geometry import complete_rotation
from nrsfm.sequence import Sequence
from nrsfm.solvers.base import Reconstruction, impute_lowrank, register, require_visible_points


@dataclass(frozen=True)
class CSF2Params:
    """Parameters of :func:`solve_csf2` (``K = 0`` / ``d = 0``: automatic, see the module docstring)."""

    K: int = 0
    d: int = 0
    max_iter: int = 300
    tol: float = 1e-6
    starts: int = 8
    seed: int = 0
    ridge: float = 1e-4

    def __post_init__(self) -> None:
        if self.ridge < 0:
            raise ValidationError(f"ridge: expected >= 0, got {self.ridge}")
        if self.K < 0 or self.d < 0 or self.max_iter < 1 or self.starts < 1:
            raise ValidationError(f"CSF2Params: expected K, d >= 0, max_iter, starts >= 1, got K={self.K}, "
                                  f"d={self.d}, max_iter={self.max_iter}, starts={self.starts}")


def dct_basis(n_frames: int, d: int) -> np.ndarray:
    """`(F, d)` orthonormal DCT-II basis (first column constant)."""
    t = np.arange(n_frames)
    k = np.arange(d)
    basis = np.cos(np.pi * (2 * t[:, None] + 1) * k[None] / (2 * n_frames))
    basis[:, 0] *= 1 / np.sqrt(2)
    return basis * np.sqrt(2 / n_frames)


def auto_rank(w: np.ndarray, energy: float = 0.995, k_min: int = 2, k_max: int = 8) -> int:
    s = np.linalg.svd(w, compute_uv=False) ** 2
    cum = np.cumsum(s) / s.sum()
    for k in range(k_min, k_max + 1):
        if cum[min(3 * k, len(cum)) - 1] >= energy:
            return k
    return k_max


def refine_triple(pi: np.ndarray, g0: np.ndarray) -> tuple[np.ndarray, float]:
    """Levenberg-Marquardt on the scale-invariant orthonormality residual of ``pi @ G``.

    Args:
        pi: `(F, 2, 3K)` rank-3K factor; g0: `(3K, 3)` start.

    Returns:
        The refined `(3K, 3)` triple and the final cost (0 for exact data).
    """
    import scipy.optimize

    r = pi.shape[2]

    def residual(g_flat: np.ndarray) -> np.ndarray:
        m = pi @ g_flat.reshape(r, 3)  # (F, 2, 3)
        a, b = m[:, 0], m[:, 1]
        na, nb = (a * a).sum(1), (b * b).sum(1)
        den = na + nb + 1e-300
        return np.concatenate([(na - nb) / den, 2 * (a * b).sum(1) / den])

    res = scipy.optimize.least_squares(residual, g0.ravel(), method="lm", max_nfev=2000, xtol=1e-12, ftol=1e-12)
    return res.x.reshape(r, 3), float(res.cost)


def recover_cameras(pi: np.ndarray, starts: int, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """`(F, 3, 3)` rotations from the rank-3K factor ``pi`` `(F, 2, 3K)` (multi-start
    :func:`refine_triple`), and the final residual."""
    r = pi.shape[2]
    best_g, best_cost = None, np.inf
    for s in range(starts):
        g0 = np.eye(r, 3) if s == 0 else rng.standard_normal((r, 3))  # the leading triple first
        g, cost = refine_triple(pi, g0)
        if cost < best_cost:
            best_g, best_cost = g, cost
    m = pi @ best_g
    scale = np.linalg.norm(m, axis=2, keepdims=True).mean(axis=1, keepdims=True)  # (F, 1, 1)
    return complete_rotation(m / np.maximum(scale, 1e-300)), best_cost


@register("csf2", CSF2Params, "column space fitting with complementary rank-3 spaces and DCT trajectories "
                              "(Gotardo & Martinez, CVPR 2011); occlusion-aware", handles_missing=True)
def solve_csf2(seq: Sequence, params: CSF2Params) -> Reconstruction:
    """CSF2 on an orthographic sequence (missing points allowed). See the module docstring."""

    if seq.projection != "orthographic":
        raise SolverError(f"csf2: expected orthographic tracks, got {seq.projection}")
    n_frames, n_points = seq.n_frames, seq.n_points
    vis = seq.weights > 0  # (F, P)
    require_visible_points(seq, "csf2")
    w = seq.measurement_matrix()  # (2F, P)
    mask = np.repeat(vis, 2, axis=0)  # (2F, P)
    k = params.K or auto_rank(impute_lowrank(w, mask, 9) if not vis.all() else w - w.mean(1, keepdims=True))
    d = params.d or int(np.clip(round(0.1 * n_frames), k + 1, 60))
    if 3 * k > min(2 * n_frames, n_points):
        raise SolverError(f"csf2: K = {k} needs 3K <= min(2F, P) = {min(2 * n_frames, n_points)}; pass a smaller "
                          "K (--set K=...)")
    d = min(d, n_frames)
    full = impute_lowrank(w, mask, 3 * k) if not vis.all() else w
    t = full.mean(axis=1, keepdims=True)  # (2F, 1) translations
    wc = full - t
    u, s, vt = np.linalg.svd(wc, full_matrices=False)
    pi = (u[:, :3 * k] * np.sqrt(s[:3 * k])).reshape(n_frames, 2, 3 * k)
    rng = np.random.default_rng(params.seed)
    rot, cam_residual = recover_cameras(pi, params.starts, rng)
    r2 = rot[:, :2]  # (F, 2, 3)
    omega = dct_basis(n_frames, d)  # (F, d)
    x = np.eye(d, k)
    wmask = mask.reshape(n_frames, 2, n_points).astype(np.float64)  # (F, 2, P)
    target = (w - t).reshape(n_frames, 2, n_points)  # visible entries matter
    basis = np.zeros((k, 3, n_points))
    prev = np.inf
    it = 0
    converged = False
    for it in range(1, params.max_iter + 1):
        c = omega @ x  # (F, K)
        # S-step: for each point p, min sum_f ||w_fp - R_f sum_k c_fk S_kp||^2 over visible entries
        a = np.einsum("fk,fij->fikj", c, r2).reshape(n_frames * 2, 3 * k)  # (2F, 3K) rows of M
        basis = _masked_lstsq(a, (target * wmask).reshape(2 * n_frames, n_points), wmask.reshape(2 * n_frames, -1),
                              params.ridge)
        basis = basis.reshape(k, 3, n_points)
        # X-step: w_f = sum_k c_fk R_f S_k = A_f c_f,  c_f = Omega_f X
        af = np.einsum("fij,kjp->fipk", r2, basis)  # (F, 2, P, K)
        af = af * wmask[..., None]
        ata = np.einsum("fipk,fipl->fkl", af, af)  # (F, K, K)
        atb = np.einsum("fipk,fip->fk", af, target * wmask)  # (F, K)
        lhs = np.einsum("fa,fb,fkl->akbl", omega, omega, ata).reshape(d * k, d * k)
        rhs = np.einsum("fa,fk->ak", omega, atb).reshape(d * k)
        x = np.linalg.solve(lhs + 1e-10 * np.trace(lhs) / (d * k) * np.eye(d * k), rhs).reshape(d, k)
        q, rr = np.linalg.qr(x)
        x = q  # re-orthonormalise; the scale moves into S at the next S-step
        resid = np.einsum("fk,fij,kjp->fip", omega @ x, r2, _rescale(basis, rr)) - target
        rmse = np.sqrt((resid**2 * wmask).sum() / wmask.sum())
        if prev - rmse < params.tol * max(prev, 1e-300) and it > 5:
            converged = True
            break
        prev = rmse
    c = omega @ x
    a = np.einsum("fk,fij->fikj", c, r2).reshape(n_frames * 2, 3 * k)
    basis = _masked_lstsq(a, (target * wmask).reshape(2 * n_frames, n_points),
                          wmask.reshape(2 * n_frames, -1), params.ridge).reshape(k, 3, n_points)
    shapes_obj = np.einsum("fk,kjp->fpj", c, basis)  # (F, P, 3) object frame
    points = np.einsum("fij,fpj->fpi", rot, shapes_obj)
    points -= points.mean(axis=1, keepdims=True)
    return Reconstruction(points_3d=points, rotations=rot, method="csf2", iterations=it, converged=converged,
                          info={"K": k, "d": d, "rmse": float(rmse), "camera_residual": cam_residual})


def _rescale(basis: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Basis shapes consistent with X -> X R^-1 (so that C S is unchanged)."""
    return np.einsum("kl,ljp->kjp", r, basis)


def _masked_lstsq(a: np.ndarray, b: np.ndarray, m: np.ndarray, ridge: float = 1e-10) -> np.ndarray:
    """Per column p: argmin_s ||m_p * (a s - b_p)||^2 + ridge' ||s||^2 for `(R, C)` a, `(R, P)` b and mask m,
    with ``ridge' = ridge * mean diagonal of a^T a``. Returns `(C, P)`."""
    if np.all(m > 0):
        ata = a.T @ a
        return np.linalg.solve(ata + ridge * np.trace(ata) / a.shape[1] * np.eye(a.shape[1]), a.T @ b)
    ata = np.einsum("ri,rj,rp->pij", a, a, m)  # (P, C, C)
    atb = np.einsum("ri,rp->pi", a, b * m)  # (P, C)
    ridge = ridge * np.trace(ata, axis1=1, axis2=2)[:, None, None] / a.shape[1] * np.eye(a.shape[1])
    return np.linalg.solve(ata + ridge, atb[..., None])[..., 0].T
