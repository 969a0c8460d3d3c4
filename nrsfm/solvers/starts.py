"""The starts that several solvers share: CSF2's reconstruction and its rank rule for K.

PR, EM-PND, EM-PPCA and the consensus start from CSF2's reconstruction (:func:`csf2_start`,
:func:`csf2_reconstruction`), and CSF2 and PR choose K by one rule (:func:`auto_k`): ``ceil(r / 3)``, plus one
when 3 does not divide ``r`` (a basis of deficient rank: rank 5 needs K = 3), at most ``k_max`` and with
3K < min(2F, P), for a rank ``r`` of the centred W:

* complete tracks: the numerical rank where W is rank deficient (noise-free tracks); otherwise the rank of
  noisy low-rank tracks (:func:`~nrsfm.lowrank.noise_rank`, Gavish & Donoho's threshold where the spectrum has
  a gap), and the cap where there is no gap (real motion capture);
* missing points: the smallest rank that fits the visible entries exactly (:func:`~nrsfm.lowrank.visible_rank`),
  else the noise floor of a ladder of fits (:func:`~nrsfm.lowrank.noise_visible_rank`), else the cap.

EM-PPCA takes its K from the exact rank alone (:func:`exact_rank`), where there is one.

A solver that runs others (the consensus: EM-PND and PR; EM-PPCA: CSF2 and its own K) wraps them in
:func:`shared_starts`, inside which each start, each noise rank and each exact rank of tracks with missing points
(:func:`shared_visible_rank`) is computed once per input. CSF2 itself is reached through the registry, so this
module imports no solver.

Whole reconstructions at a solver's defaults are kept too, for the last few inputs of the process
(:func:`remember_solution`, :func:`remembered_solution`): the automatic K of CSF2 and SPM (EM-PND, its reference)
and the consensus (its components) solve each once per input, and a solve done in another process (``nrsfm demo``)
can be handed over.
"""

from __future__ import annotations

import contextlib
import contextvars
import copy
import hashlib
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np

from nrsfm.lowrank import noise_rank, noise_visible_rank, power_of_two_unit, visible_rank
from nrsfm.reconstruction import Reconstruction
from nrsfm.sequence import Sequence
from nrsfm.solvers.registry import get_solver


