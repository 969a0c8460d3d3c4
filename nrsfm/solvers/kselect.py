"""Choosing a solver's number of basis shapes K by agreement with a reconstruction that needs no K.

The rule (``k_rule="agreement"``, the default of CSF2 and SPM with ``K = 0``):

1. reconstruct the sequence once with EM-PND at its defaults (:mod:`nrsfm.solvers.empnd`: a Procrustean normal
   distribution, no K), the *reference*;
2. solve with every K from 1 (SPM: from 2, its energy rule's floor) to 12 with 3K < min(2F, P) (the fixed Ks
   that ``benchmarks.defaults`` sweeps);
3. measure each K's distance to the reference: the e3D between their camera-frame shapes
   (:func:`nrsfm.metrics.e3d`, one global rotation or reflection, divided by the reference's scale);
4. pass over every K whose reconstruction reverses its depth between frames more often than the steadiest K's
   does (:func:`depth_flips`: a fraction of frame pairs above ``max(2 * least, least +`` :data:`FLIP_MARGIN```)``);
5. keep the largest remaining K whose distance is within :data:`TOLERANCE` (5%) of the smallest: a larger basis
   that agrees as well holds more of the motion. The tolerance was chosen on the CMU files (CSF2 and SPM within
   10% of their best fixed K on all six, worst ratio 1.05, against 1.08 for the nearest K and 1.06 for 10%) and
   then measured on the validation set of ``benchmarks.defaults``.

Step 4 guards against a reference that failed the same way as one K. Orthographic depth has no sign, and a solver
can settle on the wrong sign in some frames; the shape then jumps to its mirror image, which a real motion
seen frame after frame never does. EM-PND's reconstruction can do so on a walking person, and one K's
reconstruction that shares the fault then lies nearest it. The guard needs the frames in temporal order; in an
unordered set every K "flips" about as often, and the ``2 * least`` bound then passes over none. Its margin was set
where it met such failures (the validation and test sets of ``benchmarks.defaults``) and then checked on a set
declared afterwards (``--set holdout``); it costs two distances per frame and K.

Missing points: EM-PND takes them as they are; the Ks are then all solved on one set of complete tracks, the
visible points kept and each missing one filled by the reference's projection (:func:`fill_missing`), instead of
each K completing the tracks itself at rank 3K. The fill is the same for every K, so the distances of step 3
compare the Ks' models alone, and EM-PND's model-based fill is closer to the hidden points than a rank-3K
completion of real motion. The reconstruction's ``info["completion"]`` is then ``"reference"``.

No ground truth enters and nothing depends on a name. A K whose solution fell into a poor minimum disagrees with
the reference and is passed over; so is a K too small to hold the motion. Cost: one EM-PND solve plus one solve
per K (five on 17 joints, twelve on 37 or more points), in one :class:`joblib.Parallel` batch (one process
unless the caller's ``joblib.parallel_config`` asks for more; ``nrsfm solve --jobs N``). CSF2's rank rule
(``k_rule="rank"``) and SPM's energy rule (``k_rule="energy"``) cost one solve; the solvers that start from CSF2
(EM-PND, PR, EM-PPCA) use the rank rule. SPM starts from K = 2, its energy rule's floor: its K = 1, a shape
close to rigid, can resemble a poor EM-PND reconstruction more than SPM's good Ks do. The rule is only as good as
its reference: where EM-PND is far from the truth, it keeps the K nearest that error. Measured against the best
fixed K in ``benchmarks/RESULTS.md`` (``benchmarks.defaults``, ``benchmarks.studies.reference_trust``).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from nrsfm.errors import NRSfMError, SolverError
from nrsfm.reconstruction import Reconstruction
from nrsfm.sequence import Sequence

#: The largest K the agreement rule tries.
K_MAX = 12
#: Step 5 of the rule: the largest K whose distance to the reference is at most ``1 + TOLERANCE`` times the least.
TOLERANCE = 0.05
#: Step 4 of the rule: a K is passed over where its :func:`depth_flips` exceed ``max(2 * least, least +
#: FLIP_MARGIN)``, ``least`` the smallest among the Ks (one frame pair in a hundred above a steady K's none).
FLIP_MARGIN = 0.01


def k_candidates(n_frames: int, n_points: int, k_max: int = K_MAX) -> range:
    """The Ks the rule tries on an `(F, P)` sequence: 1 to ``k_max`` with 3K < min(2F, P) (at least 1)."""
    return range(1, max(1, min(k_max, (min(2 * n_frames, n_points) - 1) // 3)) + 1)


#: The solver whose reconstruction at its defaults is the rule's reference (step 1).
REFERENCE_SOLVER = "empnd"

def _reference(seq: Sequence) -> Reconstruction | NRSfMError:
    """:data:`REFERENCE_SOLVER`'s reconstruction at its defaults, timed, or the error that stopped it (returned, so
    that a worker process hands it back)."""
    from nrsfm.solvers.registry import get_solver

    spec = get_solver(REFERENCE_SOLVER)
    params = spec.params()
    t0 = time.perf_counter()
    try:
        rec = spec.solve.__wrapped__(seq, params)
    except NRSfMError as exc:
        return exc
    return dataclasses.replace(rec, runtime_s=time.perf_counter() - t0, params=dataclasses.asdict(params))


def _kept_reference(seq: Sequence) -> Reconstruction | NRSfMError:
    """The reference this process keeps for ``seq``'s tracks (:func:`~nrsfm.solvers.starts.remembered_solution`),
    else :func:`_reference`, kept where it succeeded."""
    from nrsfm.solvers.starts import remember_solution, remembered_solution

    reference = remembered_solution(seq, REFERENCE_SOLVER)
    if reference is None:
        reference = _reference(seq)
        if not isinstance(reference, NRSfMError):
            remember_solution(seq, REFERENCE_SOLVER, reference)
    return reference


def _attempt(solve_k: Callable[[int], Reconstruction], k: int) -> Reconstruction | None:
    """``solve_k(k)``, None where it raised :class:`~nrsfm.errors.SolverError`."""
    try:
        return solve_k(k)
    except SolverError:
        return None


def depth_flips(shapes: np.ndarray) -> float:
    """The fraction of consecutive frame pairs in which `(F, P, 3)` camera-frame shapes reverse their depth: frame
    f's shape, centred, is nearer (mean distance over points) to frame f - 1's with its depth negated than to frame
    f - 1's itself. 0 for a single frame."""
    x = np.asarray(shapes, dtype=np.float64)
    x = x - x.mean(axis=1, keepdims=True)
    if x.shape[0] < 2:
        return 0.0
    mirrored = x[:-1] * np.array([1.0, 1.0, -1.0])
    same = np.linalg.norm(x[1:] - x[:-1], axis=2).mean(axis=1)  # (F - 1,)
    flipped = np.linalg.norm(x[1:] - mirrored, axis=2).mean(axis=1)
    return float((flipped < same).mean())


