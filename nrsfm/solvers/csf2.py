"""CSF2: column space fitting with complementary rank-3 spaces (Gotardo & Martinez, CVPR 2011).

Model (orthographic, centred tracks): ``W = D (C kron I3) S`` with ``D`` `(2F, 3F)`
the block-diagonal camera rows, ``C = Omega_d X`` `(F, K)` shape coefficients on
the first ``d`` DCT vectors (smooth trajectories), and ``S`` `(3K, P)` the basis
shapes. We follow the authors' MATLAB code (``pgComputeD.m``,
``pgCSF_Bnr_fullW.m``); the reference numbers in NOTES.md come from it.

1. Cameras (:func:`camera_rows`, PTA's Euclidean upgrade as modified by the
   authors): the factor ``M = U sqrt(Sigma)`` of the centred W keeps every
   singular value above ``energy`` times the largest (a multiple of 3
   columns); the `(n, 3)` corrective matrix ``Q`` minimises the orthonormality
   residual ``sum_f (|r_f1|^2 - 1)^2 + (|r_f2|^2 - 1)^2 + (r_f1 . r_f2)^2`` of
   ``M Q``, grown three columns at a time from ``[I3; 0]`` while the cost
   falls. We minimise with BFGS and the analytic gradient (the authors call
   MATLAB's quasi-Newton ``fminunc``); Levenberg-Marquardt stalls in a worse
   minimum on yoga (cost 2e-4 against 9e-7, e3D .38 against .030).
2. Shape (:func:`fit_shape_gn`): with D fixed, ``X`` `(d, K)` minimises the
   column-space cost ``||W - M M^+ W||^2``, ``M = D (Omega X kron I3)`` (S
   eliminated in closed form), by damped Gauss-Newton on the variable-projection
   Jacobian: damping 1e-4, x10 on a failed step, /100 on a good one; X
   re-orthonormalised (QR) after every step; start ``X = I``; stop when the RMSE
   falls by less than ``tol`` (times the RMS of W) over two iterations or after
   ``max_iter`` (100) iterations. From ``X = I`` Gauss-Newton can stop in a
   poor minimum on short, nearly rigid sequences (synthetic 150-frame faces,
   exact cameras: RMSE .074 and e3D 1.27 where the true X gives .048 and
   .0018), so a second run starts from the rigid fit's residual
   (:func:`residual_start`: the constant plus the residual's first K - 1
   temporal principal components) and is kept when its RMSE is more than 1%
   lower. On the six CMU files the authors' start is the lower or within
   1e-4 of it, so their numbers are unchanged (``residual_start=False``: the
   authors' start only). Both can still stop in a poor minimum: noise-free
   smooth-camera tracks of K = 4 (smooth:4:1:0 of ``benchmarks.auto_k``, 300
   x 41) end at RMSE .0110 and e3D .3367 from both, where 4 of 6 random
   orthonormal starts reach .0019 and e3D .0029. So
   ``random_starts`` (3) random starts (fixed seed) follow, and the best
   replaces the fit above only when its RMSE is below ``random_accept``
   (half) of it: a different basin, not a slightly better fit. On real
   tracks a slightly better fit is not a better reconstruction (stretch, K =
   8: a random start fits 3.2% better and gives e3D .0401 against .0392),
   and on the CMU files no random start fits better than 0.968 times the
   deterministic starts (complete tracks; 1.000 on the completed W with 20%
   missing), so their numbers are unchanged. ``python -m benchmarks.auto_k``
   (every K on 47 sequences, complete and with 20% missing): of 376 and 209
   cells only that one moves. Cost, one thread: drink 5.1 -> 6.7 s (K = 10),
   4.5 -> 5.5 s (the automatic K, 8).

Missing points (the occlusion-aware variant): W is first completed
(:func:`~nrsfm.solvers.base.complete_lowrank`, ``info["completion"]``). Where
the visible entries are exactly low-rank (noise-free tracks: some rank r <= 3K
fits them to 1e-6 of their RMS, :func:`~nrsfm.solvers.base.visible_rank`), the
rank-r fill is the true W and CSF2 runs on it as on complete tracks (four
150-frame synthetic faces with 20% missing: e3D .0007-.0071, the complete-track
numbers; .0052-.3791 with the hard imputation). Otherwise W is completed by a
rank-3K hard imputation; steps 1-2 run on it; then X and S are refined by
alternating least squares over the visible entries only (each sub-problem is
linear; a small ``ridge`` on S keeps the depth of the basis bounded; the
X-step's normal matrix comes from 2d - 1 cosine sums, :func:`dct_weighted_gram`).
The shape step's fit to the imputed W can fail to tell the two
deterministic starts apart: on smooth:4:2:0.01 of ``benchmarks.auto_k`` with
20% missing (K = 4) the residual start fits the imputed W only .7% better
(RMSE .2460 against .2478, under ``start_margin``) and ends at e3D .0424,
where the authors' start ends at .8445 (visible RMSE .0096 against .0143).
So the other deterministic start is refined on the visible entries too;
where it ends elsewhere (visible RMSE more than 1e-4 apart), both go
``_START_PROBE_ROUNDS`` (5) camera rounds (below) and the other start is
taken when its visible RMSE is then more than ``start_margin`` lower
(``info["shape_start"]`` says "(visible entries)"; without camera rounds the
refined RMSE decides). The refined RMSE alone would mislead: on a synthetic
face (face:0.005, K = 5) it prefers the residual start, which after the
rounds fits worse (.0218 against .0178) and gives e3D .0216 against .0035;
after 5 rounds the authors' start is ahead. On the CMU files both starts
refine to the same RMSE but on dance, where the probe keeps the authors'
start: their numbers are unchanged.
The cameras of the completed W inherit the completion's errors (pickup with
20% missing: e3D .45 against .026 complete), so up to ``camera_rounds`` (200)
rounds follow: every frame's rotation and translation by Gauss-Newton on its
visible entries (:func:`_refine_cameras`), then ``round_iter`` X/S iterations;
each run returns its round of lowest visible-entry RMSE (the ridge on S lets
the RMSE rise again before the rounds stop).
The rounds run twice from the same start (``round_iter`` 20 and
``round_iter_alt`` 5), side by side on two threads, and the lower
visible-entry RMSE wins: the two land in different minima, and the better fit
is the better reconstruction on both sequences where they differ (drink: RMSE
.001444 / e3D .0175 against .001457 / .1096; pickup: .001743 / .0324 against
.001862 / .0617). The slower run (20 X/S iterations per round) stops early
when, from round 30 on, its RMSE is more than 2% above the other run's at the
same round (``race_margin``, ``race_from``; :class:`_RoundRace`): on drink it
is 2.9% behind at round 30, 1.8% at 100 and .9% at 200, so it now stops at
round 30 (drink with 20% missing: 97 s -> 47 s, the same result); nowhere
else we measured does the slower run fall 2% behind. ``info["rounds"]``: the
rounds each run took, keyed by its X/S iterations per round.

Units: W is first divided by the power of two nearest the RMS of its centred
visible entries (:func:`~nrsfm.solvers.base.power_of_two_unit`; exact in
floating point) and the shapes are multiplied back at the end, so the camera
step's BFGS tolerances and the shape step's damping mean the same in any units.
Without it, a noise-free 60 x 20 sequence gave e3D .98 with an RMS of 1e5 and
.38 at 1e-9, against .044 at 1 (and EM-PPCA, which starts from CSF2, .86 at
1e5); the CMU files' shapes move by at most 3e-5 (relative), e3D by at most
1e-6.

Automatic K and d (``K=0``/``d=0``; the authors always set them by hand):
K = ceil(r / 3), plus one when 3 does not divide r (a basis of deficient
rank: the shark's rank-5 W needs K = 3, and K = 2 fails; the faces' rank 7
needs 4), at most 8 and with 3K < min(2F, P) (at 3K = 2F the rank-3K
factorisation is all of W and leaves the cameras free: three frames of a
K = 2 sequence gave e3D 17.0 with K = 2, 2.8 with K = 1; EM-PPCA from that
start 12.1 and 3.7). r is the numerical rank of the centred W when W is
rank deficient (noise-free tracks). Noisy tracks have full numerical rank:
r is then Gavish & Donoho's noise threshold
(:func:`~nrsfm.solvers.base.noise_rank`) where the spectrum has a clear gap
there; otherwise (real motion capture such as the CMU files: no gap) K is
the cap, 8. ``python -m benchmarks.auto_k`` measures the rule against every
K (CSF2, camera-frame e3D, 300 x 41 synthetic tracks; see
``benchmarks/RESULTS.md``): with a smoothly turning camera and 1% noise the
cap (the rule before session 26) gave .38-.81 and the threshold's K gives
.009-.046; at 5% noise 7 of 9 sequences pass the gap test (.035-.49
against .41-.72), the other 2 keep the cap; the noisy synthetic faces .0005-.0007
against .12-.61. Noise-free, the earlier rule's extra basis shape on rank
3K costs .0018-.4826 where K gives .0006-.0038, on all 9 smooth-camera
sequences (session 31; until the random shape starts, K = 4 gave .3367 on
one of them, smooth:4:1:0, against .0184 at 5). With random cameras and 1% noise the two are
close (true K = 3: .0087 against the cap's .0092; K = 5: .0192 against
.0122);
with missing points r is the lowest rank whose fit to the visible entries
(variable projection) leaves less than 1e-6 of their RMS (:func:`auto_k`: on
the CMU files and the stand-ins, the complete tracks' K; the same fit serves
the exact completion above, and runs up to rank min(3K, 18) when K is given;
where no rank fits, the noise floor of a ladder of such fits
(:func:`~nrsfm.solvers.base.noise_visible_rank`: noisy low-rank tracks with
missing points, which kept the cap until session 27; real motion capture shows
no floor and keeps it);
d = ceil(0.1 F) (the authors' demos), at least K + 1. On the CMU files no rule
we tried picks the best K from W alone (the 2D fit, a held-out-frame fit and singular-value
energy all keep improving with K while the depth gets worse). The settings
that reproduce the authors' numbers on the CMU files are K = 10 (drink,
pickup), 8 (yoga, stretch), 3 (shark), 2 (dance), all with d = ceil(0.1 F);
``benchmarks.classic`` passes them (see ``benchmarks/RESULTS.md``).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import hashlib
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import as_strided
from scipy.linalg import cho_factor, cho_solve
from threadpoolctl import threadpool_limits

from nrsfm import progress
from nrsfm.errors import SolverError, ValidationError
from nrsfm.geometry import complete_rotation
from nrsfm.sequence import Sequence
from nrsfm.solvers.base import (Reconstruction, complete_lowrank, masked_lstsq, noise_rank, noise_visible_rank,
                                power_of_two_unit, register, require_visible_points, visible_rank)


@dataclass(frozen=True)
class CSF2Params:
    """Parameters of :func:`solve_csf2` (``K = 0`` / ``d = 0``: automatic, see the module docstring).

    Attributes:
        K: number of basis shapes; d: number of DCT vectors.
        max_iter, tol: Gauss-Newton iterations and stopping rule (RMSE drop over two iterations, relative to
            the RMS of the centred W).
        energy: singular values kept for the camera factor (relative to the largest).
        ridge: ridge on S in the missing-data refinement; refine_iter: its iterations.
        camera_rounds: rounds of (cameras and translations by Gauss-Newton on the visible entries, then
            ``round_iter`` X/S iterations) after that refinement; 0 keeps the cameras of the completed W.
        round_iter_alt: a second run of the rounds with this many X/S iterations per round, from the same
            start; the lower visible-entry RMSE wins (0: one run).
        race_margin, race_from: the run with more X/S iterations per round stops early when, at a round
            ``race_from``, ``race_from + 10``, ..., its RMSE is more than ``race_margin`` (relative) above the
            other run's at the same round (``race_from = 0``: both always run to the end).
        residual_start: also run the shape step from :func:`residual_start` and keep it when its RMSE is
            lower than the authors' start's by more than ``start_margin`` (relative; with imputed missing points,
            on the imputed W or on the visible entries after refinement); False: the authors' start only.
        random_starts: also run the shape step from this many random orthonormal starts (fixed seed); the
            lowest RMSE among them replaces the deterministic starts' fit only when it is below ``random_accept``
            times that fit's RMSE (module docstring).
    """

    K: int = 0
    d: int = 0
    max_iter: int = 100
    tol: float = 1e-6
    energy: float = 1e-4
    ridge: float = 1e-4
    refine_iter: int = 200
    camera_rounds: int = 200
    round_iter: int = 20
    round_iter_alt: int = 5
    race_margin: float = 0.02
    race_from: int = 30
    residual_start: bool = True
    start_margin: float = 0.01
    random_starts: int = 3
    random_accept: float = 0.5

    def __post_init__(self) -> None:
        if self.ridge < 0 or not 0 < self.energy < 1 or self.tol < 0 or not 0 <= self.start_margin < 1 \
                or not self.race_margin >= 0 or self.race_from < 0 or not 0 < self.random_accept <= 1:
            raise ValidationError(f"CSF2Params: expected ridge >= 0, 0 < energy < 1, tol >= 0, 0 <= start_margin < 1, "
                                  f"race_margin >= 0, race_from >= 0, 0 < random_accept <= 1, got ridge={self.ridge}, "
                                  f"energy={self.energy}, tol={self.tol}, start_margin={self.start_margin}, "
                                  f"race_margin={self.race_margin}, race_from={self.race_from}, "
                                  f"random_accept={self.random_accept}")
        if self.K < 0 or self.d < 0 or self.random_starts < 0 or self.max_iter < 1 or self.refine_iter < 0 \
                or self.camera_rounds < 0 or self.round_iter < 1 or self.round_iter_alt < 0:
            raise ValidationError(f"CSF2Params: expected K, d, random_starts, refine_iter, camera_rounds, "
                                  f"round_iter_alt >= 0 and max_iter, round_iter >= 1, got K={self.K}, d={self.d}, "
                                  f"random_starts={self.random_starts}, refine_iter="
                                  f"{self.refine_iter}, camera_rounds={self.camera_rounds}, max_iter={self.max_iter}, "
                                  f"round_iter={self.round_iter}, round_iter_alt={self.round_iter_alt}")


def dct_basis(n_frames: int, d: int) -> np.ndarray:
    """`(F, d)` orthonormal DCT-II basis (first column constant)."""
    t = np.arange(n_frames)
    k = np.arange(d)
    basis = np.cos(np.pi * (2 * t[:, None] + 1) * k[None] / (2 * n_frames))
    basis[:, 0] *= 1 / np.sqrt(2)
    return basis * np.sqrt(2 / n_frames)


@functools.lru_cache(maxsize=8)
def _dct_cosines(n_frames: int, d: int) -> np.ndarray:
    """`(2d - 1, F)` ``cos(pi m (2f + 1) / 2F)`` for m < 2d - 1 (read-only; cached: the missing-data rounds call
    :func:`dct_weighted_gram` thousands of times on one sequence)."""
    freq = np.arange(2 * d - 1)
    cos = np.cos(np.pi * (2 * np.arange(n_frames)[None] + 1) * freq[:, None] / (2 * n_frames))
    cos.flags.writeable = False
    return cos


def dct_weighted_gram(weights: np.ndarray, d: int) -> np.ndarray:
    """``G[a, b] = sum_f omega_fa omega_fb weights_f`` `(d, d, ...)` for the DCT basis of :func:`dct_basis` and
    `(F, ...)` weights, from ``2d - 1`` cosine sums (``cos x cos y = (cos(x + y) + cos(x - y)) / 2``): ``O(F d)``
    products instead of ``O(F d^2)`` (on drink, K = 10: 24 Mflop against 2.7 Gflop)."""
    sums, scale = _dct_cosine_sums(weights, d)
    sums = sums.reshape((2 * d - 1,) + weights.shape[1:])
    a = np.arange(d)
    gram = 0.5 * (sums[a[:, None] + a[None]] + sums[np.abs(a[:, None] - a[None])])
    return gram * (scale[:, None] * scale[None]).reshape((d, d) + (1,) * (weights.ndim - 1))


def _dct_cosine_sums(weights: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``2d - 1`` cosine sums `(2d - 1, prod(weights.shape[1:]))` of `(F, ...)` weights and the `(d,)` scale of
    the DCT basis vectors (:func:`dct_basis`)."""
    n_frames = weights.shape[0]
    scale = np.full(d, np.sqrt(2 / n_frames))
    scale[0] = np.sqrt(1 / n_frames)
    return _dct_cosines(n_frames, d) @ weights.reshape(n_frames, -1), scale