def auto_k(w: np.ndarray, mask: np.ndarray | None = None, k_max: int = 8, rel_tol: float = 1e-6,
           max_frames: int = 300, max_points: int = 60, fit: tuple[int, np.ndarray | None] | None = None) -> int:
    """CSF2's rank rule for K (``k_rule="rank"``) on a `(2F, P)` W: ``ceil(r / 3)``, plus one when 3 does not
    divide ``r``, for a rank ``r`` of the centred W, at most ``k_max`` and with 3K < min(2F, P) (module docstring).

    ``r`` is the numerical rank (singular values above ``rel_tol`` times the largest) when W is rank deficient; when
    it is not, the rank of noisy low-rank tracks (:func:`~nrsfm.lowrank.noise_rank`), and the cap where W does not look
    like one (real motion capture).

    With missing entries (``mask`` False) the rank r is the smallest whose fit to the visible entries leaves less than
    ``rel_tol`` of their RMS (:func:`~nrsfm.lowrank.visible_rank`, on at most ``max_frames`` frames and ``max_points``
    points, ranks up to 3 (cap - 2); ``fit`` passes its result when already computed); where none fits, the rank of
    noisy low-rank tracks (:func:`~nrsfm.lowrank.noise_visible_rank`, seconds on long sequences), and the cap where
    there is none.
    """
    cap = max(1, min(k_max, (min(w.shape) - 1) // 3))
    rank, s = _exact_rank(w, mask, k_max, rel_tol, max_frames, max_points, fit)
    if not rank and s is None:
        max_rank = auto_k_max_rank(w, k_max)
        rank = shared("noise_visible_rank", (w / power_of_two_unit(w, mask), mask, max_rank, max_frames, max_points),
                      lambda: noise_visible_rank(w, mask, max_rank, max_frames=max_frames, max_points=max_points))
    elif not rank:
        rank = noise_rank(s, w.shape)
    return k_for_rank(rank, cap)


def exact_rank(w: np.ndarray, mask: np.ndarray | None = None, k_max: int = 8, rel_tol: float = 1e-6) -> int:
    """The rank of the centred `(2F, P)` W where its tracks are exactly low-rank (noise-free), else 0.

    Complete tracks: the number of singular values above ``rel_tol`` times the largest, where that is below
    min(2F, P - 1). Missing entries (``mask`` False): :func:`~nrsfm.lowrank.visible_rank` up to
    :func:`auto_k_max_rank`. The first step of :func:`auto_k`.
    """
    return _exact_rank(w, mask, k_max, rel_tol, 300, 60, None)[0]


def _exact_rank(w: np.ndarray, mask: np.ndarray | None, k_max: int, rel_tol: float, max_frames: int,
                max_points: int, fit: tuple[int, np.ndarray | None] | None) -> tuple[int, np.ndarray | None]:
    """:func:`exact_rank` (0 where none) and, for complete tracks, the singular values of the centred W."""
    if mask is not None and not mask.all():
        rank = (fit or shared_visible_rank(w, mask, auto_k_max_rank(w, k_max), rel_tol, max_frames, max_points))[0]
        return rank, None
    s = np.linalg.svd(w - w.mean(axis=1, keepdims=True), compute_uv=False)
    rank = int(np.count_nonzero(s > rel_tol * s[0])) if s[0] > 0 else 1
    return (rank if rank < min(w.shape[0], w.shape[1] - 1) else 0), s


def shared_visible_rank(w: np.ndarray, mask: np.ndarray, max_rank: int, rel_tol: float = 1e-6, max_frames: int = 300,
                        max_points: int = 60) -> tuple[int, np.ndarray | None]:
    """:func:`~nrsfm.lowrank.visible_rank` of `(2F, P)` ``w``, inside :func:`shared_starts` once per input (the
    result is handed out as it is: read it, do not modify it)."""
    return shared("visible_rank", (w, mask, max_rank, rel_tol, max_frames, max_points),
                  lambda: visible_rank(w, mask, max_rank, rel_tol=rel_tol, max_frames=max_frames,
                                       max_points=max_points))


def k_for_rank(rank: int, cap: int) -> int:
    """:func:`auto_k`'s K for a rank: ``ceil(rank / 3)``, plus one when 3 does not divide it, at most ``cap``;
    ``cap`` for rank 0 (none found)."""
    if not rank:
        return cap
    return max(1, min(cap, -(-rank // 3) + (rank % 3 != 0)))


def auto_k_max_rank(w: np.ndarray, k_max: int = 8) -> int:
    """The largest rank :func:`auto_k` tests on a `(2F, P)` W with missing entries: 3 (cap - 2)."""
    return 3 * (max(1, min(k_max, min(w.shape) // 3)) - 2)


def fits_csf2(n_frames: int, n_points: int) -> bool:
    """Whether CSF2 can run: it needs 3K <= min(2F, P) with K >= 2."""
    return min(2 * n_frames, n_points) >= 6


_SHARED_STARTS: contextvars.ContextVar[dict | None] = contextvars.ContextVar("csf2_shared_starts", default=None)


@contextlib.contextmanager
def shared_starts():
    """Within this block, :func:`csf2_start` computes each start once and hands out copies.

    Solvers that run other solvers (the consensus: EM-PND and PR) start both from the same CSF2 reconstruction when
    points are missing. A start is known by the tracks' bytes, the visibility, K (the automatic K is stored under the
    K it chose too, where that K given would search the same ranks) and the other settings; the cache ends with the
    block. So is the noise rank of :func:`auto_k` with missing points, which both solvers' automatic K compute, and
    the exact rank of such tracks (:func:`shared_visible_rank`: EM-PPCA's K and its CSF2 start), and CSF2's whole
    reconstruction (:func:`csf2_reconstruction`: EM-PPCA's start at two Ks).
    """
    token = _SHARED_STARTS.set({})
    try:
        yield
    finally:
        _SHARED_STARTS.reset(token)


def shared(name: str, key: tuple, compute: Callable[[], Any]) -> Any:
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


def tracks_digest(seq: Sequence) -> str:
    """A digest of what a solver sees of ``seq``: its 2D tracks, visibility, shape and projection (not its name)."""
    digest = hashlib.sha256(np.ascontiguousarray(seq.points_2d, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(seq.weights, dtype=np.float64).tobytes())
    digest.update(f"{seq.points_2d.shape} {seq.projection}".encode())
    return digest.hexdigest()


#: Reconstructions at a solver's defaults by (solver, :func:`tracks_digest`), the most recently used last.
_SOLUTIONS: OrderedDict[tuple[str, str], Reconstruction] = OrderedDict()
#: How many :data:`_SOLUTIONS` a process keeps.
SOLUTIONS_KEPT = 8


def remember_solution(seq: Sequence, solver: str, rec: Reconstruction) -> None:
    """Keep ``rec``, the registered ``solver``'s reconstruction of ``seq`` at its default parameters, for the
    solvers of this process that run ``solver`` at its defaults on the same tracks (:func:`remembered_solution`).

    The automatic K of CSF2 and SPM keeps its reference (EM-PND) this way and the consensus its components; a solve
    done in another process is handed over the same way (``nrsfm demo`` solves EM-PND and PR first and gives their
    reconstructions to the workers that run CSF2, SPM and the consensus). A reconstruction at other settings must
    not be given: nothing here can tell.
    """
    get_solver(solver)  # an unknown name raises with the known ones
    if not isinstance(rec, Reconstruction) or rec.points_3d.shape != (seq.n_frames, seq.n_points, 3):
        got = rec.points_3d.shape if isinstance(rec, Reconstruction) else type(rec).__name__
        raise ValueError(f"remember_solution: expected a Reconstruction with shapes of shape "
                         f"{(seq.n_frames, seq.n_points, 3)} (the sequence's frames and points), got {got}")
    key = (solver, tracks_digest(seq))
    _SOLUTIONS[key] = copy.deepcopy(rec)
    _SOLUTIONS.move_to_end(key)
    while len(_SOLUTIONS) > SOLUTIONS_KEPT:
        _SOLUTIONS.popitem(last=False)


def remembered_solution(seq: Sequence, solver: str) -> Reconstruction | None:
    """A copy of the reconstruction :func:`remember_solution` kept for ``solver`` on ``seq``'s tracks (under any
    name), or None."""
    key = (solver, tracks_digest(seq))
    if key not in _SOLUTIONS:
        return None
    _SOLUTIONS.move_to_end(key)
    return copy.deepcopy(_SOLUTIONS[key])


def csf2_start(seq: Sequence, K: int = 0, **overrides) -> np.ndarray:
    """`(F, P, 3)` CSF2 reconstruction used as another solver's start (EM-PND, PR), ``K`` capped by
    3K <= min(2F, P) (0: CSF2's rank rule); ``overrides``: other :class:`CSF2Params` fields. Check
    :func:`fits_csf2` first. Inside :func:`shared_starts`, computed once per input."""
    k = min(K, min(2 * seq.n_frames, seq.n_points) // 3)
    cache = _SHARED_STARTS.get()
    if cache is None:
        return csf2_reconstruction(seq, k, **overrides).points_3d
    data = (tracks_digest(seq), tuple(sorted(overrides.items())))
    if (data, k) not in cache:
        rec = csf2_reconstruction(seq, k, **overrides)
        cache[data, k] = rec.points_3d
        if 3 * rec.info["K"] >= auto_k_max_rank(np.empty((2 * seq.n_frames, seq.n_points))):
            # the automatic K searched the same ranks as this K given would: the same start
            cache[data, rec.info["K"]] = rec.points_3d
    return cache[data, k].copy()


def csf2_reconstruction(seq: Sequence, K: int = 0, **overrides: Any) -> Reconstruction:
    """CSF2's :class:`~nrsfm.reconstruction.Reconstruction` of ``seq`` without the registry's input checks and
    timing (the caller has checked ``seq``): cameras and shapes for the solvers that start from both (EM-PPCA).
    ``overrides``: other CSF2 parameters (``K = 0``: CSF2's rank rule unless ``k_rule`` says otherwise). Inside
    :func:`shared_starts`, computed once per input and handed out as copies."""
    spec = get_solver("csf2")
    params = spec.params(K=K, **{"k_rule": "rank", **overrides})
    rec = shared("csf2_reconstruction", (tracks_digest(seq), params), lambda: spec.solve.__wrapped__(seq, params))
    return copy.deepcopy(rec) if _SHARED_STARTS.get() is not None else rec

