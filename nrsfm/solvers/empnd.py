"""EM-PND: NRSfM with a Procrustean normal distribution fitted by EM (Lee, Cho & Oh, CVPR 2013; the PND2 form
of TPAMI 2016, ``NRSfM_PND2.m``).

Model (orthographic). Shapes live in translation-free coordinates: ``X_f`` `(3, P-1)` is the camera-frame shape
times an orthonormal basis ``H`` `(P, P-1)` of the complement of the all-ones vector. Each shape, rotated and
scaled onto the mean shape ``M`` `(3, P-1)` (``||M|| = 1``) by its own Procrustes alignment,

    Y_f = s_f R_f X_f,   (R_f, s_f) = argmax tr(R X_f M^T),  <Y_f, M> = 1,

follows a Gaussian that is *degenerate along the alignment*: zero mean and precision ``Lambda = Q C^-1 Q^T``
where ``Q`` `(3(P-1), 3(P-1) - 4)` spans the complement of ``M`` and its three infinitesimal rotations
``e_k x M`` (the directions the alignment removes) and ``C`` is a *full* covariance: no number of bases K. The
observed rows are ``x, y`` of ``X_f`` (visible points only; each frame's translation is eliminated with the
visible points' centroid) plus Gaussian noise ``sigma^2``.

EM (per iteration):

* E-step: each frame's posterior over all of ``X_f`` is Gaussian with precision ``K_f^T Lambda K_f + W_f /
  sigma^2`` (``K_f = s_f R_f kron I``, ``W_f`` the projector onto the observed rows); mean and covariance by one
  batched Cholesky factorisation (:class:`DensePosterior`), or by a Woodbury form when every point is visible
  (:class:`CompletePosterior`, the same result).
* ``sigma^2`` in closed form; like the authors we let it fall by at most a factor ``var_drop`` per iteration.
* M-step: ``C = Q^T A Q`` with ``A = mean_f K_f E[X_f X_f^T] K_f^T``, and the profiled cost ``J(M) = 1/2 log
  det(Q^T A Q) - (3(P-1) - 4) mean_f log s_f`` (``R_f, s_f, Q, A`` all depend on ``M``) gets one line-searched
  gradient step on the unit sphere. ``log det(Q^T A Q) = log det(Pi A Pi + N N^T)`` with ``N`` the four
  constrained directions, so no basis of ``Q`` is differentiated; the gradient is torch autograd of that closed
  form (the authors derive it by hand), the step an Armijo backtracking search (theirs: strong Wolfe).
* Stop when the per-dimension cost falls by less than ``tol`` (the authors' ``1e-2``) or after ``max_iter``
  iterations (their 1000).

Where we differ from the authors' code, and why:

* Start (``init="auto"``). With complete tracks, the authors' own start
  (:func:`nrsfm.solvers.rectify.factorisation_start`), aligned by generalised Procrustes. It can fail on
  noise-free sequences whose camera turns steadily about one axis, so on noise-free tracks
  (:func:`exactly_low_rank`) EM first runs ``PROBE_ITER_EXACT`` iterations from it and from CSF2's
  reconstruction and goes on from the lower PND cost. With missing points the start is CSF2's occlusion-aware
  reconstruction cut to ``init_rounds`` camera rounds (the authors instead fill the gaps by nuclear-norm
  completion first). ``init="rigid"`` (the rank-3 factorisation) is the fallback for sequences too small for CSF2.
* The alignment uses proper rotations only (``det R = +1``); the authors' ``svd``-based update may return a
  reflection.

Cost: ``O(F (3P)^3)`` per iteration with missing points, ``O(F P^3)`` with complete tracks. All of it is batched
tensor algebra in float64, on a GPU when torch sees one (``device``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from nrsfm.device import pick_device
from nrsfm.errors import SolverError, ValidationError
from nrsfm.procrustes import proper_procrustes, skew
from nrsfm.progress import report
from nrsfm.sequence import Sequence
from nrsfm.reconstruction import Reconstruction
from nrsfm.solvers.rank3 import Rank3Params, solve_rank3
from nrsfm.solvers.rectify import factorisation_start
from nrsfm.solvers.registry import register, require_visible_points, solve
from nrsfm.solvers.starts import csf2_start, fits_csf2

_DT = torch.float64


INITS = ("auto", "factorisation", "csf2", "rigid", "spm", "pr")


@dataclass(frozen=True)
class EMPNDParams:
    """Parameters of :func:`solve_empnd` (the authors' defaults where they have one).

    Attributes:
        max_iter: EM iterations (authors: 1000).
        tol: stop when the cost per shape dimension falls by less than this in one iteration (authors: 1e-2).
        var_init: starting noise variance in normalised units (shapes of norm ~1; the authors' 1e-4); 0 takes the
            start's reprojection error.
        var_drop: the noise variance falls by at most this factor per iteration (authors: 2).
        c_init: ridge on the starting shape covariance (authors: 1e-4).
        init: the start. ``"factorisation"``: the authors' own (rank-3 rectification of a rank-3K factorisation,
            trace-minimising depths; :mod:`nrsfm.solvers.rectify`), complete tracks only. ``"csf2"``: CSF2's
            reconstruction (its occlusion-aware form when points are missing). ``"rigid"``: the rank-3
            factorisation. ``"spm"``, ``"pr"``: that solver's reconstruction with its defaults (``"spm"``: complete
            tracks only). ``"auto"`` (default): with every point visible, the factorisation start (and, with
            ``probe_iter > 0``, also CSF2's: EM runs ``probe_iter`` iterations from each and goes on from the one
            with the lower PND cost); with missing points, CSF2.
        init_K: CSF2's K for the ``"csf2"`` start (0: CSF2's rank rule).
        init_rounds: camera rounds of that start when points are missing, one run of 5 X/S iterations per round
            (CSF2's own defaults: 200 rounds, two runs of 20 and 5): EM needs only a rough start.
        probe_iter: iterations of each start before ``"auto"`` picks one (0: factorisation only; ``max_iter``: both
            run to convergence, the lower final cost wins, at twice the time). -1 (default): ``PROBE_ITER_EXACT``
            when the tracks are noise-free (:func:`exactly_low_rank`), else 0.
        fast: use :class:`CompletePosterior` when every point is visible (the same result, faster); False forces
            :class:`DensePosterior`.
        device: where EM's tensor algebra runs (:func:`nrsfm.device.pick_device`): ``"auto"`` (default) a CUDA GPU
            when torch sees one, else the CPU; ``"cpu"``, ``"cuda"``, ``"cuda:N"``. The start (CSF2, the
            factorisation) runs on the CPU either way.
    """

    max_iter: int = 1000
    tol: float = 1e-2
    var_init: float = 1e-4
    var_drop: float = 2.0
    c_init: float = 1e-4
    init: str = "auto"
    init_K: int = 0
    init_rounds: int = 50
    probe_iter: int = -1
    fast: bool = True
    device: str = "auto"

    def __post_init__(self) -> None:
        if self.init not in INITS:
            raise ValidationError(f"init: expected one of {', '.join(INITS)}, got {self.init!r}")
        if self.probe_iter < -1:
            raise ValidationError(f"probe_iter: expected >= 0, or -1 for the automatic rule, got {self.probe_iter}")
        if self.init_rounds < 0:
            raise ValidationError(f"init_rounds: expected >= 0, got {self.init_rounds}")
        if self.max_iter < 1 or self.tol < 0 or self.var_init < 0 or self.var_drop < 1 or self.c_init <= 0:
            raise ValidationError("EMPNDParams: expected max_iter >= 1, tol >= 0, var_init >= 0, var_drop >= 1, "
                                  f"c_init > 0, got {self.max_iter}, {self.tol}, {self.var_init}, {self.var_drop}, "
                                  f"{self.c_init}")
        pick_device(self.device)  # a device this machine lacks is refused here, before any work


def centring_basis(n_points: int) -> np.ndarray:
    """`(P, P-1)` orthonormal basis of the vectors orthogonal to the all-ones vector."""
    q, _ = np.linalg.qr(np.ones((n_points, 1)), mode="complete")
    return q[:, 1:]


def constrained_directions(mean: torch.Tensor) -> torch.Tensor:
    """`(3q, 4)` orthonormal basis of ``M`` and its infinitesimal rotations ``[e_k]_x M`` for `(3, q)` ``M``."""
    rotated = skew(torch.eye(3, dtype=mean.dtype, device=mean.device)) @ mean  # (3, 3, q)
    basis, _ = torch.linalg.qr(torch.cat([mean.reshape(1, -1), rotated.reshape(3, -1)]).T)
    return basis


def align(shapes: torch.Tensor, mean: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Scaled Procrustes alignment of `(F, 3, q)` shapes onto `(3, q)` ``mean`` with proper rotations.

    Returns ``sR`` `(F, 3, 3)` and ``s`` `(F,)` with ``<sR_f X_f, M> = 1``.
    """
    rot = proper_procrustes(mean, shapes)
    s = 1.0 / ((rot @ shapes) * mean).sum(dim=(1, 2))
    return s[:, None, None] * rot, s


def _pair_weights(a: torch.Tensor) -> torch.Tensor:
    """`(F, 9, 9)` ``T[f, (j, l), (m, o)] = a[f, j, m] a[f, l, o]`` for `(F, 3, 3)` ``a``."""
    n = a.shape[0]
    return (a[:, :, None, :, None] * a[:, None, :, None, :]).reshape(n, 9, 9)


# the 3x3 blocks (m, o), m <= o, of a symmetric (3q, 3q) matrix: all that the rotated sums below need of it
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_UPPER_COLS = [3 * m + o for m, o in _UPPER]  # their columns (m, o) in _pair_weights
_UPPER_HALF = [0.5 if m == o else 1.0 for m, o in _UPPER]  # the diagonal blocks count once in C_jl + C_lj^T


def _upper_blocks(mats: torch.Tensor, q: int) -> torch.Tensor:
    """`(F, 3q, 3q)` symmetric matrices as `(F*6, q*q)`: their blocks (m, o) with m <= o, `[f, (m, o) | a, b]`."""
    b = mats.reshape(-1, 3, q, 3, q)
    return torch.stack([b[:, m, :, o, :] for m, o in _UPPER], dim=1).reshape(-1, q * q)


def _upper_gram_blocks(factor: torch.Tensor, q: int) -> torch.Tensor:
    """:func:`_upper_blocks` of ``factor_f^T factor_f`` for `(F, k, 3q)` ``factor``, computing those blocks only."""
    n = factor.shape[0]
    rows = [(factor[:, :, m * q:(m + 1) * q].transpose(1, 2) @ factor[:, :, m * q:])  # (F, q, (3-m) q)
            .reshape(n, q, 3 - m, q).transpose(1, 2) for m in range(3)]
    return torch.cat(rows, dim=1).reshape(-1, q * q)


def _rotated_block_sum(rot: torch.Tensor, blocks: torch.Tensor, q: int) -> torch.Tensor:
    """``sum_f (rot_f kron I_q) B_f (rot_f kron I_q)^T`` `(3q, 3q)` for `(F, 3, 3)` ``rot`` and symmetric ``B_f``
    given by :func:`_upper_blocks`. Block (j, l) of the sum is ``C_jl + C_lj^T`` with ``C_jl = sum_{m<o}
    rot_jm rot_lo B_mo + 1/2 sum_m rot_jm rot_lm B_mm``: one `(9, 6F) x (6F, q^2)` product."""
    weights = _pair_weights(rot)[:, :, _UPPER_COLS] * rot.new_tensor(_UPPER_HALF)  # (F, 9 [j, l], 6 [m <= o])
    c = _as_matrix(weights.permute(1, 0, 2).reshape(9, -1) @ blocks, q)
    return c + c.T


def _as_matrix(jl_blocks: torch.Tensor, q: int) -> torch.Tensor:
    """`(9 [j, l], q*q [a, b])` -> the `(3q, 3q)` matrix with rows (j, a), columns (l, b)."""
    return jl_blocks.reshape(3, 3, q, q).permute(0, 2, 1, 3).reshape(3 * q, 3 * q)


class DensePosterior:
    """E-step for any visibility: one Cholesky factorisation of the `(3q, 3q)` posterior precision per frame.

    ``mu`` `(F, 3, q)` posterior means (camera frame); ``trace`` = sum_f tr(W_f Cov_f);
    :meth:`moment` gives ``A = mean_f K'_f E[X_f X_f^T] K'_f^T`` for any alignment ``sR'`` `(F, 3, 3)`.
    """

    def __init__(self, lam: torch.Tensor, sr: torch.Tensor, data: torch.Tensor, obs: torch.Tensor, var: float) -> None:
        n, _, q = data.shape
        dim = 3 * q
        lam_blocks = lam.reshape(3, q, 3, q).permute(0, 2, 1, 3).reshape(9, q * q)
        prec = (_pair_weights(sr.transpose(1, 2)).reshape(n * 9, 9) @ lam_blocks)
        prec = prec.reshape(n, 3, 3, q, q).permute(0, 1, 3, 2, 4).contiguous()  # (F, 3, q, 3, q)
        prec[:, 0, :, 0, :] += obs / var
        prec[:, 1, :, 1, :] += obs / var
        chol, info = torch.linalg.cholesky_ex(prec.reshape(n, dim, dim))
        _check_factorisation(info)
        cov = torch.cholesky_inverse(chol)
        self.mu = (cov @ data.reshape(n, dim, 1)).reshape(n, 3, q) / var
        c5 = cov.reshape(n, 3, q, 3, q)
        self.trace = float((obs * c5[:, 0, :, 0, :]).sum() + (obs * c5[:, 1, :, 1, :]).sum())
        self._blocks = _upper_blocks(cov, q)
        self._q = q

    def moment(self, sr: torch.Tensor) -> torch.Tensor:
        n, q = sr.shape[0], self._q
        y = (sr @ self.mu).reshape(n, 3 * q)
        return (_rotated_block_sum(sr, self._blocks, q) + y.T @ y) / n


class CompletePosterior:
    """E-step when every point is visible in every frame; the same result as :class:`DensePosterior`.

    In frame f's aligned coordinates the posterior precision is ``Lambda + c_f (I - u_f u_f^T) kron I_q``
    (``c_f = 1 / (s_f^2 var)``, ``u_f`` the viewing direction), i.e. ``(Lambda + c_f I)`` minus a rank-q term:
    Woodbury in the eigenbasis of ``Lambda`` leaves one `(q, q)` factorisation per frame; the second moments are kept
    as ``V diag(g_f) V^T`` (one weight vector per frame) plus a rank-(q+1) part stored as `(3, 3)` blocks, so
    :meth:`moment` is a few matrix products, with `O(q * 3q)` memory beyond the blocks.
    """

    def __init__(self, lam: torch.Tensor, sr: torch.Tensor, s: torch.Tensor, data: torch.Tensor, var: float) -> None:
        n, _, q = data.shape
        dim = 3 * q
        evals, v = torch.linalg.eigh(lam)
        evals = evals.clamp(min=0.0)
        rot = sr / s[:, None, None]  # (F, 3, 3) camera -> aligned
        c = 1.0 / (s**2 * var)  # (F,)
        v3 = v.reshape(3, q, dim)
        phi_t = (rot[:, :, 2] @ v3.reshape(3, q * dim)).reshape(n, q, dim)  # (u_f kron I_q)^T V
        g = 1.0 / (evals[None] + c[:, None])  # (F, dim)
        h = evals[None] * g / c[:, None]  # 1/c - g without cancellation
        m = (phi_t * h[:, None, :]) @ phi_t.transpose(1, 2)  # (F, q, q) = I/c - Phi^T G Phi
        chol, info = torch.linalg.cholesky_ex(m)
        _check_factorisation(info)
        psi_t = phi_t * g[:, None, :]  # (F, q, dim) = (G Phi)^T in the eigenbasis
        beta = ((rot @ data) / (s[:, None, None] * var)).reshape(n, dim) @ v  # V^T K^-T d / var
        w = torch.cholesky_solve(psi_t @ beta[..., None], chol)
        y_v = g * beta + (psi_t.transpose(1, 2) @ w)[..., 0]
        y = y_v @ v.T  # (F, dim) aligned posterior means
        self.mu = (rot.transpose(1, 2) @ y.reshape(n, 3, q)) / s[:, None, None]
        # tr(W_f Cov_f) = (tr Inner^-1 - tr U^T Inner^-1 U) / s^2, with tr Inner^-1 = sum g + |L^-1 Psi^T|^2 and
        # U^T Inner^-1 U = S + S M^-1 S where S = Psi^T Phi = I/c - M (Phi has orthonormal columns), so
        # tr Inner^-1 - tr U^T Inner^-1 U = sum g + |L^-1 Psi^T|^2 + q/c - tr(M^-1)/c^2
        z = torch.linalg.solve_triangular(chol, psi_t, upper=False)  # (F, q, dim) = L^-1 Psi^T
        eye_q = torch.eye(q, dtype=_DT, device=chol.device).expand(n, q, q)
        tr_m_inv = (torch.linalg.solve_triangular(chol, eye_q, upper=False) ** 2).sum(dim=(1, 2))
        per_frame = g.sum(dim=1) + (z**2).sum(dim=(1, 2)) + q / c - tr_m_inv / c**2
        self.trace = float((per_frame / s**2).sum())
        # aligned-frame second moments: K (Cov_f + mu mu^T) K^T = V diag(g_f) V^T + Xi Xi^T, Xi = [V Psi L^-T, y_f]
        z = z @ v.T  # (F, q, dim)
        xi = torch.cat([z, y[:, None, :]], dim=1)  # (F, q+1, dim), aligned frame
        # Xi Xi^T per frame as its six blocks m <= o: three batched products now, one (9, 6F) x (6F, q^2) product
        # per cost evaluation (a (3q, F(q+1)) factor product costs 2.3x more per evaluation; all nine blocks, 1.5x
        # the products and memory)
        self._blocks = _upper_gram_blocks(xi, q)
        self._g = g
        self._v3 = v3  # (3 [m], q [a], dim [e])
        self._v_rows = v3.permute(0, 2, 1).reshape(3 * dim, q)  # [(o, e), b]
        self._to_aligned = rot.transpose(1, 2) / s[:, None, None]  # K_f^-1 as (F, 3, 3)
        self._q = q

    def moment(self, sr: torch.Tensor) -> torch.Tensor:
        n, q = sr.shape[0], self._q
        dim = 3 * q
        delta = sr @ self._to_aligned  # K'_f K_f^-1
        coef = _pair_weights(delta).reshape(n, 81).T @ self._g  # (81 [(j,l),(m,o)], dim)
        # sum_f (delta_f kron I) V diag(g_f) V^T (delta_f kron I)^T, block (j, l) = sum_{m,o} V_m diag(c_jlmo) V_o^T:
        # contract m first (batched over e), then (o, e) in one product: O(q dim) memory (class docstring)
        half = torch.einsum("jlmoe,mae->jlaoe", coef.reshape(3, 3, 3, 3, dim), self._v3)  # (3, 3, q, 3, dim)
        diag_part = (half.reshape(9, q, 3 * dim) @ self._v_rows).reshape(9, q * q)
        return (_as_matrix(diag_part, q) + _rotated_block_sum(delta, self._blocks, q)) / n


def _check_factorisation(info: torch.Tensor) -> None:
    if int(info.max()) > 0:
        raise SolverError(f"empnd: the posterior precision of frame {int(torch.argmax((info > 0).int()))} is not "
                          "positive definite (degenerate shapes?); try init='rigid' or a larger c_init")


def pnd_cost(mean: torch.Tensor, mu: torch.Tensor, moment):
    """The profiled EM cost ``J(M)`` (module docstring) for `(3, q)` ``mean``; ``moment(sR)`` gives ``A``."""
    n, _, q = mu.shape
    sr, s = align(mu, mean)
    a = moment(sr)
    nb = constrained_directions(mean)
    proj = torch.eye(3 * q, dtype=_DT, device=mean.device) - nb @ nb.T
    b = proj @ a @ proj
    # a variance floor (1e-9 x the mean variance, and 1e-12 for shapes of norm ~1): on exactly low-rank data
    # (the shark) or a rigid sequence A is singular
    b = b + nb @ nb.T + (1e-9 * torch.trace(b).detach() / (3 * q - 4) + 1e-12) * proj.detach()
    chol, info = torch.linalg.cholesky_ex(0.5 * (b + b.T))
    if int(info) > 0:
        raise SolverError("empnd: the aligned shapes' covariance is singular beyond its variance floor (degenerate "
                          "shapes: collinear or coincident points?); try init='rigid' or another solver")
    cost = torch.log(torch.diagonal(chol)).sum() - (3 * q - 4) * torch.log(s).mean()
    return cost, (sr, s, chol, nb)


def _precision_from(chol: torch.Tensor, nb: torch.Tensor) -> torch.Tensor:
    """``Lambda = Q (Q^T A Q)^-1 Q^T = B^-1 - N N^T`` from the Cholesky factor of ``B = Pi A Pi + N N^T``."""
    lam = torch.cholesky_inverse(chol) - nb @ nb.T
    return 0.5 * (lam + lam.T)


@register("empnd", EMPNDParams, "EM with a Procrustean normal distribution, PND2 (Lee, Cho & Oh, CVPR 2013 / "
                                "TPAMI 2016)", handles_missing=True)
def solve_empnd(seq: Sequence, params: EMPNDParams) -> Reconstruction:
    """EM-PND2 on an orthographic sequence (missing points allowed). See the module docstring."""
    vis = require_visible_points(seq, "empnd")
    n, p = seq.n_frames, seq.n_points
    em = _EM(seq, vis, params)
    start_s = 0.0

    def timed_start(kind: str) -> np.ndarray:
        nonlocal start_s
        t0 = time.perf_counter()
        report("empnd", f"{kind} start", 0)
        shapes = _start_shapes(seq, params, kind)
        start_s += time.perf_counter() - t0
        return shapes

    kind = _init_kind(seq, params)
    probe_iter = params.probe_iter
    if probe_iter < 0:
        probe_iter = PROBE_ITER_EXACT if kind == "factorisation" and exactly_low_rank(seq) else 0
    probe_iter = min(probe_iter, params.max_iter)
    if params.init == "auto" and kind == "factorisation" and probe_iter > 0 and fits_csf2(n, p):
        # both starts for probe_iter iterations; the lower PND cost goes on
        probes = [em.iterate(em.begin(timed_start(k)), probe_iter) for k in ("factorisation", "csf2")]
        best = min(range(2), key=lambda i: probes[i]["cost"])
        kind = ("factorisation", "csf2")[best]
        st = probes[best]
        st["probe_costs"] = [p["cost"] for p in probes]
    else:
        st = em.begin(timed_start(kind))
    if not st["converged"]:
        st = em.iterate(st, params.max_iter - st["it"])
    mu, sr, s, var, cost, it = st["mu"], st["sr"], st["s"], st["var"], st["cost"], st["it"]
    converged, history = st["converged"], st["history"]

    points = np.einsum("pa,fja->fpj", em.basis, mu.cpu().numpy()) * em.unit  # (F, P, 3) camera frame
    rot = (sr / s[:, None, None]).cpu().numpy().transpose(0, 2, 1)  # camera <- aligned object frame
    return Reconstruction(points_3d=points, rotations=rot, method="empnd", iterations=it, converged=converged,
                          info={"noise_std": float(np.sqrt(var)) * em.unit, "cost": cost, "init": kind,
                                "cost_history": history, "probe_costs": st.get("probe_costs"),
                                "device": str(em.device), "start_s": start_s})


class _EM:
    """The data of one EM-PND run in normalised, translation-free coordinates, and its two steps:
    :meth:`begin` (a state from starting shapes) and :meth:`iterate` (EM iterations on a state)."""

    def __init__(self, seq: Sequence, vis: np.ndarray, params: EMPNDParams) -> None:
        n, p = seq.n_frames, seq.n_points
        q = p - 1
        self.params, self.n, self.dim, self.cdim = params, n, 3 * q, 3 * q - 4
        self.basis = basis = centring_basis(p)  # (P, q)
        visf = vis.astype(np.float64)
        count = visf.sum(axis=1)
        w = seq.points_2d
        wc = (w - (w * visf[..., None]).sum(axis=1, keepdims=True) / count[:, None, None]) * visf[..., None]
        self.unit = float(np.sqrt((wc**2).sum() / (2 * visf.sum()) * 3 * p))  # a shape's norm ~ 1 in these units
        if self.unit <= 0:
            raise SolverError("empnd: every visible track is constant (no 2D motion to reconstruct)")
        data = np.zeros((n, 3, q))
        data[:, :2] = np.einsum("pa,fpj->fja", basis, wc) / self.unit
        # projector onto each frame's observed (centred) rows, per coordinate: H^T (D_v - v v^T / |v|) H  (F, q, q)
        hv = visf @ basis  # (F, q)
        obs = (basis.T * visf[:, None, :]) @ basis - hv[:, :, None] * hv[:, None, :] / count[:, None, None]
        self.n_obs = 2.0 * (count - 1).sum()
        self.complete = bool(vis.all()) and params.fast
        self.device = pick_device(params.device)
        self.d_t = torch.from_numpy(data).to(self.device)
        self.obs_t = torch.from_numpy(obs).to(self.device)

    def begin(self, start: np.ndarray) -> dict:
        """EM state from `(F, P, 3)` camera-frame starting shapes (generalised Procrustes, sample covariance)."""
        n, dim, cdim, device = self.n, self.dim, self.cdim, self.device
        x0 = np.einsum("pa,fpj->fja", self.basis, start - start.mean(axis=1, keepdims=True)) / self.unit
        mu = torch.from_numpy(x0).to(device)
        mean = (mu / mu.reshape(n, -1).norm(dim=1)[:, None, None]).mean(dim=0)
        mean = mean / mean.norm()
        for _ in range(200):
            sr, _ = align(mu, mean)
            new = (sr @ mu).mean(dim=0)
            new = new / new.norm()
            done = float((new - mean).norm()) < 1e-12
            mean = new
            if done:
                break
        sr, s = align(mu, mean)
        y = (sr @ mu).reshape(n, dim)
        nb = constrained_directions(mean)
        full, _ = torch.linalg.qr(torch.cat([nb, torch.eye(dim, dtype=_DT, device=device)], dim=1))
        qb = full[:, 4:dim]  # (dim, cdim)
        cp = self.params.c_init * torch.eye(cdim, dtype=_DT, device=device) + qb.T @ (y.T @ y / n) @ qb
        fit = torch.zeros_like(mu)
        fit[:, :2] = mu[:, :2] @ self.obs_t
        var = self.params.var_init or max(float(((self.d_t - fit) ** 2).sum()) / self.n_obs, 1e-14)
        return dict(mu=mu, mean=mean, sr=sr, s=s, lam=qb @ torch.linalg.solve(cp, qb.T), var=var, step=1e-4,
                    cost=np.inf, history=[], it=0, converged=False)

    def iterate(self, st: dict, n_iter: int) -> dict:
        """Up to ``n_iter`` EM iterations from state ``st`` (updated and returned)."""
        params, d_t, obs_t, n_obs = self.params, self.d_t, self.obs_t, self.n_obs
        mean, sr, s, lam, var, step, cost = st["mean"], st["sr"], st["s"], st["lam"], st["var"], st["step"], st["cost"]
        fit = torch.zeros_like(st["mu"])
        mu = st["mu"]
        for _ in range(n_iter):
            st["it"] += 1
            # ---- E-step
            if self.complete:
                post = CompletePosterior(lam, sr, s, d_t, var)
            else:
                post = DensePosterior(lam, sr, d_t, obs_t, var)
            mu = post.mu
            # ---- noise variance
            fit[:, :2] = mu[:, :2] @ obs_t
            new_var = (float(((d_t - fit) ** 2).sum()) + post.trace) / n_obs
            var = max(min(params.var_drop * new_var, max(var, new_var)), 1e-14)
            # ---- M-step: one line-searched gradient step on the mean shape
            mean, j0, aux, step = _mean_step(mean, mu, post.moment, step)
            sr, s, chol_b, nb = aux
            lam = _precision_from(chol_b, nb)
            previous, cost = cost, (2.0 * j0 + np.log(var) * n_obs / self.n) / self.cdim
            st["history"].append(cost)
            report("empnd", "EM", st["it"], params.max_iter, cost=cost)
            if previous - cost < params.tol:
                st["converged"] = True
                break
        st.update(mu=mu, mean=mean, sr=sr, s=s, lam=lam, var=var, step=step, cost=cost)
        return st


def _mean_step(mean: torch.Tensor, mu: torch.Tensor, moment, step: float):
    """The M-step: one Armijo-backtracked gradient step of the profiled PND cost on the unit sphere of mean shapes
    `(3, q)`, from step length ``step`` (doubled after a success, halved on each failure). Returns the new mean,
    its cost, :func:`pnd_cost`'s by-products there and the next step length."""
    m_var = mean.clone().requires_grad_(True)
    j0, aux = pnd_cost(m_var, mu, moment)
    (grad,) = torch.autograd.grad(j0, m_var)
    grad = grad - (grad * mean).sum() * mean  # J is scale invariant: stay on the sphere
    g2 = float((grad * grad).sum())
    j0 = float(j0.detach())
    aux = tuple(a.detach() for a in aux)
    for _ in range(40):
        trial = mean - step * grad
        trial = trial / trial.norm()
        if not bool(torch.isfinite(trial).all()):  # degenerate shapes (e.g. collinear points): no usable step
            break
        try:
            with torch.no_grad():
                jt, aux_t = pnd_cost(trial, mu, moment)
        except (SolverError, torch.linalg.LinAlgError):  # a trial where the covariance is singular: a failed step
            step *= 0.5
            continue
        if float(jt) <= j0 - 1e-4 * step * g2:
            mean, j0, aux = trial, float(jt), aux_t
            step *= 2.0
            break
        step *= 0.5
    return mean, j0, aux, step


#: Iterations of each start on noise-free tracks (``probe_iter = -1``) before the lower PND cost picks one.
PROBE_ITER_EXACT = 20


def exactly_low_rank(seq: Sequence, rel: float = 1e-8) -> bool:
    """True when the centred `(2F, P)` tracks of ``seq`` have numerical rank below ``min(2F, P - 1)``
    (singular values below ``rel`` times the largest): noise-free data such as synthetic sequences or the shark
    (2e-18); the five CMU mocap files' smallest singular values are 8e-6 to 1.2e-4 of the largest."""
    w = seq.points_2d - seq.points_2d.mean(axis=1, keepdims=True)
    sv = np.linalg.svd(w.transpose(0, 2, 1).reshape(-1, seq.n_points), compute_uv=False)
    full = min(2 * seq.n_frames, seq.n_points - 1)
    return bool(sv[0] > 0 and (sv[:full] < rel * sv[0]).any())


def _init_kind(seq: Sequence, params: EMPNDParams) -> str:
    kind = params.init
    if kind == "auto":
        kind = "factorisation" if bool((seq.weights > 0).all()) else "csf2"
    if kind == "csf2" and not fits_csf2(seq.n_frames, seq.n_points):
        return "rigid"  # documented fallback
    return kind


def _start_shapes(seq: Sequence, params: EMPNDParams, kind: str) -> np.ndarray:
    """`(F, P, 3)` camera-frame starting shapes of the given ``kind`` (see :class:`EMPNDParams` ``init``)."""
    if kind == "factorisation":
        if not bool((seq.weights > 0).all()):
            raise ValidationError("empnd: init='factorisation' needs every point visible; this sequence has "
                                  f"{int((seq.weights <= 0).sum())} missing entries. Use init='auto' or 'csf2'.")
        return factorisation_start(seq.points_2d)
    if kind == "csf2":
        return csf2_start(seq, params.init_K, camera_rounds=params.init_rounds, round_iter=5, round_iter_alt=0)
    if kind in ("spm", "pr"):
        if kind == "spm" and not bool((seq.weights > 0).all()):
            raise ValidationError("empnd: init='spm' needs every point visible; this sequence has "
                                  f"{int((seq.weights <= 0).sum())} missing entries. Use init='auto', 'csf2' or 'pr'.")
        return solve(seq, kind).points_3d
    return solve_rank3.__wrapped__(seq, Rank3Params()).points_3d