def steady_ks(flips: dict[Any, float], margin: float = FLIP_MARGIN) -> list[Any]:
    """Step 4 of the rule: the Ks of ``{K: depth_flips}`` whose fraction is at most ``max(2 * least, least +
    margin)``."""
    least = min(flips.values())
    return [k for k, f in flips.items() if f <= max(2 * least, least + margin)]


def agreeing_k(distance: dict[Any, float], tolerance: float = TOLERANCE) -> Any:
    """Step 5 of the rule: the largest K of ``{K: distance to the reference}`` whose distance is within
    ``1 + tolerance`` of the least (the keys compare as integers)."""
    least = min(distance.values())
    return max((k for k, d in distance.items() if d <= (1 + tolerance) * least), key=int)


def agreement_choice(distance: dict[Any, float], flips: dict[Any, float]) -> Any:
    """Steps 4 and 5 of the rule: :func:`agreeing_k` among the :func:`steady_ks` of ``{K: distance to the
    reference}`` and ``{K: depth_flips}`` (every key of ``distance`` in ``flips``)."""
    steady = steady_ks({k: flips[k] for k in distance})
    return agreeing_k({k: distance[k] for k in steady})


def _keep(ks: list[int], recs: list[Reconstruction | None],
          reference: np.ndarray) -> tuple[Reconstruction, dict[int, float], dict[int, float]]:
    from nrsfm.metrics import e3d

    dist = {k: float("nan") if rec is None else e3d(rec.points_3d, reference) for k, rec in zip(ks, recs)}
    flips = {k: depth_flips(rec.points_3d) for k, rec in zip(ks, recs) if rec is not None}
    solved = [k for k, rec in zip(ks, recs) if rec is not None]
    if not solved:
        raise SolverError(f"automatic K: no K in {sorted(dist)} could be solved; pass K explicitly")
    finite = [k for k in solved if np.isfinite(dist[k])]
    if not finite:
        return recs[ks.index(solved[0])], dist, flips
    return recs[ks.index(agreement_choice({k: dist[k] for k in finite}, flips))], dist, flips


