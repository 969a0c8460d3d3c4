"""PR: per-sequence Procrustean regression (Park, Lee & Kwak, IEEE TIP 2018).

Model: the camera-frame shapes ``X_f = [x_f; y_f; z_f]`` `(3, P)` keep the
observed image coordinates of visible points (orthographic camera) and have
free depths ``z_f`` (and free x, y for missing points). The depths minimise
the low-rank regulariser of the PR cost on the Procrustes-aligned shapes,

    min_z  g(Z~),   Z_f = R_f X_f T,  R = GPA alignment to the mean aligned shape,

with ``g`` the nuclear norm smoothed as ``sum_k sqrt(s_k^2 + e^2)`` and ``e``
decreased over a few continuation stages (a consistent objective inside a
stage, so L-BFGS sees a fixed function). The gradient comes from the shared
analytic alignment gradient (:func:`nrsfm.procrustes.align_vjp`; an exact
O(F P^2) Woodbury solve for long sequences), and each evaluation warm-starts
the alignment from the previous rotations. Initialisation: the rank-3 rigid
factorisation of the (imputed) tracks.

The data term of the PRN loss becomes a hard constraint here because
per-sequence NRSfM inputs are exact projections; with noisy tracks use a
small ``smoothing_end`` and expect the reprojection to be exact anyway.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nrsfm.errors import SolverError, ValidationError
from nrsfm.sequence import Sequence
from nrsfm.solvers.base import Reconstruction, impute_lowrank, register, require_visible_points


@dataclass(frozen=True)
class PRParams:
    """Parameters of :func:`solve_pr`.

    Attributes:
        smoothing_start / smoothing_end: relative smoothing ``e / s_max`` of
            the nuclear norm at the first and last continuation stage.
        stages: continuation stages (geometric steps from start to end).
        max_iter: L-BFGS iterations per stage.
        tol: L-BFGS relative function tolerance.
        impute_rank: rank of the measurement-matrix imputation used to
            initialise missing points (0 = 3 * 3).
    """

    smoothing_start: float = 1e-2
    smoothing_end: float = 1e-4
    stages: int = 3
    max_iter: int = 150
    tol: float = 1e-10
    impute_rank: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.smoothing_end <= self.smoothing_start < 1:
            raise ValidationError(f"smoothing: expected 0 < smoothing_end <= smoothing_start < 1, got "
                                  f"{self.smoothing_end}, {self.smoothing_start}")
        if self.stages < 1 or self.max_iter < 1:
            raise ValidationError(f"stages, max_iter: expected >= 1, got {self.stages}, {self.max_iter}")


@register("pr", PRParams, "Procrustean regression: low-rank aligned shapes by analytic-gradient L-BFGS "
                          "(Park et al., TIP 2018)", handles_missing=True)
def solve_pr(seq: Sequence, params: PRParams) -> Reconstruction:
    """Per-sequence PR. See the module docstring for the model."""
    import scipy.optimize
    import torch

    from nrsfm.procrustes import align, align_vjp, smoothed_nuclear_norm_and_gradient
    from nrsfm.solvers.rank3 import Rank3Params, solve_rank3

    if seq.projection != "orthographic":
        raise SolverError(f"pr: expected orthographic tracks, got {seq.projection}; normalise perspective "
                          "detections with the intrinsics first")
    n_frames, n_points = seq.n_frames, seq.n_points
    if n_points < 4:
        raise SolverError(f"pr: expected at least 4 points, got {n_points}")
    visible = require_visible_points(seq, "pr")  # (F, P)
    w = seq.measurement_matrix()  # (2F, P)
    if not visible.all():
        mask = np.repeat(visible, 2, axis=0)
        w = impute_lowrank(w, mask, params.impute_rank or 9)
    p2 = w.reshape(n_frames, 2, n_points).transpose(0, 2, 1)  # (F, P, 2)
    p2 = p2 - p2.mean(axis=1, keepdims=True)
    scale = np.sqrt((p2**2).sum() / n_frames)
    if scale <= 0:
        raise SolverError("pr: all points coincide; nothing to reconstruct")
    p2 = p2 / scale
    init = solve_rank3.__wrapped__(Sequence(points_2d=p2), Rank3Params())
    free_xy = ~visible  # (F, P)
    n_free_xy = int(free_xy.sum())
    x0 = np.concatenate([init.points_3d[..., 2].ravel(), p2[free_xy].ravel()])
    state = {"rot": None, "evals": 0}

    def unpack(v: np.ndarray) -> np.ndarray:
        shapes = np.empty((n_frames, n_points, 3))
        shapes[..., :2] = p2
        shapes[..., 2] = v[: n_frames * n_points].reshape(n_frames, n_points)
        if n_free_xy:
            shapes[free_xy, :2] = v[n_frames * n_points:].reshape(-1, 2)
        return shapes

    def objective(v: np.ndarray, smoothing: float):
        state["evals"] += 1
        x = torch.as_tensor(unpack(v).transpose(0, 2, 1)[None])  # (1, F, 3, P)
        al = align(x, init=state["rot"], tol=1e-12)
        state["rot"] = al.rotations
        val, grad_z = smoothed_nuclear_norm_and_gradient(al.aligned, smoothing)
        g = align_vjp(grad_z, al)[0].numpy().transpose(0, 2, 1)  # (F, P, 3)
        out = np.concatenate([g[..., 2].ravel(), g[free_xy, :2].ravel()])
        return float(val.sum()), out

    v = x0
    iterations = 0
    converged = True
    s_max = np.linalg.svd(init.points_3d.reshape(n_frames, -1), compute_uv=False)[0]
    for e_rel in np.geomspace(params.smoothing_start, params.smoothing_end, params.stages):
        res = scipy.optimize.minimize(objective, v, args=(float(e_rel * s_max),), jac=True, method="L-BFGS-B",
                                      options={"maxiter": params.max_iter, "ftol": params.tol, "gtol": 1e-12})
        v = res.x
        iterations += int(res.nit)
        converged = bool(res.success)
    shapes = unpack(v)
    al = align(torch.as_tensor(shapes.transpose(0, 2, 1)[None]), init=state["rot"])
    rotations = al.rotations[0].numpy().transpose(0, 2, 1)  # object -> camera is R_f^T
    shapes = (shapes - shapes.mean(axis=1, keepdims=True)) * scale
    if not np.isfinite(shapes).all():
        raise SolverError("pr: the optimisation diverged (non-finite depths); try a larger smoothing_end")
    return Reconstruction(points_3d=shapes, rotations=rotations, method="pr", iterations=iterations,
                          converged=converged, info={"evaluations": state["evals"], "final_cost": float(res.fun)})
