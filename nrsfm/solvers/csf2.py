"""CSF2: column space fitting with complementary rank-3 spaces (Gotardo & Martinez, CVPR 2011).

Model (orthographic, centred tracks): ``W = D (C kron I3) S`` with ``D`` `(2F, 3F)` the block-diagonal camera
rows, ``C = Omega_d X`` `(F, K)` shape coefficients on the first ``d`` DCT vectors (smooth trajectories,
:mod:`nrsfm.solvers.dct`) and ``S`` `(3K, P)` the basis shapes. We follow the authors' MATLAB code
(``pgComputeD.m``, ``pgCSF_Bnr_fullW.m``).

1. Cameras (:func:`~nrsfm.solvers.cameras.camera_rows`): the factor ``M = U sqrt(Sigma)`` of the centred W,
   upgraded by a `(n, 3)` corrective matrix grown three columns at a time while the orthonormality residual falls.
   The authors minimise with MATLAB's ``fminunc``; we use BFGS on the analytic gradient.
2. Shape (:func:`fit_shape_gn`): with D fixed, ``X`` `(d, K)` minimises the column-space cost
   ``||W - M M^+ W||^2``, ``M = D (Omega X kron I3)`` (S eliminated in closed form), by damped Gauss-Newton on the
   variable-projection Jacobian (damping 1e-4, x10 on a failed step, /100 on a good one; X re-orthonormalised
   after every step), from the authors' start ``X = I``.

Departures from the authors, each to escape a poor minimum of step 2 (``benchmarks/RESULTS.md``):

* a second start from the rigid fit's residual (:func:`residual_start`), kept when its RMSE is more than
  ``start_margin`` lower (``residual_start=False``: the authors' start only);
* ``random_starts`` random orthonormal starts (fixed seed), kept only when one fits with less than
  ``random_accept`` times the RMSE of the deterministic starts: a different basin, not a slightly better fit.

Missing points (the occlusion-aware variant): W is completed first (:func:`~nrsfm.lowrank.complete_lowrank`,
``info["completion"]``; ``fill`` in :class:`CSF2Params` can complete it by EM-PND's reconstruction instead, the
automatic K's default). Where the visible entries are exactly low-rank (noise-free tracks), that fill is the true
W and CSF2 runs on it as on complete tracks. Otherwise W is completed by a rank-3K hard imputation, steps 1-2 run
on it, and then

* X and S are refined by alternating least squares on the visible entries only (:func:`_refine_masked`; a small
  ``ridge`` on S; the X-step's normal matrix from ``2d - 1`` cosine sums);
* the deterministic start not chosen is refined too; where the two end apart, each goes
  :data:`_START_PROBE_ROUNDS` camera rounds and the one with the lower visible RMSE is kept;
* up to ``camera_rounds`` rounds alternate every frame's rotation and translation by Gauss-Newton on its visible
  entries (:func:`_refine_cameras`) with ``round_iter`` X/S iterations. The rounds run twice from the same start
  (``round_iter`` and ``round_iter_alt`` X/S iterations per round) on two threads, and the lower visible RMSE
  wins; the slower run stops when it falls ``race_margin`` behind (:class:`_RoundRace`, deterministic).

Units: W is divided by the power of two nearest its RMS (:func:`~nrsfm.lowrank.power_of_two_unit`, exact in
floating point) so that tolerances and damping mean the same in any units.

Automatic K and d (``K = 0`` / ``d = 0``; the authors set both by hand): d = ceil(0.1 F) as in the authors' demos,
at least K + 1. K by ``k_rule``: ``"agreement"`` (the default) solves every K from 1 to the cap and keeps the
largest that agrees (within 5%) as well as any with a reconstruction that needs no K, passing over the Ks whose
depth reverses between frames more often than the steadiest K's (:mod:`nrsfm.solvers.kselect`;
with missing points every K runs on the tracks that reconstruction completes, ``info["completion"] = "reference"``);
``"rank"`` takes K from the rank of the tracks (:func:`~nrsfm.solvers.starts.auto_k`, one solve; it takes its cap
on real motion capture, and it is the rule of the CSF2 starts of other solvers). The settings that reproduce the
authors' numbers on the CMU files are a named table in ``benchmarks/classic.py``.
"""

from __future__ import annotations

