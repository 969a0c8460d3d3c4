"""PR: per-sequence Procrustean regression (Park, Lee & Kwak, IEEE TIP 2018).

Model: the camera-frame shapes ``X_f = [x_f; y_f; z_f]`` `(3, P)` keep the observed image coordinates of visible
points (orthographic camera) and have free depths ``z_f`` (and free x, y for missing points). The depths minimise a
low-rank regulariser of the Procrustes-aligned shapes,

    min_z  g(Z~),   Z_f = R_f X_f T,  R = GPA alignment to the mean aligned shape.

The gradient comes from the shared analytic alignment gradient (:func:`nrsfm.procrustes.align_vjp`; an exact
O(F P^2) Woodbury solve for long sequences), minimised by L-BFGS; each evaluation warm-starts the alignment from
the previous rotations. The data term of the PRN loss becomes a hard constraint here because per-sequence NRSfM
inputs are exact projections.

Two regularisers (``regulariser``), the two the PRN paper names (Sec. 3.3):

- ``"logdet"`` (default): ``sum_k log sqrt(s_k^2 + delta^2)`` of the singular values ``s_k`` of the aligned shapes
  minus their mean shape (``centre``), with ``delta`` = ``delta_rel`` times the largest singular value of the
  starting shapes. The nuclear norm pays for the size of every singular value, so its minimiser flattens the
  shapes; the log-determinant does not. It is not convex, so the start matters: CSF2's reconstruction
  (``init="csf2"``, the default) or the rigid factorisation.
- ``"nuclear"``: the paper's nuclear norm, smoothed as ``sum_k sqrt(s_k^2 + e^2)`` with ``e`` decreased from
  ``smoothing_start`` to ``smoothing_end`` (times the largest singular value) over ``stages`` continuation stages.
  ``regulariser=nuclear centre=false init=rigid`` is the TIP paper's formulation.

Missing points: their x, y are free variables like the depths. The tracks are first completed: exactly where the
visible entries are exactly low-rank (noise-free tracks), else by a rank-3K imputation (CSF2's rank-rule K). The
completion fixes the objective (each frame's centring, the scale and ``delta``). On imputed tracks the free
variables then start from CSF2's occlusion-aware reconstruction (``start_rounds`` camera rounds), which fits the
visible entries only, since the imputation can be far off where a point is missing long. Sequences too small for
CSF2 (``min(2F, P) < 6``) or where it fails fall back to the rigid start, recorded in ``info["init"]``.

Threads: L-BFGS runs with numpy's BLAS on one thread (``threadpoolctl``): each evaluation mixes torch's batched
`(3, 3)` work with numpy, and two thread pools busy-waiting on the same cores slow it down. torch's own thread
count is left alone (changing it can hang MKL, pytorch#141358).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from nrsfm.errors import SolverError, ValidationError
from nrsfm.progress import report
from nrsfm.sequence import Sequence
from nrsfm.lowrank import complete_lowrank, visible_rank
from nrsfm.reconstruction import Reconstruction
from nrsfm.solvers.rank3 import Rank3Params, solve_rank3
from nrsfm.solvers.registry import register, require_visible_points
from nrsfm.solvers.starts import auto_k, auto_k_max_rank, csf2_start, fits_csf2

log = logging.getLogger(__name__)


REGULARISERS = ("logdet", "nuclear")
PR_INITS = ("csf2", "rigid")


@dataclass(frozen=True)
class PRParams:
    """Parameters of :func:`solve_pr`.

    Attributes:
        regulariser: ``"logdet"`` (default) or ``"nuclear"`` (the paper's); see the module docstring.
        centre: regularise the aligned shapes minus their mean shape (default) or the aligned shapes.
        delta_rel: log-determinant offset relative to the largest singular value of the start.
        init: ``"csf2"`` (default: CSF2's reconstruction) or ``"rigid"`` (the rank-3 factorisation).
        init_K: CSF2's K for the start (0: CSF2's rank rule; with missing points the rule runs once on the
            visible entries, not on the completion, whose W is never exactly low-rank).
        smoothing_start / smoothing_end: relative smoothing ``e / s_max`` of the nuclear norm at the first and last
            continuation stage.
        stages: continuation stages of the nuclear norm (geometric steps from start to end).
        max_iter: L-BFGS iterations (per stage for the nuclear norm).
        tol: L-BFGS relative function tolerance.
        impute_rank: rank of the measurement-matrix completion (:func:`~nrsfm.lowrank.complete_lowrank`) used to
            initialise missing points (0: 3K with CSF2's rank-rule K, the rank CSF2 imputes with).
        start_rounds: with missing points on tracks that are not exactly low-rank, the free variables start from
            CSF2's occlusion-aware reconstruction cut to this many camera rounds (module docstring, "Missing
            points"); 0: from CSF2 on the imputed tracks.
    """

    regulariser: str = "logdet"
    centre: bool = True
    delta_rel: float = 1e-3
    init: str = "csf2"
    init_K: int = 0
    smoothing_start: float = 1e-2
    smoothing_end: float = 1e-4
    stages: int = 3
    max_iter: int = 2000
    tol: float = 1e-10
    impute_rank: int = 0
    start_rounds: int = 50

    def __post_init__(self) -> None:
        if self.regulariser not in REGULARISERS:
            raise ValidationError(f"regulariser: expected one of {', '.join(REGULARISERS)}, got {self.regulariser!r}")
        if self.init not in PR_INITS:
            raise ValidationError(f"init: expected one of {', '.join(PR_INITS)}, got {self.init!r}")
        if not 0 < self.delta_rel < 1:
            raise ValidationError(f"delta_rel: expected a value in (0, 1), got {self.delta_rel}")
        if self.init_K < 0:
            raise ValidationError(f"init_K: expected >= 0 (0 = automatic), got {self.init_K}")
        if not 0 < self.smoothing_end <= self.smoothing_start < 1:
            raise ValidationError(f"smoothing: expected 0 < smoothing_end <= smoothing_start < 1, got "
                                  f"{self.smoothing_end}, {self.smoothing_start}")
        if self.start_rounds < 0:
            raise ValidationError(f"start_rounds: expected >= 0, got {self.start_rounds}")
        if self.stages < 1 or self.max_iter < 1:
            raise ValidationError(f"stages, max_iter: expected >= 1, got {self.stages}, {self.max_iter}")


@register("pr", PRParams, "Procrustean regression: low-rank aligned shapes by analytic-gradient L-BFGS "
                          "(Park et al., TIP 2018)", handles_missing=True)
def solve_pr(seq: Sequence, params: PRParams) -> Reconstruction:
    """Per-sequence PR. See the module docstring for the model."""
    import scipy.optimize
    import torch
    from threadpoolctl import threadpool_limits

    from nrsfm.procrustes import align, align_vjp, log_det_and_gradient, smoothed_nuclear_norm_and_gradient

    n_frames, n_points = seq.n_frames, seq.n_points
    visible = require_visible_points(seq, "pr")  # (F, P)
    mask = np.repeat(visible, 2, axis=0)  # (2F, P)
    w, completion, params = _complete(seq.measurement_matrix(), mask, params)
    p2 = w.reshape(n_frames, 2, n_points).transpose(0, 2, 1)  # (F, P, 2)
    centre = p2.mean(axis=1, keepdims=True)  # (F, 1, 2)
    p2 = p2 - centre
    scale = np.sqrt((p2**2).sum() / n_frames)
    if scale <= 0:
        raise SolverError("pr: all points coincide; nothing to reconstruct")
    p2 = p2 / scale
    start, init_used = _start(p2, params)  # (F, P, 3); its largest singular value sets delta below
    s_max = float(np.linalg.svd(start.reshape(n_frames, -1), compute_uv=False)[0])
    if completion == "imputed" and init_used == "csf2" and params.start_rounds > 0:
        occluded = _occlusion_aware_start(seq, params)  # (F, P, 3) camera frame, data units
        if occluded is not None:
            # the same objective (the imputed tracks' centring and scale, delta from the start above); only the
            # free variables start elsewhere (module docstring, "Missing points")
            filled = _fill_from_shapes(seq.measurement_matrix(), mask, occluded)
            xy = (filled.reshape(n_frames, 2, n_points).transpose(0, 2, 1) - centre) / scale
            z = (occluded[..., 2:] - occluded[..., 2:].mean(axis=1, keepdims=True)) / scale
            start, init_used = np.concatenate([xy, z], axis=2), "csf2-occlusion"
    free_xy = ~visible  # (F, P)
    n_free_xy = int(free_xy.sum())
    state = {"rot": None, "evals": 0, "steps": 0}

    def unpack(v: np.ndarray) -> np.ndarray:
        shapes = np.empty((n_frames, n_points, 3))
        shapes[..., :2] = p2
        shapes[..., 2] = v[: n_frames * n_points].reshape(n_frames, n_points)
        if n_free_xy:
            shapes[free_xy, :2] = v[n_frames * n_points:].reshape(-1, 2)
        return shapes

    def objective(v: np.ndarray, offset: float):
        state["evals"] += 1
        x = torch.as_tensor(unpack(v).transpose(0, 2, 1)[None])  # (1, F, 3, P)
        al = align(x, init=state["rot"], tol=1e-12)
        state["rot"] = al.rotations
        z = al.aligned - al.aligned.mean(dim=1, keepdim=True) if params.centre else al.aligned
        if params.regulariser == "logdet":
            val, grad_z = log_det_and_gradient(z, offset)
        else:
            val, grad_z = smoothed_nuclear_norm_and_gradient(z, offset)
        if params.centre:  # the adjoint of removing the mean over frames
            grad_z = grad_z - grad_z.mean(dim=1, keepdim=True)
        g = align_vjp(grad_z, al)[0].numpy().transpose(0, 2, 1)  # (F, P, 3)
        out = np.concatenate([g[..., 2].ravel(), g[free_xy, :2].ravel()])
        return float(val.sum()), out

    if params.regulariser == "logdet":
        offsets = [params.delta_rel * s_max]
    else:
        offsets = list(np.geomspace(params.smoothing_start, params.smoothing_end, params.stages) * s_max)

    def step_done(intermediate_result) -> None:  # scipy passes the iterate's OptimizeResult by this name
        state["steps"] += 1
        report("pr", "L-BFGS", state["steps"], params.max_iter * len(offsets), cost=intermediate_result.fun)

    v = np.concatenate([start[..., 2].ravel(), start[..., :2][free_xy].ravel()])
    iterations = 0
    converged = True
    with threadpool_limits(limits=1, user_api="blas"):  # see "Threads" in the module docstring
        for offset in offsets:
            res = scipy.optimize.minimize(objective, v, args=(float(offset),), jac=True, method="L-BFGS-B",
                                          callback=step_done,
                                          options={"maxiter": params.max_iter, "ftol": params.tol, "gtol": 1e-12})
            v = res.x
            iterations += int(res.nit)
            converged = bool(res.success)
    shapes = unpack(v)
    al = align(torch.as_tensor(shapes.transpose(0, 2, 1)[None]), init=state["rot"])
    rotations = al.rotations[0].numpy().transpose(0, 2, 1)  # object -> camera is R_f^T
    shapes = (shapes - shapes.mean(axis=1, keepdims=True)) * scale
    if not np.isfinite(shapes).all():
        raise SolverError("pr: the optimisation diverged (non-finite depths); try regulariser=nuclear or a "
                          "larger delta_rel")
    return Reconstruction(points_3d=shapes, rotations=rotations, method="pr", iterations=iterations,
                          converged=converged, info={"evaluations": state["evals"], "final_cost": float(res.fun),
                                                     "init": init_used, "init_K": params.init_K,
                                                     "impute_rank": params.impute_rank,
                                                     "completion": completion})


def _complete(w: np.ndarray, mask: np.ndarray, params: PRParams) -> tuple[np.ndarray, str, PRParams]:
    """`(2F, P)` ``w`` completed where ``mask`` hides entries (module docstring, "Missing points"), how
    (``"none"``, ``"exact"``, ``"imputed"``), and ``params`` with the automatic ``init_K`` and ``impute_rank``
    filled in."""
    if mask.all():
        return w, "none", params
    max_rank = auto_k_max_rank(w)
    if params.impute_rank and params.init_K:
        max_rank = min(max_rank, params.impute_rank)
    # the visible entries' exact rank, if any, for one K (CSF2's rule on a completion sees a full-rank W) and for
    # the completion
    fit = visible_rank(w, mask, max_rank)
    if not (params.impute_rank and params.init_K):
        k = auto_k(w, mask, fit=fit)
        params = replace(params, impute_rank=params.impute_rank or 3 * k, init_K=params.init_K or k)
    filled, completion = complete_lowrank(w, mask, params.impute_rank, fit)
    return filled, completion, params


def _occlusion_aware_start(seq: Sequence, params: PRParams) -> np.ndarray | None:
    """`(F, P, 3)` camera-frame shapes of CSF2's occlusion-aware form on ``seq`` (K: ``params.init_K``), cut
    to ``params.start_rounds`` camera rounds of 5 X/S iterations (EM-PND's start with missing points); None
    where it fails."""
    try:
        return csf2_start(seq, params.init_K, camera_rounds=params.start_rounds, round_iter=5, round_iter_alt=0)
    except SolverError as err:
        log.info("pr: CSF2's occlusion-aware start failed (%s); starting from the imputed tracks", err)
        return None


def _fill_from_shapes(w: np.ndarray, mask: np.ndarray, shapes: np.ndarray) -> np.ndarray:
    """`(2F, P)` ``w`` with its missing entries (``mask`` False) replaced by the image coordinates of the
    `(F, P, 3)` camera-frame ``shapes`` plus each frame's translation, fitted on its visible entries."""
    n_frames, n_points = shapes.shape[:2]
    model = shapes[..., :2].transpose(0, 2, 1).reshape(2 * n_frames, n_points)  # (2F, P)
    count = mask.sum(axis=1, keepdims=True)
    shift = np.where(mask, w - model, 0.0).sum(axis=1, keepdims=True) / np.maximum(count, 1)
    return np.where(mask, w, model + shift)


def _start(p2: np.ndarray, params: PRParams) -> tuple[np.ndarray, str]:
    """`(F, P, 3)` starting shapes for the normalised, centred, completed tracks ``p2`` `(F, P, 2)`, and the
    start used (``"csf2"`` falls back to ``"rigid"`` where CSF2 cannot run)."""
    seq = Sequence(points_2d=p2)
    if params.init == "csf2" and fits_csf2(seq.n_frames, seq.n_points):
        try:
            return csf2_start(seq, params.init_K), "csf2"
        except SolverError as err:
            log.info("pr: CSF2's start failed (%s); starting from the rigid factorisation", err)
    elif params.init == "csf2":
        log.info("pr: min(2F, P) = %d is too small for CSF2's start; starting from the rigid factorisation",
                 min(2 * seq.n_frames, seq.n_points))
    return solve_rank3.__wrapped__(seq, Rank3Params()).points_3d, "rigid"