def dct_weighted_gram_blocks(weights: np.ndarray, d: int) -> np.ndarray:
    """:func:`dct_weighted_gram` of `(F, K, K)` weights laid out as the `(d K, d K)` matrix with entry
    ``[(a, k), (b, l)]`` = ``G[a, b, k, l]``: the X-step's normal matrix. The ``a + b`` (Hankel) and ``|a - b|``
    (Toeplitz) terms are strided views of the cosine sums, added straight into that layout (the same values to
    the bit as :func:`dct_weighted_gram`; on drink, K = 10, one thread, back to back: 4.7-5.0 ms against
    8.6-9.8 ms with an index gather)."""
    k = weights.shape[1]
    sums, scale = _dct_cosine_sums(weights, d)
    sums = sums.reshape(2 * d - 1, k, k)
    s0, s1, s2 = sums.strides
    plus = as_strided(sums, shape=(d, k, d, k), strides=(s0, s1, s0, s2), writeable=False)  # [a, k, b, l]: a + b
    # |a - b| as b - a + d - 1 in the mirrored sums (entry m = sums[|m - (d - 1)|]), read from their middle
    mirrored = np.concatenate([sums[d - 1:0:-1], sums[:d]])[d - 1:]
    minus = as_strided(mirrored, shape=(d, k, d, k), strides=(-s0, s1, s0, s2), writeable=False)
    gram = np.add(plus, minus)
    gram *= (0.5 * scale[:, None] * scale[None])[:, None, :, None]  # halving is exact: as (x * 0.5) * (s_a s_b)
    return gram.reshape(d * k, d * k)