import dataclasses
import functools
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from nrsfm import progress
from nrsfm.errors import SolverError, ValidationError
from nrsfm.geometry import complete_rotation
from nrsfm.lowrank import complete_lowrank, masked_lstsq, power_of_two_unit
from nrsfm.reconstruction import Reconstruction
from nrsfm.sequence import Sequence
from nrsfm.solvers.cameras import camera_rows
from nrsfm.solvers.dct import dct_basis, dct_weighted_gram_blocks
from nrsfm.solvers.kselect import FILLS, solve_on_reference_fill
from nrsfm.solvers.registry import register, require_visible_points
from nrsfm.solvers.starts import auto_k, auto_k_max_rank, shared_visible_rank


#: How ``K = 0`` chooses K (:class:`CSF2Params`).
K_RULES = ("agreement", "rank")


@dataclass(frozen=True)
class CSF2Params:
    """Parameters of :func:`solve_csf2` (``K = 0`` / ``d = 0``: automatic, see the module docstring).

    Attributes:
        K: number of basis shapes; d: number of DCT vectors.
        k_rule: how ``K = 0`` chooses K: ``"agreement"`` or ``"rank"`` (module docstring).
        fill: how missing points are completed: ``"auto"`` (by EM-PND's reconstruction with the automatic K,
            at rank 3K with a fixed K), ``"reference"`` (always by EM-PND's; one EM-PND solve per tracks) or
            ``"lowrank"`` (always at rank 3K); :data:`~nrsfm.solvers.kselect.FILLS`.
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
    k_rule: str = "agreement"
    fill: str = "auto"
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
        if self.k_rule not in K_RULES:
            raise ValidationError(f"k_rule: expected one of {K_RULES}, got {self.k_rule!r}")
        if self.fill not in FILLS:
            raise ValidationError(f"fill: expected one of {FILLS}, got {self.fill!r}")
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
        # component along X A) with a smaller, positive definite `((d - k) k)` system
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
    if params.K == 0 and params.k_rule == "agreement":
        return _agreement(seq, params)
    if params.fill == "reference" and not seq.is_complete:
        return solve_on_reference_fill(solve_csf2.__wrapped__, seq, params)
    n_frames = seq.n_frames
    vis = seq.weights > 0  # (F, P)
    require_visible_points(seq, "csf2")
    mask = np.repeat(vis, 2, axis=0)  # (2F, P)
    w = seq.measurement_matrix()  # (2F, P)
    unit = power_of_two_unit(w, mask)  # the tracks' units; the shapes are scaled back at the end
    w /= unit
    complete = bool(vis.all())
    # the visible entries' exact rank, if any: for the automatic K and the completion
    max_rank = min(auto_k_max_rank(w), 3 * params.K) if params.K else auto_k_max_rank(w)
    fit = None if complete else shared_visible_rank(w, mask, max_rank)
    k, d = _basis_sizes(w, mask, fit, params)
    full, completion = (w, "none") if complete else complete_lowrank(w, mask, 3 * k, fit)
    t = full.mean(axis=1, keepdims=True)  # (2F, 1) translations
    wc = full - t  # (2F, P)
    omega = dct_basis(n_frames, d)  # (F, d)
    rows, cam_residual, cam_cols = camera_rows(wc, params.energy)
    shape, shape_start, deterministic = _shape_step(wc, rows, k, d, omega, params)
    x, basis, it, converged, rmse = shape
    rot = complete_rotation(rows)
    rounds_run: dict[str, int] = {}
    if completion == "imputed":  # an exact completion is as good as complete tracks: nothing to refine
        rot, (x, basis, rmse), (it, converged), shape_start, rounds_run = _refine_on_visible_entries(
            w, mask, t, rows, rot, omega, shape, shape_start, deterministic, params)
    shapes_obj = np.einsum("fk,kjp->fpj", omega @ x, basis)  # (F, P, 3) object frame
    points = np.einsum("fij,fpj->fpi", rot, shapes_obj)
    points -= points.mean(axis=1, keepdims=True)
    return Reconstruction(points_3d=points * unit, rotations=rot, method="csf2", iterations=it, converged=converged,
                          info={"K": k, "d": d, "rmse": float(rmse) * unit, "camera_residual": cam_residual,
                                "camera_columns": cam_cols, "shape_start": shape_start, "completion": completion,
                                "rounds": rounds_run, "k_rule": params.k_rule if params.K == 0 else None})


def _agreement(seq: Sequence, params: CSF2Params) -> Reconstruction:
    """CSF2 with the K that agrees with a reconstruction that needs no K (:mod:`nrsfm.solvers.kselect`)."""
    from nrsfm.solvers.kselect import k_candidates, solve_by_agreement

    ks = k_candidates(seq.n_frames, seq.n_points)
    if len(ks) == 1:
        rec = solve_csf2.__wrapped__(seq, dataclasses.replace(params, K=1))
        rec.info.update(k_rule="agreement")
        return rec
    return solve_by_agreement(seq, params, "csf2", list(ks), "rank")


def _basis_sizes(w: np.ndarray, mask: np.ndarray, fit: tuple[int, np.ndarray | None] | None,
                 params: CSF2Params) -> tuple[int, int]:
    """K (given, or :func:`~nrsfm.solvers.starts.auto_k`) and d (given, or ceil(0.1 F) and at least K + 1) for the
    unit-scaled `(2F, P)` ``w``; a clear error where they cannot fit the sequence."""
    n_frames, n_points = w.shape[0] // 2, w.shape[1]
    k = params.K or auto_k(w, mask, fit=fit)
    if 3 * k > min(2 * n_frames, n_points):
        raise SolverError(f"csf2: K = {k} needs 3K <= min(2F, P) = {min(2 * n_frames, n_points)}; pass a smaller "
                          "K (--set K=...)")
    d = min(params.d or max(int(np.ceil(0.1 * n_frames)), k + 1), n_frames)
    if d < k:  # only a user's d can be: the rule gives d >= K + 1 (3K <= 2F leaves enough frames)
        raise SolverError(f"csf2: d = {d} DCT vectors cannot hold K = {k} orthonormal coefficient columns; pass "
                          f"d >= K (--set d={k}) or a smaller K")
    return k, d


def _shape_step(wc: np.ndarray, rows: np.ndarray, k: int, d: int, omega: np.ndarray, params: CSF2Params):
    """Step 2 from the authors' start, the residual start and the random starts (module docstring).

    Returns:
        The kept fit ``(X, S, iterations, converged, RMSE)`` of :func:`fit_shape_gn`, the name of its start, and
        the fits of the deterministic starts by name.
    """
    shape_fit = functools.partial(fit_shape_gn, wc, rows, k, d, max_iter=params.max_iter, tol=params.tol,
                                  omega=omega)
    best = shape_fit()
    shape_start = "identity"
    deterministic = {"identity": best}
    if params.residual_start and k > 1:
        alt = deterministic["residual"] = shape_fit(x0=residual_start(wc, rows, omega, k))
        if alt[4] < (1 - params.start_margin) * best[4]:
            best, shape_start = alt, "residual"
    rng = np.random.default_rng(0)
    threshold = params.random_accept * best[4]
    for i in range(params.random_starts):
        alt = shape_fit(x0=np.linalg.qr(rng.standard_normal((d, k)))[0])
        if alt[4] < min(threshold, best[4]):
            best, shape_start = alt, f"random {i}"
    return best, shape_start, deterministic


def _refine_on_visible_entries(w: np.ndarray, mask: np.ndarray, t: np.ndarray, rows: np.ndarray, rot: np.ndarray,
                               omega: np.ndarray, shape: tuple, shape_start: str, deterministic: dict,
                               params: CSF2Params):
    """The missing-point refinement of the module docstring, after steps 1-2 on the imputed W.

    Args:
        w: `(2F, P)` unit-scaled tracks; mask: `(2F, P)` visible entries; t: `(2F, 1)` translations of the
            completion; rows: `(F, 2, 3)` camera rows and rot `(F, 3, 3)` their rotations; omega: `(F, d)` DCT
            basis; shape, shape_start, deterministic: :func:`_shape_step`'s result.

    Returns:
        ``rot``, ``(X, S, RMSE)`` on the visible entries, ``(iterations, converged)`` of the shape step, the
        start's name and the rounds each run of camera rounds took.
    """
    n_frames = rows.shape[0]
    x, basis, it, converged, rmse = shape
    rounds_run: dict[str, int] = {}
    # many small products and solves per iteration: BLAS threads cost more than they give here, so BLAS runs
    # on one thread and the two runs of rounds below go on two Python threads instead
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
    return rot, (x, basis, rmse), (it, converged), shape_start, rounds_run


#: Camera rounds that rank CSF2's two deterministic shape starts when points are missing (module docstring).
_START_PROBE_ROUNDS = 5


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
    posts its RMSE every 10 rounds and never waits; the following run, at rounds ``start``, ``start + 10``, ..., waits
    for the leader's post of the same round (or its end) and stops when its own RMSE is more than ``margin`` above
    it. Only the follower reads the other's numbers, so the result does not depend on thread timing.
    """

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
