"""SPM / BMM: "A simple prior-free method for non-rigid structure from motion" (Dai, Li & He, CVPR 2012).

Rotation (cameras):

1. the rank-3K factor ``Pi`` `(2F, 3K)` of the centred W;
2. ``Q = G G^T`` `(3K, 3K)`, PSD, with each frame's two rows of ``Pi`` giving equal norms and orthogonality
   (``a Q a^T = b Q b^T``, ``a Q b^T = 0``): a convex program in cvxpy, least squares on those constraints plus a
   small trace (low-rank) term under the normalisation mean(``a Q a^T + b Q b^T``)/2 = 1 (the authors solve an SDP
   with SDPT3);
3. rank-3 truncation ``G`` = top eigenvectors; nonlinear refinement of ``G`` on the scale-invariant orthonormality
   residual (:func:`~nrsfm.solvers.cameras.refine_triple`);
4. per frame: normalise the rows, third row by cross product. The sign of each frame's scale is ambiguous (a
   camera flipped by 180 degrees about the optical axis). The authors keep the sign within 90 degrees of the
   previous frame, which breaks when the camera jumps (PRN's camera alternation); we compare every frame with the
   cameras of the corrective-matrix upgrade (:func:`~nrsfm.solvers.cameras.camera_rows`, whose signs are
   consistent by construction) after one global alignment, so no temporal order is used.

Shape: with ``S_f = R_f^T [W_f; z_f]`` (exact reprojection), minimise the nuclear norm of ``S#`` `(F, 3P)` (rows
``[X_f Y_f Z_f]``) over the depths ``z``: with cvxpy where its semidefinite block is small (``F + 3P <=
cvxpy_limit``), by ADMM otherwise (:func:`shape_admm`); the two agree on small problems. The authors' fixed-point
continuation is kept as ``shape_solver="fpc"`` (with their 20 stages it can stop short of the minimum). An optional
final rank-K truncation follows the authors' code.

Options that are not the authors' method, off by default:

* ``shape_objective="partial"``: the sum of the singular values beyond the K largest (Oh et al., TPAMI 2016) from
  the nuclear norm's depths (:func:`shape_partial`). The nuclear norm also shrinks the singular values that carry
  the basis shapes, so its minimum is not the shape when the camera turns through a short arc. Not convex.
* ``refine_cameras=true``: the cameras refined by the shape step's nuclear norm (:func:`refine_cameras_nuclear`).

Missing points (not in the authors' method, which needs complete tracks): W is completed at rank 3K first, as CSF2
completes it (:func:`~nrsfm.lowrank.complete_lowrank`: exactly where the visible entries are low-rank, else by hard
imputation; ``info["completion"]``), and SPM runs on the completed tracks. The energy rule's K then starts from its
floor (2): while the rule finds a larger K on the tracks completed at 3K, they are completed again at that K's 3K
(3K + 1 < min(2F, P), K <= 8). ``fill`` chooses the completion (:class:`SPMParams`): the automatic K's
default fills the tracks by EM-PND's reconstruction instead.

K (``K = 0``), by ``k_rule``: ``"agreement"`` (the default) solves every K from 2 (the energy rule's floor) to
12 with 3K < min(2F, P) and keeps the largest that agrees (within 5%) as well as any with EM-PND's
reconstruction, passing over the Ks whose depth reverses between frames more often than the steadiest K's
(:mod:`nrsfm.solvers.kselect`; with missing points every K runs on the tracks EM-PND's
reconstruction completes, not at rank 3K: ``info["completion"] = "reference"``);
``"energy"`` is :func:`auto_rank`, one solve: ``ceil(r / 3)`` for rank-deficient tracks of numerical rank ``r``,
else the smallest K whose 3K singular values hold 99.5% of the energy. The authors' K per CMU file is a settings
table of ``benchmarks/classic.py``.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from nrsfm.errors import SolverError, ValidationError
from nrsfm.geometry import complete_rotation, nearest_rotation
from nrsfm.progress import report
from nrsfm.sequence import Sequence
from nrsfm.lowrank import complete_lowrank, power_of_two_unit
from nrsfm.reconstruction import Reconstruction
from nrsfm.solvers.cameras import camera_rows, refine_triple
from nrsfm.solvers.kselect import FILLS, solve_on_reference_fill
from nrsfm.solvers.registry import register, require_visible_points

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class SPMParams:
    """Parameters of :func:`solve_spm` (``K = 0``: automatic).

    Attributes:
        K: number of basis shapes (0: automatic, by ``k_rule``: ``"agreement"`` or ``"energy"``; module docstring).
        fill: how missing points are completed: ``"auto"`` (by EM-PND's reconstruction with the automatic K,
            at rank 3K with a fixed K), ``"reference"`` (always by EM-PND's; one EM-PND solve per tracks) or
            ``"lowrank"`` (always at rank 3K); :data:`~nrsfm.solvers.kselect.FILLS`.
        shape_solver: ``"cvxpy"``, ``"admm"``, ``"fpc"`` or ``"auto"`` (cvxpy when F + 3P <= cvxpy_limit, else ADMM).
        trace_weight: weight of trace(Q) in the rotation program (relative).
        shape_objective: ``"nuclear"`` (the authors': the nuclear norm of ``S#``) or ``"partial"`` (the sum of its
            singular values beyond the K largest, :func:`shape_partial`, from the nuclear norm's depths; not the
            authors' method, off by default).
        truncate: final rank-K truncation of the shape matrix.
        admm_tol / admm_max_iter: relative residual tolerance and iteration cap of :func:`shape_admm`.
        fpc_outer / fpc_inner / fpc_tol: continuation stages, inner steps, inner tolerance (the authors' FPC).
        refine_cameras: after the camera step, refine the cameras by the shape step's own objective
            (:func:`refine_cameras_nuclear`; not the authors' method, off by default).
        refine_weight / refine_iter: the orthonormality residual's weight and the L-BFGS iterations of that step.
    """

    K: int = 0
    k_rule: str = "agreement"
    fill: str = "auto"
    shape_solver: str = "auto"
    shape_objective: str = "nuclear"
    trace_weight: float = 1e-4
    truncate: bool = False
    admm_tol: float = 1e-4
    admm_max_iter: int = 5000
    fpc_tau: float = 0.2
    fpc_outer: int = 20
    fpc_inner: int = 100
    fpc_tol: float = 1e-7
    cvxpy_limit: int = 64
    refine_cameras: bool = False
    refine_weight: float = 3.0
    refine_iter: int = 300

    def __post_init__(self) -> None:
        if self.k_rule not in ("agreement", "energy"):
            raise ValidationError(f"k_rule: expected 'agreement' or 'energy', got {self.k_rule!r}")
        if self.fill not in FILLS:
            raise ValidationError(f"fill: expected one of {FILLS}, got {self.fill!r}")
        if self.shape_solver not in ("auto", "cvxpy", "admm", "fpc"):
            raise ValidationError(f"shape_solver: expected 'auto', 'cvxpy', 'admm' or 'fpc', got {self.shape_solver!r}")
        if self.shape_objective not in ("nuclear", "partial"):
            raise ValidationError(f"shape_objective: expected 'nuclear' or 'partial', got {self.shape_objective!r}")
        if not (0 < self.admm_tol < 1 and self.admm_max_iter >= 1):
            raise ValidationError(f"SPMParams: expected 0 < admm_tol < 1 and admm_max_iter >= 1, got {self.admm_tol}, "
                                  f"{self.admm_max_iter}")
        if not (np.isfinite(self.refine_weight) and self.refine_weight >= 0 and self.refine_iter >= 1):
            raise ValidationError(f"SPMParams: expected refine_weight >= 0 and refine_iter >= 1, got "
                                  f"{self.refine_weight}, {self.refine_iter}")
        if self.K < 0 or not 0 < self.fpc_tau <= 1.9:
            raise ValidationError(f"SPMParams: expected K >= 0 and 0 < fpc_tau <= 1.9, got {self.K}, {self.fpc_tau}")


def auto_rank(w: np.ndarray, energy: float = 0.995, k_min: int = 2, k_max: int = 8, rel_tol: float = 1e-8) -> int:
    """SPM's automatic K for a centred `(2F, P)` W: ``ceil(r / 3)`` when W is rank deficient, of numerical rank
    ``r <= 3 k_max`` below ``min(2F, P - 1)`` (singular values below ``rel_tol`` of the largest are zero: noise-free
    tracks), else the smallest K whose 3K singular values hold ``energy`` of the total; within ``[k_min, k_max]``.

    The rank comes first because the energy rule under-counts exactly low-rank tracks whose last basis shape moves
    little.
    """
    s = np.linalg.svd(w, compute_uv=False)
    rank = int((s > rel_tol * s[0]).sum()) if s.size and s[0] > 0 else 0
    if rank <= 3 * k_max and rank < min(w.shape[0], w.shape[1] - 1):
        return min(k_max, max(k_min, -(-rank // 3)))
    cum = np.cumsum(s**2) / (s**2).sum()
    for k in range(k_min, k_max + 1):
        if cum[min(3 * k, len(cum)) - 1] >= energy:
            return k
    return k_max


def choose_k(wm: np.ndarray, k: int = 0) -> int:
    """SPM's K for a `(2F, P)` W: ``k`` when given, else :func:`auto_rank`; at most min(2F, P) // 3."""
    k = k or auto_rank(wm)
    return max(1, min(k, min(wm.shape) // 3))


def rotation_program(pi: np.ndarray, trace_weight: float) -> np.ndarray:
    """The PSD matrix ``Q`` `(3K, 3K)` of step 2 for the rank-3K factor ``pi`` `(F, 2, 3K)`."""
    import cvxpy as cp

    r = pi.shape[2]
    a, b = pi[:, 0], pi[:, 1]  # (F, r)
    q = cp.Variable((r, r), PSD=True)
    # every term is linear in the r(r+1)/2 entries t = [diag Q, strict upper Q] (cvxpy's upper_tri order):
    # x^T Q y = sum_i Q_ii x_i y_i + sum_{i<j} Q_ij (x_i y_j + x_j y_i)
    iu, ju = np.triu_indices(r, 1)

    def rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:  # (F, r(r+1)/2): the map t -> x_f^T Q y_f
        return np.concatenate([x * y, x[:, iu] * y[:, ju] + x[:, ju] * y[:, iu]], axis=1)

    aqa, bqb, aqb = rows(a, a), rows(b, b), rows(a, b)
    # sum_f (aQa - bQb)^2 + 4 (aQb)^2 = |C t|^2 with C (2F, r(r+1)/2); its R factor (r(r+1)/2 square) gives the
    # same objective with far fewer rows than the 2F that cvxpy would build from Q entry by entry
    factor = np.linalg.qr(np.concatenate([aqa - bqb, 2 * aqb]), mode="r")
    t = cp.hstack([cp.diag(q), cp.reshape(cp.upper_tri(q), (len(iu),), order="F")])
    scale = np.mean((a * a).sum(1) + (b * b).sum(1)) / 2  # keeps the objective's terms comparable
    objective = cp.sum_squares(factor @ t) + trace_weight * scale * cp.trace(q)
    problem = cp.Problem(cp.Minimize(objective), [(aqa + bqb).sum(axis=0) @ t / (2 * len(a)) == 1])
    value = _solve(problem, q, "rotation")
    return 0.5 * (value + value.T)


def _solve(problem, variable, what: str) -> np.ndarray:
    """Solve a cvxpy problem with Clarabel, falling back to SCS; the variable's value.

    A solution the solver flags as inaccurate is kept (Clarabel's are still close on the programs here) and
    reported through this module's logger instead of cvxpy's ``UserWarning``.
    """
    import warnings

    import cvxpy as cp

    for solver in ("CLARABEL", "SCS"):
        try:
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message="Solution may be inaccurate")
                problem.solve(solver=solver)
        except (cp.error.SolverError, ValueError):
            continue
        if variable.value is not None:
            if problem.status != cp.OPTIMAL:
                log.warning("spm: %s flags the %s program's solution as %s", solver, what, problem.status)
            return variable.value
    raise SolverError(f"spm: the {what} program failed ({problem.status})")


def resolve_signs(rot: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Flip frames by diag(-1, -1, 1) so that the camera rows agree with ``reference`` `(F, 3, 3)`.

    ``reference`` (the corrective-matrix cameras) is consistent over frames but lives in another object frame,
    possibly mirrored: one global orthogonal H with ``reference_f[:2] ~ s_f rot_f[:2] H`` and the per-frame signs
    ``s_f`` are fitted jointly (alternating, from several seed frames). No temporal order is used, so camera jumps
    are handled.
    """
    r2, q2 = rot[:, :2], reference[:, :2]
    best_cost, best_signs = np.inf, np.ones(len(rot))
    for f0 in np.unique(np.linspace(0, len(rot) - 1, min(len(rot), 6)).astype(int)):
        for s0 in (1.0, -1.0):
            h = nearest_rotation(s0 * r2[f0].T @ q2[f0], allow_reflection=True)
            for _ in range(6):
                keep = np.linalg.norm(r2 @ h - q2, axis=(1, 2))
                flip = np.linalg.norm(-(r2 @ h) - q2, axis=(1, 2))
                signs = np.where(flip < keep, -1.0, 1.0)
                h = nearest_rotation(np.einsum("f,fji,fjk->ik", signs, r2, q2), allow_reflection=True)
            cost = np.minimum(keep, flip).sum()
            if cost < best_cost:
                best_cost, best_signs = cost, signs
    out = rot.copy()
    out[best_signs < 0] = np.diag([-1.0, -1.0, 1.0]) @ rot[best_signs < 0]
    return out


@dataclass(frozen=True)
class Cameras:
    """The result of :func:`camera_step`.

    Attributes:
        rotations: `(F, 3, 3)` the cameras, signs resolved.
        pi: `(F, 2, 3K)` the rank-3K factor of W.
        g: `(3K, 3)` the refined corrective triple.
        signs: `(F,)` +1 or -1: frame f's rows are ``signs[f]`` times the orthonormalised ``pi[f] @ g``.
        residual: the orthonormality cost at ``g``.
        reference: `(F, 3, 3)` the corrective-matrix cameras the signs were resolved against.
    """

    rotations: np.ndarray
    pi: np.ndarray
    g: np.ndarray
    signs: np.ndarray
    residual: float
    reference: np.ndarray


def rotations_from_triple(pi: np.ndarray, g: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Step 4: the cameras `(F, 3, 3)` of the corrective triple ``g`` `(3K, 3)` for the rank-3K factor ``pi``
    `(F, 2, 3K)`, each frame's sign resolved against ``reference`` `(F, 3, 3)` (:func:`resolve_signs`), and
    those signs `(F,)`."""
    m = pi @ g  # (F, 2, 3)
    plain = complete_rotation(m / np.linalg.norm(m, axis=2, keepdims=True).mean(axis=1, keepdims=True))
    rot = resolve_signs(plain, reference)
    return rot, np.where((rot[:, 0] * plain[:, 0]).sum(axis=1) < 0, -1.0, 1.0)


def camera_step(wm: np.ndarray, k: int, trace_weight: float = 1e-4) -> Cameras:
    """Steps 1-4 of the module docstring for a centred `(2F, P)` W (rows 2f, 2f+1 of frame f) and K basis shapes."""

    n_frames = wm.shape[0] // 2
    u, s, _ = np.linalg.svd(wm, full_matrices=False)
    pi = (u[:, :3 * k] * np.sqrt(s[:3 * k])).reshape(n_frames, 2, 3 * k)
    q = rotation_program(pi, trace_weight)
    evals, evecs = np.linalg.eigh(q)
    g0 = evecs[:, -3:] * np.sqrt(np.maximum(evals[-3:], 1e-12))
    g, residual = refine_triple(pi, g0)
    reference = complete_rotation(camera_rows(wm)[0])
    rot, signs = rotations_from_triple(pi, g, reference)
    return Cameras(rotations=rot, pi=pi, g=g, signs=signs, residual=residual, reference=reference)


def refine_cameras_nuclear(wf: np.ndarray, cameras: Cameras, depth: np.ndarray, weight: float = 3.0,
                           iters: int = 300) -> np.ndarray:
    """Cameras `(F, 3, 3)` refined by the shape step's objective (``SPMParams.refine_cameras``).

    Minimises, jointly over the corrective triple ``G`` `(3K, 3)` and the depths ``z`` `(F, P)`,
    ``||S#(R(G), z)||_* / ||S#_0||_* + weight * orthonormality residual(G)``, from :func:`camera_step`'s ``cameras``
    and the shape step's ``depth`` at them (``S#_0``): ``R_f`` is the frame's sign times the nearest orthonormal rows
    to ``pi_f G``, third row by cross product; the residual is the camera step's. L-BFGS (torch, float64, CPU) for
    ``iters`` iterations. The camera step alone fits orthonormality only; this asks the nuclear norm too. Not the
    authors' method (off by default).

    Args:
        wf: `(F, 2, P)` centred tracks.
    """
    import torch

    pi = torch.tensor(cameras.pi, dtype=torch.float64)
    signs = torch.tensor(cameras.signs, dtype=torch.float64)[:, None, None]
    w = torch.tensor(wf, dtype=torch.float64)
    g = torch.tensor(cameras.g, dtype=torch.float64, requires_grad=True)
    z = torch.tensor(depth, dtype=torch.float64, requires_grad=True)
    n_frames = wf.shape[0]

    def rotations() -> torch.Tensor:
        # the nearest orthonormal rows, A^-1/2 m with A = m m^T (2 x 2), in closed form: the SVD's gradient is
        # singular at rows of equal norm (every exact camera). G's scale is fixed: it is a flat direction
        m = pi @ (g / g.norm())  # (F, 2, 3)
        a = m @ m.transpose(1, 2)
        root_det = torch.sqrt(torch.clamp(torch.linalg.det(a), min=0))[:, None, None]
        trace = a.diagonal(dim1=1, dim2=2).sum(1)[:, None, None]
        sqrt_a = (a + root_det * torch.eye(2, dtype=a.dtype)) / torch.sqrt(trace + 2 * root_det)
        rows = signs * torch.linalg.solve(sqrt_a, m)
        return torch.cat([rows, torch.linalg.cross(rows[:, 0], rows[:, 1])[:, None]], dim=1)

    def nuclear() -> torch.Tensor:
        cam = torch.cat([w, z[:, None]], dim=1)  # (F, 3, P)
        return torch.linalg.matrix_norm((rotations().transpose(1, 2) @ cam).reshape(n_frames, -1), "nuc")

    def orthonormality() -> torch.Tensor:  # the residual of nrsfm.solvers.csf2.refine_triple
        m = pi @ g
        na, nb, ab = (m[:, 0] ** 2).sum(1), (m[:, 1] ** 2).sum(1), (m[:, 0] * m[:, 1]).sum(1)
        den = na + nb
        return 0.5 * (((na - nb) / den) ** 2 + (2 * ab / den) ** 2).sum()

    with torch.no_grad():
        start = max(nuclear().item(), 1e-300)
    opt = torch.optim.LBFGS([g, z], lr=1, max_iter=iters, history_size=50, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-10, tolerance_change=1e-14)
    evaluations = [0]

    def closure() -> torch.Tensor:
        opt.zero_grad()
        value = nuclear() / start + weight * orthonormality()
        value.backward()
        evaluations[0] += 1
        report("spm", "camera refinement", min(evaluations[0], iters), iters, objective=value.item())
        return value

    opt.step(closure)
    with torch.no_grad():
        rot = rotations().numpy()
    if not np.isfinite(rot).all():
        raise SolverError("spm: the camera refinement diverged (non-finite cameras); set refine_cameras=false")
    return rot


def shape_cvxpy(w: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """Depths `(F, P)` minimising ``||S#||_*`` exactly (cvxpy), for `(F, 2, P)` centred ``w``, `(F, 3, 3)` ``rot``.

    The program sees ``w`` in units of the power of two nearest its RMS: Clarabel's tolerances are absolute.
    """
    import cvxpy as cp

    n_frames, _, n_points = w.shape
    unit = power_of_two_unit(w.reshape(n_frames * 2, n_points))
    base = np.einsum("fji,fjp->fip", rot[:, :2], w / unit)  # (F, 3, P) = R^(2)T W
    r3 = rot[:, 2]  # (F, 3)
    z = cp.Variable((n_frames, n_points))
    blocks = [base[:, i, :] + cp.multiply(np.repeat(r3[:, i:i + 1], n_points, axis=1), z) for i in range(3)]
    return _solve(cp.Problem(cp.Minimize(cp.normNuc(cp.hstack(blocks)))), z, "shape") * unit


def singular_value_threshold(m: np.ndarray, t: float, keep: int = 0) -> np.ndarray:
    """``U max(S - t, 0) V^T`` for ``m = U S V^T`` `(a, b)`, through the eigenvectors of the smaller Gram matrix;
    the ``keep`` largest singular values are not shrunk (the proximal map of the partial sum of the others: Oh et al.,
    TPAMI 2016).

    Only the singular values above ``t`` are kept, so the squared condition number of the Gram matrix does not reach
    the result.
    """
    if m.shape[0] < m.shape[1]:
        return singular_value_threshold(m.T, t, keep).T
    evals, vecs = np.linalg.eigh(m.T @ m)  # ascending
    sig = np.sqrt(np.maximum(evals, 0.0))
    shrink = np.full(sig.shape, float(t))
    if keep > 0:
        shrink[-keep:] = 0.0
    new = sig - shrink
    take = (new > 0) & (sig > 0)
    vecs, sig, new = vecs[:, take], sig[take], new[take]
    return ((m @ vecs) * (new / sig)) @ vecs.T


def shape_fpc(w: np.ndarray, rot: np.ndarray, *, tau: float = 0.2, outer: int = 20, inner: int = 300,
              tol: float = 1e-7) -> np.ndarray:
    """Depths `(F, P)` by fixed-point continuation on ``mu ||S#||_* + 1/2 ||A(S) - W||^2``, mu -> 1e-10.

    ``A`` projects each frame's shape with its camera rows (orthonormal, so
    ``||A|| = 1``); the last stage's solution nearly satisfies ``A(S) = W``
    and is then made exact by keeping only its depths.
    """
    n_frames, _, n_points = w.shape
    r2 = rot[:, :2]  # (F, 2, 3)
    s = np.einsum("fji,fjp->fip", r2, w)  # (F, 3, P) start: zero depth

    def to_mat(x):  # (F, 3, P) -> (F, 3P) rows [X Y Z]
        return x.reshape(n_frames, 3 * n_points)

    for level in range(outer):
        mu = max(1e-10, 4 * 0.25**level)
        for _ in range(inner):
            resid = np.einsum("fij,fjp->fip", r2, s) - w  # (F, 2, P)
            y = s - tau * np.einsum("fji,fjp->fip", r2, resid)
            new = singular_value_threshold(to_mat(y), tau * mu).reshape(n_frames, 3, n_points)
            change = np.linalg.norm(new - s) / max(np.linalg.norm(s), 1e-300)
            s = new
            if change < tol:
                break
    return np.einsum("fi,fip->fp", rot[:, 2], s)  # depth along each camera's third row


def _splitting(w: np.ndarray, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The terms of ``S#(z) = B + L(z)`` for `(F, 2, P)` ``w`` and `(F, 3, 3)` ``rot``: ``B`` `(F, 3, P)`, the third
    camera rows `(F, 3, 1)`, ``|B|`` and the starting ADMM penalty."""
    n_frames, _, n_points = w.shape
    base = np.einsum("fji,fjp->fip", rot[:, :2], w)
    scale = float(np.linalg.norm(base))
    return base, rot[:, 2][:, :, None], scale, np.sqrt(min(n_frames, 3 * n_points)) / max(scale, 1e-300)


def shape_admm(w: np.ndarray, rot: np.ndarray, *, tol: float = 1e-4, max_iter: int = 5000, relax: float = 1.6,
               rho: float | None = None) -> tuple[np.ndarray, int]:
    """Depths `(F, P)` minimising ``||S#||_*`` by ADMM; for `(F, 2, P)` centred ``w`` and `(F, 3, 3)` ``rot``.

    With exact reprojection, ``S#(z) = B + L(z)``: ``B`` `(F, 3P)` holds the back-projected tracks ``R_f^(2)T W_f``
    and ``L(z)_f = r3_f kron z_f`` puts each depth along its camera's third row ``r3_f``. ``L^T L = I``, so the
    splitting ``min ||Y||_* s.t. Y = B + L(z)`` has closed-form steps: ``Y`` by singular-value thresholding,
    ``z = L^T(Y - B - U)`` (Boyd et al. 2011, over-relaxed, penalty balanced every 10 iterations). Stops when the
    primal and dual residuals fall below ``tol`` relative to their scales. Unlike the authors' FPC, whose fixed step
    and continuation can stop short of the minimum, it runs to the stated tolerance.

    Returns:
        the depths `(F, P)` and the number of iterations.
    """
    n_frames = w.shape[0]
    base, r3, scale, rho0 = _splitting(w, rot)
    rho = rho0 if rho is None else rho
    y = base.copy()
    u = np.zeros_like(base)
    for it in range(1, max_iter + 1):
        z = np.einsum("fip,fip->fp", r3, y - base - u)  # L^T (Y - B - U)
        s_z = base + r3 * z[:, None, :]  # S#(z) = B + L(z)
        x_hat = relax * s_z + (1 - relax) * y
        y_old = y
        y = singular_value_threshold((x_hat + u).reshape(n_frames, -1), 1.0 / rho).reshape(base.shape)
        u = u + x_hat - y
        primal = np.linalg.norm(s_z - y) / max(np.linalg.norm(y), scale)
        dual = np.linalg.norm(np.einsum("fip,fip->fp", r3, y - y_old)) / max(np.linalg.norm(u), 1e-300)
        report("spm", "shape ADMM", it, max_iter, primal=primal, dual=dual)
        if primal < tol and dual < tol:
            break
        if it % 10 == 0 and (primal > 10 * dual or dual > 10 * primal):
            factor = 2.0 if primal > dual else 0.5
            rho, u = rho * factor, u / factor
    return np.einsum("fip,fip->fp", r3, y - base), it


def shape_partial(w: np.ndarray, rot: np.ndarray, keep: int, depth: np.ndarray, *, tol: float = 1e-5,
                  max_iter: int = 5000, grow: float = 1.03) -> tuple[np.ndarray, int]:
    """Depths `(F, P)` minimising the partial sum of ``S#``'s singular values (all but the ``keep`` largest),
    from the depths ``depth`` `(F, P)` (the nuclear norm's); for `(F, 2, P)` centred ``w`` and `(F, 3, 3)` ``rot``.

    The partial sum (Oh et al., "Partial sum minimization of singular values in robust PCA", TPAMI 2016) leaves the
    ``keep`` largest singular values, which carry the basis shapes, alone. The splitting is :func:`shape_admm`'s with
    their partial thresholding as the ``Y`` step and, as in their ALM, a penalty that grows by ``grow`` every
    iteration (the objective is not convex; a balanced penalty lets the iterates cycle). Stops when the primal
    residual and the relative change of the depths fall below ``tol``.

    Returns:
        the depths `(F, P)` and the number of iterations.
    """
    n_frames = w.shape[0]
    base, r3, scale, rho = _splitting(w, rot)
    y = base + r3 * depth[:, None, :]
    u = np.zeros_like(base)
    z = depth
    for it in range(1, max_iter + 1):
        z_old = z
        z = np.einsum("fip,fip->fp", r3, y - base - u)  # L^T (Y - B - U)
        s_z = base + r3 * z[:, None, :]
        y = singular_value_threshold((s_z + u).reshape(n_frames, -1), 1.0 / rho, keep).reshape(base.shape)
        u = u + s_z - y
        primal = np.linalg.norm(s_z - y) / max(np.linalg.norm(y), scale)
        change = np.linalg.norm(z - z_old) / max(np.linalg.norm(z), 1e-300)
        report("spm", "partial-sum ADMM", it, max_iter, primal=primal, change=change)
        if primal < tol and change < tol:
            break
        rho, u = rho * grow, u / grow
    return np.einsum("fip,fip->fp", r3, y - base), it


@register("spm", SPMParams, "prior-free NRSfM: PSD rotation program + nuclear-norm shape (Dai et al., CVPR 2012)",
          handles_missing=True)
def solve_spm(seq: Sequence, params: SPMParams) -> Reconstruction:
    """SPM on an orthographic sequence (missing points completed first). See the module docstring."""
    if params.K == 0 and params.k_rule == "agreement":
        return _agreement(seq, params)
    if params.fill == "reference" and not seq.is_complete:
        return solve_on_reference_fill(solve_spm.__wrapped__, seq, params)
    n_frames, n_points = seq.n_frames, seq.n_points
    points_2d, k, completion = _complete_tracks(seq, params.K)
    w = points_2d - points_2d.mean(axis=1, keepdims=True)  # (F, P, 2)
    wm = w.transpose(0, 2, 1).reshape(2 * n_frames, n_points)  # (2F, P)
    k = k or choose_k(wm, params.K)
    cameras = camera_step(wm, k, params.trace_weight)
    rot, cam_residual = cameras.rotations, cameras.residual
    wf = w.transpose(0, 2, 1)  # (F, 2, P)
    solver = params.shape_solver
    if solver == "auto":
        solver = "cvxpy" if n_frames + 3 * n_points <= params.cvxpy_limit else "admm"

    def nuclear_step(rot: np.ndarray) -> tuple[np.ndarray, int, bool]:
        if solver == "cvxpy":
            return shape_cvxpy(wf, rot), 1, True
        if solver == "admm":
            depth, iterations = shape_admm(wf, rot, tol=params.admm_tol, max_iter=params.admm_max_iter)
            return depth, iterations, iterations < params.admm_max_iter
        return shape_fpc(wf, rot, tau=params.fpc_tau, outer=params.fpc_outer, inner=params.fpc_inner,
                         tol=params.fpc_tol), 1, True

    def shape_step(rot: np.ndarray) -> tuple[np.ndarray, int, bool]:
        depth, iterations, converged = nuclear_step(rot)
        if params.shape_objective == "partial":
            depth, more = shape_partial(wf, rot, k, depth, max_iter=params.admm_max_iter)
            iterations, converged = iterations + more, converged and more < params.admm_max_iter
        return depth, iterations, converged

    depth, shape_iterations, converged = shape_step(rot)
    if params.refine_cameras:
        rot = refine_cameras_nuclear(wf, cameras, depth, params.refine_weight, params.refine_iter)
        depth, shape_iterations, converged = shape_step(rot)
    cam = np.concatenate([wf, depth[:, None, :]], axis=1)  # (F, 3, P) camera frame
    if params.truncate:
        obj = np.einsum("fji,fjp->fip", rot, cam).reshape(n_frames, -1)  # S# rows
        uu, ss, vv = np.linalg.svd(obj, full_matrices=False)
        obj = ((uu[:, :k] * ss[:k]) @ vv[:k]).reshape(n_frames, 3, n_points)
        cam = np.einsum("fij,fjp->fip", rot, obj)
    points = cam.transpose(0, 2, 1)
    points = points - points.mean(axis=1, keepdims=True)
    return Reconstruction(points_3d=points, rotations=rot, method="spm", iterations=shape_iterations,
                          converged=converged,
                          info={"K": k, "completion": completion, "shape_solver": solver,
                                "shape_iterations": shape_iterations,
                                "shape_objective": params.shape_objective, "camera_residual": cam_residual,
                                "refined_cameras": params.refine_cameras,
                                "k_rule": params.k_rule if params.K == 0 else None})


def _complete_tracks(seq: Sequence, k: int) -> tuple[np.ndarray, int, str]:
    """`(F, P, 2)` tracks of ``seq`` with its missing points completed at rank 3K (module docstring), K (``k``, or
    for ``k = 0`` the energy rule's on missing tracks; 0 for complete tracks, whose K the caller chooses) and how
    they were completed (``"none"``, ``"exact"`` or ``"imputed"``)."""
    vis = seq.weights > 0  # (F, P)
    if vis.all():
        return seq.points_2d, 0, "none"
    require_visible_points(seq, "spm")
    n_frames, n_points = seq.n_frames, seq.n_points
    mask = np.repeat(vis, 2, axis=0)  # (2F, P)
    w = np.where(mask, seq.measurement_matrix(), 0.0)  # (2F, P)
    room = min(2 * n_frames, n_points)
    cap = min(8, (room - 2) // 3)  # the largest K with 3K + 1 < min(2F, P)
    if cap < 1 or (k and 3 * k + 1 >= room):
        raise SolverError(f"spm: completing missing points at rank 3K needs 3K + 1 < min(2F, P) (here 2F = "
                          f"{2 * n_frames}, P = {n_points}{f', K = {k}' if k else ''}); pass a smaller K, or complete "
                          "tracks")
    given = k
    k = k or min(2, cap)  # the energy rule's floor
    while True:
        full, completion = complete_lowrank(w, mask, 3 * k)
        more = 0 if given else min(choose_k(full - full.mean(axis=1, keepdims=True), 0), cap)
        if more <= k:
            break
        k = more
    return full.reshape(n_frames, 2, n_points).transpose(0, 2, 1), k, completion


def _agreement(seq: Sequence, params: SPMParams) -> Reconstruction:
    """SPM with the K (from 2) that agrees with a reconstruction that needs no K (:mod:`nrsfm.solvers.kselect`)."""
    from nrsfm.solvers.kselect import k_candidates, solve_by_agreement

    ks = [k for k in k_candidates(seq.n_frames, seq.n_points) if k >= 2]
    if len(ks) <= 1:
        return solve_spm.__wrapped__(seq, dataclasses.replace(params, k_rule="energy"))
    return solve_by_agreement(seq, params, "spm", ks, "energy")