def auto_k(w: np.ndarray, mask: np.ndarray | None = None, k_max: int = 8, rel_tol: float = 1e-6,
           max_frames: int = 300, max_points: int = 60, fit: tuple[int, np.ndarray | None] | None = None) -> int:
    """CSF2's automatic K for a `(2F, P)` W: ``ceil(r / 3)``, plus one when 3 does not divide ``r``, for a rank
    ``r`` of the centred W, at most ``k_max`` and with 3K < min(2F, P) (module docstring).

    ``r`` is the numerical rank (singular values above ``rel_tol`` times the largest) when W is rank deficient;
    when it is not, the rank of noisy low-rank tracks (:func:`~nrsfm.solvers.base.noise_rank`), and the cap
    where W does not look like one (real motion capture).

    With missing entries (``mask`` False) the rank r is the smallest whose fit to the visible entries leaves less
    than ``rel_tol`` of their RMS (:func:`~nrsfm.solvers.base.visible_rank`, on at most ``max_frames`` frames and
    ``max_points`` points, ranks up to 3 (cap - 2); ``fit`` passes its result when already computed); where none
    fits, the rank of noisy low-rank tracks (:func:`~nrsfm.solvers.base.noise_visible_rank`, seconds: 4.9 s on
    drink and 9.2 s on dance with 20% missing for the whole rule, one core), and the cap where there is none.
    """
    cap = max(1, min(k_max, (min(w.shape) - 1) // 3))
    if mask is not None and not mask.all():
        max_rank = auto_k_max_rank(w, k_max)
        rank = (fit or visible_rank(w, mask, max_rank, rel_tol=rel_tol, max_frames=max_frames,
                                    max_points=max_points))[0]
        if not rank:
            rank = _shared("noise_visible_rank", (w / power_of_two_unit(w, mask), mask, max_rank, max_frames,
                                                  max_points),
                           lambda: noise_visible_rank(w, mask, max_rank, max_frames=max_frames, max_points=max_points))
    else:
        s = np.linalg.svd(w - w.mean(axis=1, keepdims=True), compute_uv=False)
        rank = int(np.count_nonzero(s > rel_tol * s[0])) if s[0] > 0 else 1
        if rank >= min(w.shape[0], w.shape[1] - 1):
            rank = noise_rank(s, w.shape)
    return k_for_rank(rank, cap)


def k_for_rank(rank: int, cap: int) -> int:
    """:func:`auto_k`'s K for a rank: ``ceil(rank / 3)``, plus one when 3 does not divide it, at most ``cap``;
    ``cap`` for rank 0 (none found)."""
    if not rank:
        return cap
    return max(1, min(cap, -(-rank // 3) + (rank % 3 != 0)))


def auto_k_max_rank(w: np.ndarray, k_max: int = 8) -> int:
    """The largest rank :func:`auto_k` tests on a `(2F, P)` W with missing entries: 3 (cap - 2)."""
    return 3 * (max(1, min(k_max, min(w.shape) // 3)) - 2)


def refine_triple(pi: np.ndarray, g0: np.ndarray) -> tuple[np.ndarray, float]:
    """Minimise the scale-invariant orthonormality residual of ``pi @ G`` from ``g0``.

    BFGS (analytic gradient) followed by a Levenberg-Marquardt polish, and LM
    from ``g0`` alone; the lower cost wins. LM alone is fragile: on drink
    (SPM, K = 12) it stalls at cost 4.0 (cameras 15 degrees off) or reaches
    7e-4 (0.3 degrees) depending on the BLAS thread count; BFGS reaches 7e-4
    either way.

    Args:
        pi: `(F, 2, 3K)` rank-3K factor; g0: `(3K, 3)` start.

    Returns:
        The refined `(3K, 3)` triple and the final cost (0 for exact data).
    """
    import scipy.optimize

    r = pi.shape[2]
    pa, pb = pi[:, 0], pi[:, 1]  # (F, r)

    def residual(g_flat: np.ndarray) -> np.ndarray:
        m = pi @ g_flat.reshape(r, 3)  # (F, 2, 3)
        a, b = m[:, 0], m[:, 1]
        na, nb = (a * a).sum(1), (b * b).sum(1)
        den = na + nb + 1e-300
        return np.concatenate([(na - nb) / den, 2 * (a * b).sum(1) / den])

    def cost_grad(g_flat: np.ndarray) -> tuple[float, np.ndarray]:
        a, b = pa @ g_flat.reshape(r, 3), pb @ g_flat.reshape(r, 3)  # (F, 3)
        na, nb, ab = (a * a).sum(1), (b * b).sum(1), (a * b).sum(1)
        den = na + nb + 1e-300
        e, o = (na - nb) / den, 2 * ab / den
        den2 = den**2
        ca = 2 * (e * 2 * nb - o * 2 * ab) / den2  # d cost / d na, times 2 (d na / d a = 2 a)
        cb = 2 * (-e * 2 * na - o * 2 * ab) / den2
        co = 2 * o / den
        grad = pa.T @ (ca[:, None] * a + co[:, None] * b) + pb.T @ (cb[:, None] * b + co[:, None] * a)
        return 0.5 * float(e @ e + o @ o), grad.ravel()

    # LM needs at least as many residuals (2F) as unknowns (3r); with fewer frames (three frames, K >= 1) the
    # trust-region solver polishes instead
    method = "lm" if 2 * pi.shape[0] >= 3 * r else "trf"

    def polish(g_flat: np.ndarray) -> tuple[np.ndarray, float]:
        res = scipy.optimize.least_squares(residual, g_flat, method=method, max_nfev=2000, xtol=1e-12, ftol=1e-12)
        return res.x, float(res.cost)

    bfgs = scipy.optimize.minimize(cost_grad, g0.ravel(), jac=True, method="BFGS",
                                   options={"gtol": 1e-10, "maxiter": 5000})
    candidates = [polish(bfgs.x), polish(g0.ravel())]
    g, cost = min(candidates, key=lambda c: c[1])
    return g.reshape(r, 3), cost


def camera_rows(wc: np.ndarray, energy: float = 1e-4) -> tuple[np.ndarray, float, int]:
    """Orthographic camera rows from the centred `(2F, P)` W (step 1 of the module docstring).

    Returns:
        `(F, 2, 3)` rows ``M Q`` (nearly orthonormal, not normalised: the shape
        step uses them as they are, like the authors), the final orthonormality
        cost (mean over the 2F rows; 0 for exact data) and the number of columns
        of M used.
    """
    import scipy.optimize

    n_frames = wc.shape[0] // 2
    u, s, _ = np.linalg.svd(wc, full_matrices=False)
    n_cols = 3 * int(np.ceil(np.count_nonzero(s / s[0] > energy) / 3))
    if n_cols > u.shape[1]:
        n_cols -= 3
    m = (u[:, :n_cols] * np.sqrt(s[:n_cols])).reshape(n_frames, 2, n_cols)

    def cost_grad(q_flat: np.ndarray, mm: np.ndarray) -> tuple[float, np.ndarray]:
        rows = mm @ q_flat.reshape(-1, 3)  # (F, 2, 3)
        a, b = rows[:, 0], rows[:, 1]
        ea, eb, ab = (a * a).sum(1) - 1, (b * b).sum(1) - 1, (a * b).sum(1)  # (F,)
        scale = 1.0 / n_frames  # the authors' 2 f / (2F)
        # d/dQ of the three residuals: M_f1^T (2 a), M_f2^T (2 b), M_f1^T b + M_f2^T a
        grad = mm[:, 0].T @ (4 * ea[:, None] * a + 2 * ab[:, None] * b) \
            + mm[:, 1].T @ (4 * eb[:, None] * b + 2 * ab[:, None] * a)
        return scale * float(ea @ ea + eb @ eb + ab @ ab), scale * grad.ravel()

    def fit(q0: np.ndarray) -> tuple[np.ndarray, float]:
        res = scipy.optimize.minimize(cost_grad, q0.ravel(), args=(m[:, :, :len(q0)],), jac=True, method="BFGS",
                                      options={"gtol": 1e-12, "maxiter": 2000})
        return res.x.reshape(-1, 3), float(res.fun)

    if n_cols == 3:  # rigid (rank 3): the metric upgrade of the rigid factorisation
        q, best = fit(np.eye(3))
    else:
        q, best = np.eye(3), np.inf
        while q.shape[0] + 3 <= n_cols:  # grow [Q; 0] three columns at a time while the cost falls
            new_q, cost = fit(np.vstack([q, np.zeros((3, 3))]))
            if not cost < best:
                break
            q, best = new_q, cost
    return m[:, :, :q.shape[0]] @ q, best, q.shape[0]


def residual_start(wc: np.ndarray, rows: np.ndarray, omega: np.ndarray, k: int) -> np.ndarray:
    """`(d, k)` orthonormal start for :func:`fit_shape_gn` from the rigid fit's residual.

    The coefficients ``C`` `(F, k)` start as the constant plus the first ``k - 1`` temporal principal components of
    what the best rigid shape (least squares given the camera rows) leaves unexplained, projected on the DCT basis.

    Args:
        wc: `(2F, P)` centred W; rows: `(F, 2, 3)` camera rows; omega: `(F, d)` DCT basis.
    """
    n_frames = rows.shape[0]
    d_rows = rows.reshape(2 * n_frames, 3)
    rigid = np.linalg.lstsq(d_rows, wc, rcond=None)[0]  # (3, P)
    resid = (wc - d_rows @ rigid).reshape(n_frames, -1)  # (F, 2P)
    u = np.linalg.svd(resid, full_matrices=False)[0][:, :k - 1]  # (F, k-1)
    c = np.column_stack([np.full(n_frames, n_frames**-0.5), u])
    return np.linalg.qr(omega.T @ c)[0]


def fit_shape_gn(wc: np.ndarray, rows: np.ndarray, k: int, d: int, *, max_iter: int = 100, tol: float = 1e-6,
                 x0: np.ndarray | None = None, omega: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, int, bool, float]:
    """Damped Gauss-Newton on the column-space cost (step 2 of the module docstring).

    Args:
        wc: `(2F, P)` centred W; rows: `(F, 2, 3)` camera rows; k, d: bases.
        tol: stop when the RMSE falls by less than ``tol`` times the RMS of ``wc`` over two iterations.
        x0: `(d, k)` start (default: the first k columns of the identity).
        omega: `(F, d)` trajectory basis (default: the first d DCT vectors).

    Returns:
        X `(d, k)`, S `(k, 3, P)`, iterations, converged, final RMSE.
    """
    n_frames, n_points = rows.shape[0], wc.shape[1]
    omega = dct_basis(n_frames, d) if omega is None else omega  # (F, d)
    bnr = np.einsum("fij,fa->fiaj", rows, omega).reshape(2 * n_frames, 3 * d)  # D (Omega kron I3), cols (a, j)
    btb = bnr.T @ bnr

    def kron_i3(a: np.ndarray, x: np.ndarray) -> np.ndarray:
        """``a @ kron(x, I3)`` for `(R, 3d)` a, without forming the Kronecker product: `(R, 3K)`, columns (k, j)."""
        return np.tensordot(a.reshape(len(a), d, 3), x, axes=([1], [0])).transpose(0, 2, 1).reshape(len(a), -1)

    def factors(x: np.ndarray):
        m = kron_i3(bnr, x)  # (2F, 3K), columns (k, j)
        pinv = np.linalg.pinv(m)
        s = pinv @ wc
        return pinv, s, wc - m @ s

    x = np.eye(d, k) if x0 is None else x0
    pinv, s, r = factors(x)
    history = [float(np.sqrt((r**2).mean()))]
    tol_abs = tol * float(np.sqrt((wc**2).mean()))
    delta, it, converged = 1e-4, 0, False
    if d <= k:  # X's columns span every trajectory the basis has: nothing to fit
        return x, s.reshape(k, 3, n_points), 0, True, history[-1]
    for it in range(1, max_iter + 1):
        # gradient of 1/2 ||R||^2 in X: -sum_i (Bnr^T R S^T)[(a, i), (k, i)]; Gauss-Newton matrix
        # H[(a,k),(b,l)] = sum_ij YY[(a,i),(b,j)] (S S^T)[(k,i),(l,j)], YY = Bnr^T (I - M M^+) Bnr
        zz = ((bnr.T @ r) @ s.T).reshape(d, 3, k, 3)
        g = -np.einsum("aiki->ak", zz).ravel()
        yy = (btb - kron_i3(btb, x) @ (pinv @ bnr)).reshape(d, 3, d, 3)  # Bnr^T M = Bnr^T Bnr (X kron I3)
        ss = (s @ s.T).reshape(k, 3, k, 3)
        # X is defined up to an invertible k x k factor (X -> X A keeps the column space of M), so H is singular
        # along X A; the steps orthogonal to those, X_perp C with X_perp `(d, d - k)` spanning the complement of
        # X's columns, give the same damped step as the minimum-norm solve of the full system (g has no
        # component along X A) with a positive definite `((d - k) k)` system (drink, K = 10: 17.0 -> 3.3 s)
        perp = np.linalg.qr(x, mode="complete")[0][:, k:]
        yy_perp = np.einsum("ab,aicj,cm->bimj", perp, yy, perp, optimize=True)  # (d - k, 3, d - k, 3)
        n_red = (d - k) * k
        h_red = np.tensordot(yy_perp, ss, axes=([1, 3], [1, 3])).transpose(0, 2, 1, 3).reshape(n_red, n_red)
        g_red = (perp.T @ g.reshape(d, k)).ravel()
        while True:
            try:
                c_red = cho_solve(cho_factor(h_red + delta * np.eye(n_red)), g_red)
            except np.linalg.LinAlgError:  # not positive definite in floating point: the minimum-norm solution
                c_red = np.linalg.lstsq(h_red + delta * np.eye(n_red), g_red, rcond=None)[0]
            new_x, _ = np.linalg.qr(x - perp @ c_red.reshape(d - k, k))
            new = factors(new_x)
            rmse = float(np.sqrt((new[2]**2).mean()))
            if rmse < history[-1]:
                break
            delta *= 10
            if delta > 1e30:
                return x, s.reshape(k, 3, n_points), it, True, history[-1]  # no descent direction: a minimum
        x, (pinv, s, r) = new_x, new
        delta = max(delta / 100, 1e-20)
        history.append(rmse)
        progress.report("csf2", "shape", it, max_iter, rmse=rmse)
        if it > 1 and history[-3] - history[-1] < tol_abs:
            converged = True
            break
    return x, s.reshape(k, 3, n_points), it, converged, history[-1]


@register("csf2", CSF2Params, "column space fitting with complementary rank-3 spaces and DCT trajectories "
                              "(Gotardo & Martinez, CVPR 2011); occlusion-aware", handles_missing=True)
def solve_csf2(seq: Sequence, params: CSF2Params) -> Reconstruction:
    """CSF2 on an orthographic sequence (missing points allowed). See the module docstring."""

    n_frames, n_points = seq.n_frames, seq.n_points
    vis = seq.weights > 0  # (F, P)
    require_visible_points(seq, "csf2")
    mask = np.repeat(vis, 2, axis=0)  # (2F, P)
    w = seq.measurement_matrix()  # (2F, P)
    unit = power_of_two_unit(w, mask)  # the tracks' units; the shapes are scaled back at the end
    w /= unit
    complete = bool(vis.all())
    # the visible entries' exact rank, if any: for the automatic K and the completion
    max_rank = min(auto_k_max_rank(w), 3 * params.K) if params.K else auto_k_max_rank(w)
    fit = None if complete else visible_rank(w, mask, max_rank)
    k = params.K or auto_k(w, mask, fit=fit)
    if 3 * k > min(2 * n_frames, n_points):
        raise SolverError(f"csf2: K = {k} needs 3K <= min(2F, P) = {min(2 * n_frames, n_points)}; pass a smaller "
                          "K (--set K=...)")
    d = min(params.d or max(int(np.ceil(0.1 * n_frames)), k + 1), n_frames)
    if d < k:  # only a user's d can be: the rule gives d >= K + 1 (3K <= 2F leaves enough frames)
        raise SolverError(f"csf2: d = {d} DCT vectors cannot hold K = {k} orthonormal coefficient columns; pass "
                          f"d >= K (--set d={k}) or a smaller K")
    full, completion = (w, "none") if complete else complete_lowrank(w, mask, 3 * k, fit)
    t = full.mean(axis=1, keepdims=True)  # (2F, 1) translations
    wc = full - t  # (2F, P)
    omega = dct_basis(n_frames, d)  # (F, d)
    rows, cam_residual, cam_cols = camera_rows(wc, params.energy)
    shape_fit = functools.partial(fit_shape_gn, wc, rows, k, d, max_iter=params.max_iter, tol=params.tol,
                                  omega=omega)
    x, basis, it, converged, rmse = shape_fit()
    shape_start = "identity"
    deterministic = {"identity": (x, basis, it, converged, rmse)}
    if params.residual_start and k > 1:
        alt = deterministic["residual"] = shape_fit(x0=residual_start(wc, rows, omega, k))
        if alt[4] < (1 - params.start_margin) * rmse:
            (x, basis, it, converged, rmse), shape_start = alt, "residual"
    rng = np.random.default_rng(0)
    threshold = params.random_accept * rmse
    for i in range(params.random_starts):
        alt = shape_fit(x0=np.linalg.qr(rng.standard_normal((d, k)))[0])
        if alt[4] < min(threshold, rmse):
            (x, basis, it, converged, rmse), shape_start = alt, f"random {i}"
    rot = complete_rotation(rows)
    rounds_run: dict[str, int] = {}
    if completion == "imputed":  # an exact completion is as good as complete tracks: nothing to refine
        # many small products and solves per iteration: BLAS threads cost more than they give here (1102 x 41,
        # 20% missing, 2 cores: 102 s with two BLAS threads, 53 s with this limit; drink 330 s -> 168 s); the
        # two runs of rounds below go on two Python threads instead (drink 114.7 s -> 99.5 s, the same result;
        # 47 s with the race between them, _RoundRace)
        with threadpool_limits(limits=1, user_api="blas"):
            x, basis, rmse = _refine_masked(w - t, mask, rows, omega, x, params.refine_iter, params.ridge)
            scale = float(np.sqrt((rows**2).sum() / (2 * n_frames)))

            def probe(xb: tuple[np.ndarray, np.ndarray, float]) -> float:  # visible RMSE after a few rounds
                if not params.camera_rounds:
                    return xb[2]
                n_probe = min(n for n in (params.round_iter, params.round_iter_alt) if n > 0)  # X/S its a round
                with progress.listen(None):
                    return _occlusion_rounds(w, mask, omega, rot, t.reshape(n_frames, 2), xb[0], xb[1] * scale,
                                             min(_START_PROBE_ROUNDS, params.camera_rounds), n_probe,
                                             params.ridge)[3]

            # the fit to the imputed entries does not rank the deterministic starts (module docstring): the other
            # one is refined on the visible entries too and, where it ends elsewhere, both go a few camera rounds;
            # it is taken when it then fits the visible entries more than start_margin better
            other = {"identity": "residual", "residual": "identity"}.get(shape_start)  # none after a random start
            if other in deterministic:
                fit = deterministic[other]
                alt = _refine_masked(w - t, mask, rows, omega, fit[0], params.refine_iter, params.ridge)
                if abs(alt[2] - rmse) > 1e-4 * rmse and probe(alt) < (1 - params.start_margin) * probe(
                        (x, basis, rmse)):
                    (x, basis, rmse), (it, converged), shape_start = alt, fit[2:4], f"{other} (visible entries)"
            if params.camera_rounds:
                # alternate: cameras and translations on the visible entries, then X and S again (the camera
                # upgrade above saw the imputed entries, whose errors it inherits); from the same start with
                # round_iter and round_iter_alt X/S iterations per round, keeping the lower visible-entry RMSE
                start = (rot, t.reshape(n_frames, 2), x, basis * scale)
                order = [n for n in dict.fromkeys((params.round_iter, params.round_iter_alt)) if n > 0]  # ties: first
                counts = sorted(order)
                race = _RoundRace(params.race_margin, params.race_from) if len(counts) == 2 else None
                # the two runs side by side on two threads: LAPACK releases the GIL, BLAS is on one thread each;
                # the slower one (more X/S iterations per round) stops when it falls behind (_RoundRace)
                listener = progress.current()  # the lead run reports its rounds to this thread's listener

                def rounds(n_als: int, role: str):
                    with progress.listen(listener if role == "lead" else None):
                        return _occlusion_rounds(w, mask, omega, *start, params.camera_rounds, n_als, params.ridge,
                                                 race, role)

                with ThreadPoolExecutor(len(counts)) as pool:
                    runs = dict(zip(counts, pool.map(rounds, counts, ("lead", "follow"))))
                rot, x, basis, rmse, _ = min((runs[n] for n in order), key=lambda run: run[3])
                rounds_run = {str(n): runs[n][4] for n in order}
    shapes_obj = np.einsum("fk,kjp->fpj", omega @ x, basis)  # (F, P, 3) object frame
    points = np.einsum("fij,fpj->fpi", rot, shapes_obj)
    points -= points.mean(axis=1, keepdims=True)
    return Reconstruction(points_3d=points * unit, rotations=rot, method="csf2", iterations=it, converged=converged,
                          info={"K": k, "d": d, "rmse": float(rmse) * unit, "camera_residual": cam_residual,
                                "camera_columns": cam_cols, "shape_start": shape_start, "completion": completion,
                                "rounds": rounds_run})


#: Camera rounds that rank CSF2's two deterministic shape starts when points are missing (module docstring).
_START_PROBE_ROUNDS = 5


def fits_csf2(n_frames: int, n_points: int) -> bool:
    """Whether CSF2 can run: it needs 3K <= min(2F, P) with K >= 2."""
    return min(2 * n_frames, n_points) >= 6


_SHARED_STARTS: contextvars.ContextVar[dict | None] = contextvars.ContextVar("csf2_shared_starts", default=None)


@contextlib.contextmanager
def shared_starts():
    """Within this block, :func:`csf2_start` computes each start once and hands out copies.

    Solvers that run other solvers (the consensus: EM-PND and PR) start both from the same CSF2 reconstruction
    when points are missing (its occlusion-aware form, 50 camera rounds; 10 s of drink with 20% missing). A
    start is known by the tracks' bytes, the visibility, K (the automatic K is stored under the K it chose too,
    where that K given would search the same ranks) and the other settings; the cache ends with the block.
    So is the noise rank of :func:`auto_k` with missing points (most of its 4.9 s on drink with 20% missing),
    which both solvers' automatic K compute.
    """
    token = _SHARED_STARTS.set({})
    try:
        yield
    finally:
        _SHARED_STARTS.reset(token)


def _shared(name: str, key: tuple, compute: Callable[[], Any]) -> Any:
    """``compute()``, or inside :func:`shared_starts` its value for the same ``name`` and ``key`` (arrays in it by
    their bytes) when already computed there."""
    cache = _SHARED_STARTS.get()
    if cache is None:
        return compute()
    digest = hashlib.sha256(name.encode())
    for part in key:
        if isinstance(part, np.ndarray):
            digest.update(f"{part.dtype}{part.shape}".encode())
            digest.update(np.ascontiguousarray(part).tobytes())
        else:
            digest.update(repr(part).encode())
    if digest.hexdigest() not in cache:
        cache[digest.hexdigest()] = compute()
    return cache[digest.hexdigest()]


def csf2_start(seq: Sequence, K: int = 0, **overrides) -> np.ndarray:
    """`(F, P, 3)` CSF2 reconstruction used as another solver's start (EM-PND, PR), ``K`` capped by
    3K <= min(2F, P) (0: the automatic rule); ``overrides``: other :class:`CSF2Params` fields. Check
    :func:`fits_csf2` first. Inside :func:`shared_starts`, computed once per input."""
    k = min(K, min(2 * seq.n_frames, seq.n_points) // 3)
    cache = _SHARED_STARTS.get()
    if cache is None:
        return solve_csf2.__wrapped__(seq, CSF2Params(K=k, **overrides)).points_3d
    digest = hashlib.sha256(np.ascontiguousarray(seq.points_2d, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(seq.weights, dtype=np.float64).tobytes())
    data = (digest.hexdigest(), seq.points_2d.shape, seq.projection, tuple(sorted(overrides.items())))
    if (data, k) not in cache:
        rec = solve_csf2.__wrapped__(seq, CSF2Params(K=k, **overrides))
        cache[data, k] = rec.points_3d
        if 3 * rec.info["K"] >= auto_k_max_rank(np.empty((2 * seq.n_frames, seq.n_points))):
            # the automatic K searched the same ranks as this K given would: the same start
            cache[data, rec.info["K"]] = rec.points_3d
    return cache[data, k].copy()


def _refine_masked(wc: np.ndarray, mask: np.ndarray, rows: np.ndarray, omega: np.ndarray, x: np.ndarray,
                   n_iter: int, ridge: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Alternating least squares on the visible entries of `(2F, P)` wc (S-step, X-step; X re-orthonormalised).

    ``omega`` must be :func:`dct_basis` ``(F, d)``: the X-step's normal matrix uses its cosine structure
    (:func:`dct_weighted_gram_blocks`).

    Returns X `(d, K)`, S `(K, 3, P)` and the RMSE over the visible entries.
    """
    n_frames, n_points = rows.shape[0], wc.shape[1]
    d, k = x.shape
    wmask = mask.reshape(n_frames, 2, n_points).astype(np.float64)  # (F, 2, P)
    vis = wmask[:, 0]  # (F, P)
    target = wc.reshape(n_frames, 2, n_points) * wmask

    def s_step(x: np.ndarray) -> np.ndarray:
        a = np.einsum("fk,fij->fikj", omega @ x, rows).reshape(n_frames, 2, 3 * k)  # (F, 2, 3K)
        return masked_lstsq(a, target, vis, ridge).reshape(k, 3, n_points)

    def _masked_rmse(x: np.ndarray, basis: np.ndarray) -> float:
        shapes = ((omega @ x) @ basis.reshape(k, -1)).reshape(n_frames, 3, n_points)
        resid = (rows @ shapes - target) * wmask
        return float(np.sqrt((resid**2).sum() / wmask.sum()))

    basis = s_step(x)
    prev = np.inf
    rmse = _masked_rmse(x, basis)
    for _ in range(n_iter):
        af = (rows @ basis.transpose(1, 0, 2).reshape(3, -1)).reshape(n_frames, 2, k, n_points).transpose(0, 1, 3, 2)
        af = (af * wmask[..., None]).reshape(n_frames, -1, k)  # (F, 2P, K)
        ata = af.transpose(0, 2, 1) @ af  # (F, K, K)
        atb = (af.transpose(0, 2, 1) @ target.reshape(n_frames, -1, 1))[..., 0]  # (F, K)
        lhs = dct_weighted_gram_blocks(ata, d)  # (dK, dK)
        rhs = (omega.T @ atb).reshape(d * k)
        lhs[np.diag_indices(d * k)] += 1e-10 * np.trace(lhs) / (d * k)
        x = cho_solve(cho_factor(lhs, overwrite_a=True, check_finite=False), rhs, check_finite=False).reshape(d, k)
        x, _ = np.linalg.qr(x)
        basis = s_step(x)
        rmse = _masked_rmse(x, basis)
        if prev - rmse < 1e-6 * prev:
            break
        prev = rmse
    return x, basis, rmse


class _RoundRace:
    """What the two runs of occlusion rounds share: the leading run (fewer X/S iterations per round, so faster)
    posts its RMSE every 10 rounds and never waits; the following run, at rounds ``start``, ``start + 10``, ...,
    waits for the leader's post of the same round (or its end) and stops when its own RMSE is more than
    ``margin`` above it. Only the follower reads the other's numbers, so the result does not depend on thread
    timing. (Drink with 20% missing: the 20-iteration run is 2.9% behind at round 30, 1.8% at 100 and still .9%
    behind at round 200; it stops at round 30 instead of taking the whole run's time. On pickup, yoga, stretch,
    dance, the shark and seven synthetic sequences the slower run is never 2% behind: the same result.)"""

    def __init__(self, margin: float, start: int) -> None:
        self.margin, self.start = margin, start
        self._posts: dict[int, float] = {}
        self._ended = False
        self._cond = threading.Condition()

    def post(self, r: int, rmse: float) -> None:
        with self._cond:
            self._posts[r] = rmse
            self._cond.notify_all()

    def end(self) -> None:
        with self._cond:
            self._ended = True
            self._cond.notify_all()

    def behind(self, r: int, rmse: float) -> bool:
        if not self.start or r < self.start:
            return False
        with self._cond:
            self._cond.wait_for(lambda: r in self._posts or self._ended)
            lead = self._posts.get(r)
        return lead is not None and rmse > (1 + self.margin) * lead


def _occlusion_rounds(w: np.ndarray, mask: np.ndarray, omega: np.ndarray, rot: np.ndarray, t: np.ndarray,
                      x: np.ndarray, basis: np.ndarray, n_rounds: int, n_als: int, ridge: float,
                      race: _RoundRace | None = None, role: str = "lead"):
    """Up to ``n_rounds`` of (cameras and translations by Gauss-Newton, then ``n_als`` X/S iterations) on the
    visible entries; stops when ten rounds improve the RMSE by less than 1e-4 (relative), or, as the ``follow``
    run of a ``race``, when it falls behind the other run (:class:`_RoundRace`).
    Returns the round with the lowest RMSE (the ridge on S lets it rise again): rot `(F, 3, 3)`, X, S, RMSE;
    and the number of rounds run."""
    n_frames = rot.shape[0]
    best = np.inf
    lowest = (rot, x, basis, np.inf)
    r = 0
    try:
        for r in range(1, n_rounds + 1):
            shapes = np.einsum("fk,kjp->fjp", omega @ x, basis)  # (F, 3, P)
            rot, t = _refine_cameras(w, mask, rot, shapes, t)
            x, basis, rmse = _refine_masked(w - t.reshape(2 * n_frames, 1), mask, rot[:, :2], omega, x, n_als, ridge)
            if rmse < lowest[3]:
                lowest = (rot, x, basis, rmse)
            progress.report("csf2", "camera rounds", r, n_rounds, rmse=rmse)
            if r % 10 == 0:
                if race is not None and role == "lead":
                    race.post(r, rmse)
                elif race is not None and race.behind(r, rmse):
                    break
                if rmse > (1 - 1e-4) * best:
                    break
                best = rmse
    finally:
        if race is not None and role == "lead":
            race.end()
    return (*lowest, r)


def _refine_cameras(w: np.ndarray, mask: np.ndarray, rot: np.ndarray, shapes: np.ndarray, t: np.ndarray,
                    steps: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on each frame's rotation (3) and translation (2) over its visible entries.

    ``w`` `(2F, P)` raw tracks, ``mask`` `(2F, P)`, ``rot`` `(F, 3, 3)`, ``shapes`` `(F, 3, P)` object frame,
    ``t`` `(F, 2)`. Rotations are updated as ``R exp([omega]_x)``. Returns the new ``rot`` and ``t``.
    """
    from scipy.spatial.transform import Rotation

    n_frames, n_points = shapes.shape[0], shapes.shape[2]
    wf = w.reshape(n_frames, 2, n_points)
    m = mask.reshape(n_frames, 2, n_points).astype(np.float64)
    sx, sy, sz = shapes[:, 0], shapes[:, 1], shapes[:, 2]
    zero = np.zeros_like(sx)
    # e_k x s for k = x, y, z: (3, F, 3, P)
    crosses = np.stack([np.stack([zero, -sz, sy], 1), np.stack([sz, zero, -sx], 1), np.stack([-sy, sx, zero], 1)])
    ones = np.broadcast_to(np.eye(2)[None, :, :, None], (n_frames, 2, 2, n_points))  # d model / d t
    for _ in range(steps):
        resid = (wf - rot[:, :2] @ shapes - t[:, :, None]) * m  # (F, 2, P)
        jac = np.concatenate([np.stack([rot[:, :2] @ c for c in crosses], axis=1), ones.transpose(0, 2, 1, 3)],
                             axis=1) * m[:, None]  # (F, 5, 2, P)
        jac = jac.reshape(n_frames, 5, 2 * n_points)
        lhs = jac @ jac.transpose(0, 2, 1)
        lhs += 1e-9 * np.trace(lhs, axis1=1, axis2=2)[:, None, None] * np.eye(5)
        step = np.linalg.solve(lhs, (jac @ resid.reshape(n_frames, -1, 1)))[..., 0]  # (F, 5)
        rot = rot @ Rotation.from_rotvec(step[:, :3]).as_matrix()
        t = t + step[:, 3:]
    return rot, t