def agreement_k(solve_k: Callable[[int], Reconstruction], ks: Iterable[int],
                reference: np.ndarray) -> tuple[Reconstruction, dict[int, float], dict[int, float]]:
    """The reconstruction, among ``solve_k(k)`` for ``k`` in ``ks``, of the largest K, among those that reverse
    their depth no more often than the steadiest (:func:`steady_ks`), within :data:`TOLERANCE` of the least e3D to
    ``reference`` `(F, P, 3)` (the module docstring).

    A K whose solve raises :class:`~nrsfm.errors.SolverError` is skipped (recorded as NaN). The solves go
    through :class:`joblib.Parallel` with joblib's default ``n_jobs``: one at a time in this process unless the
    caller sets more, e.g. ``with joblib.parallel_config(backend="loky", n_jobs=2, inner_max_num_threads=1):``
    around ``nrsfm.solve(...)`` (``nrsfm solve --jobs 2``); ``solve_k`` must then pickle (a
    :func:`functools.partial` of a module function).

    Returns:
        The kept reconstruction, every K's distance to the reference and every solved K's :func:`depth_flips`.
    """
    from joblib import Parallel, delayed

    ks = list(ks)
    return _keep(ks, Parallel()(delayed(_attempt)(solve_k, k) for k in ks), reference)


def _solve_fixed(solver: str, seq: Sequence, params: Any, k: int | None = None) -> Reconstruction:
    """The registered ``solver`` without its registry wrapper (which validates and times the whole call), with
    ``K = k`` when given; a module function, so that a worker process can receive it."""
    from nrsfm.solvers.registry import get_solver

    return get_solver(solver).solve.__wrapped__(seq, params if k is None else dataclasses.replace(params, K=k))


def fill_missing(seq: Sequence, shapes: np.ndarray) -> Sequence:
    """``seq`` with each missing point replaced by the orthographic projection of ``shapes`` `(F, P, 3)` (camera
    frame, a :class:`~nrsfm.reconstruction.Reconstruction`'s ``points_3d``), shifted by the frame's translation
    fitted on its visible points; visible points are kept and every weight becomes 1. Complete tracks are returned
    as they are."""
    vis = seq.weights > 0  # (F, P)
    if vis.all():
        return seq
    proj = np.asarray(shapes, dtype=np.float64)[..., :2]  # (F, P, 2)
    gap = np.where(vis[..., None], seq.points_2d - proj, 0.0)
    shift = gap.sum(axis=1, keepdims=True) / np.maximum(vis.sum(axis=1), 1)[:, None, None]  # (F, 1, 2)
    return seq.replace(points_2d=np.where(vis[..., None], seq.points_2d, proj + shift), visibility=None)


#: How CSF2 and SPM complete missing points (their ``fill`` parameter): ``"auto"``: by the reference's
#: reconstruction with the agreement rule's automatic K (:func:`solve_by_agreement`), each K on its own (rank 3K)
#: with a fixed K; ``"reference"``: always by EM-PND's reconstruction (:func:`fill_from_reference`);
#: ``"lowrank"``: always each K on its own.
FILLS = ("auto", "reference", "lowrank")


def fill_from_reference(seq: Sequence) -> Sequence:
    """``seq`` with its missing points filled by :data:`REFERENCE_SOLVER`'s reconstruction at its defaults
    (:func:`fill_missing`), solved once per tracks and kept (:func:`~nrsfm.solvers.starts.remember_solution`);
    raises the reference's :class:`~nrsfm.errors.NRSfMError` where it refuses the tracks."""
    if seq.is_complete:
        return seq
    reference = _kept_reference(seq)
    if isinstance(reference, NRSfMError):
        raise reference
    return fill_missing(seq, reference.points_3d)


def solve_on_reference_fill(solve: Callable[[Sequence, Any], Reconstruction], seq: Sequence,
                            params: Any) -> Reconstruction:
    """``solve(filled, params)`` on ``seq`` filled by :func:`fill_from_reference`, ``info["completion"]`` set to
    ``"reference"`` where points were missing."""
    rec = solve(fill_from_reference(seq), params)
    if not seq.is_complete:
        rec.info.update(completion="reference")
    return rec


def solve_by_agreement(seq: Sequence, params: Any, solver: str, ks: list[int], fallback_rule: str) -> Reconstruction:
    """The registered ``solver`` on ``seq`` with the K among ``ks`` that agrees with EM-PND's reconstruction
    (:func:`agreement_k`), the distances in ``info["agreement"]`` and each K's :func:`depth_flips` in
    ``info["depth_flips"]``. EM-PND runs in the same
    :class:`joblib.Parallel` batch as the K solves unless this process has it
    (:func:`~nrsfm.solvers.starts.remembered_solution`), and is kept for the next solver on the same tracks. Where
    EM-PND refuses the tracks (degenerate input), ``params`` with ``k_rule=fallback_rule``, ``info["k_rule"]``
    saying why.

    With missing points (and ``params.fill`` not ``"lowrank"``) EM-PND runs first and every K is solved on the
    tracks its reconstruction completes (:func:`fill_missing`; ``info["completion"] = "reference"``) instead of
    the solver's own rank-3K completion."""
    from joblib import Parallel, delayed

    from nrsfm.solvers.registry import require_visible_points
    from nrsfm.solvers.starts import remember_solution, remembered_solution

    def solves(tracks: Sequence) -> list:
        return [delayed(_attempt)(functools.partial(_solve_fixed, solver, tracks, params), k) for k in ks]

    as_given = seq.is_complete or params.fill == "lowrank"  # else the Ks run on the reference's fill
    if not as_given:
        require_visible_points(seq, solver)
    reference, recs = remembered_solution(seq, REFERENCE_SOLVER), None
    if reference is None and as_given:  # the reference in the same batch as the K solves
        reference, *recs = Parallel()([delayed(_reference)(seq), *solves(seq)])
        if not isinstance(reference, NRSfMError):
            remember_solution(seq, REFERENCE_SOLVER, reference)
    elif reference is None:  # the K solves need its fill first
        reference = _kept_reference(seq)
    if isinstance(reference, NRSfMError):
        rec = _solve_fixed(solver, seq, dataclasses.replace(params, k_rule=fallback_rule))
        rec.info.update(k_rule=f"{fallback_rule} (the agreement rule's reference failed: {reference})")
        return rec
    if recs is None:
        recs = Parallel()(solves(seq if as_given else fill_missing(seq, reference.points_3d)))
    rec, dist, flips = _keep(list(ks), recs, reference.points_3d)
    rec.info.update(k_rule="agreement", agreement=dist, depth_flips=flips)
    if not as_given:
        rec.info.update(completion="reference")
    return rec
