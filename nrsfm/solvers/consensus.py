"""Consensus: a weighted average of the reconstructions of several solvers.

Two solvers built on different models make partly independent errors, so a weighted mean of their camera-frame
shapes can be closer to the truth than either. The default pairs EM-PND (a Procrustean normal distribution of the
shapes) with PR (Procrustean regression: a log-determinant of the aligned shapes, from CSF2's start) at weights
0.85 and 0.15.

Each reconstruction is centred per frame and, frame by frame, given the depth sign (the reflection ``z -> -z``
that orthographic projection cannot see) that brings it closer to the first method's; the image coordinates are
untouched. The cameras are the weighted chordal mean of the solvers' rotations (the same reflection applied as
``D R D``, ``D = diag(1, 1, -1)``), projected onto SO(3).

The weight is a setting, not something learnt from the sequence: no ground truth and nothing else of the sequence
chooses it. It was chosen on the CMU files leaving each file out in turn
(``python -m benchmarks.studies.consensus_weight``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nrsfm.errors import NRSfMError, ValidationError
from nrsfm.geometry import nearest_rotation
from nrsfm.reconstruction import Reconstruction
from nrsfm.sequence import Sequence
from nrsfm.solvers.registry import get_solver, register
from nrsfm.solvers.starts import remember_solution, remembered_solution, shared_starts

_FLIP = np.array([1.0, 1.0, -1.0])


@dataclass(frozen=True)
class ConsensusParams:
    """Parameters of :func:`solve_consensus`.

    Attributes:
        methods: comma-separated registered solvers, each run with its defaults; the first sets the depth sign
            (default ``"empnd,pr"``).
        weights: comma-separated non-negative weights, one per method, scaled to sum to 1 (default ``"0.85,0.15"``,
            chosen leaving each CMU file out in turn: ``python -m benchmarks.studies.consensus_weight``).
    """

    methods: str = "empnd,pr"
    weights: str = "0.85,0.15"

    def __post_init__(self) -> None:
        self.parsed()

    def parsed(self) -> tuple[list[str], np.ndarray]:
        """The method names and the weights scaled to sum to 1; raises a :class:`ValidationError` on bad ones."""
        names = [m.strip() for m in self.methods.split(",") if m.strip()]
        try:
            weights = np.array([float(w) for w in self.weights.split(",") if w.strip()])
        except ValueError:
            raise ValidationError(f"consensus weights: expected comma-separated numbers such as '0.85,0.15', got "
                                  f"{self.weights!r}") from None
        if len(names) < 2 or "consensus" in names:
            raise ValidationError(f"consensus methods: expected two or more registered solvers other than "
                                  f"'consensus', comma-separated (e.g. 'empnd,pr'), got {self.methods!r}")
        for name in names:
            get_solver(name)  # unknown names raise with the list of known ones
        if weights.shape != (len(names),) or not np.isfinite(weights).all() or (weights < 0).any() \
                or weights.sum() <= 0:
            raise ValidationError(f"consensus weights: expected {len(names)} non-negative numbers, one per method "
                                  f"({', '.join(names)}), not all 0, got {self.weights!r}")
        return names, weights / weights.sum()


def average_reconstructions(recs: list[Reconstruction], weights) -> tuple[np.ndarray, np.ndarray | None, int]:
    """The weighted mean of ``recs`` (same sequence) in the camera frame.

    Args:
        recs: reconstructions of one sequence, `(F, P, 3)` shapes each; the first sets the depth sign.
        weights: `(len(recs),)` non-negative weights summing to 1.

    Returns:
        `(F, P, 3)` centred shapes; `(F, 3, 3)` rotations (the weighted chordal mean in SO(3), or None when a
        reconstruction has none); the number of (reconstruction, frame) pairs whose depth sign was flipped
        to agree with the first.
    """
    weights = np.asarray(weights, dtype=np.float64)
    ref = recs[0].points_3d - recs[0].points_3d.mean(axis=1, keepdims=True)
    shapes = np.zeros_like(ref)
    rot_sum = np.zeros((ref.shape[0], 3, 3)) if all(r.rotations is not None for r in recs) else None
    flipped = 0
    for rec, w in zip(recs, weights):
        x = rec.points_3d - rec.points_3d.mean(axis=1, keepdims=True)
        flip = ((x * _FLIP - ref) ** 2).sum(axis=(1, 2)) < ((x - ref) ** 2).sum(axis=(1, 2))  # (F,)
        flipped += int(flip.sum())
        shapes += w * np.where(flip[:, None, None], x * _FLIP, x)
        if rot_sum is not None:
            r = rec.rotations
            rot_sum += w * np.where(flip[:, None, None], r * _FLIP[:, None] * _FLIP[None, :], r)  # D R D
    rotations = None
    if rot_sum is not None:
        rotations = nearest_rotation(rot_sum)
    return shapes, rotations, flipped


@register("consensus", ConsensusParams, "weighted mean of several solvers' reconstructions (default: EM-PND 0.85, "
                                         "PR 0.15)", handles_missing=True)
def solve_consensus(seq: Sequence, params: ConsensusParams) -> Reconstruction:
    """Every method of ``params`` on ``seq`` with its defaults, then :func:`average_reconstructions`. Missing points
    are allowed when every method handles them; a method that refuses the sequence stops the consensus with
    its own message.

    A method whose reconstruction of these tracks this process already has
    (:func:`~nrsfm.solvers.starts.remembered_solution`: solved by an earlier consensus or automatic K, or handed
    over by another process) is not solved again; ``info["reused"]`` names those, and the run time then excludes
    theirs (``info["component_seconds"]`` keeps each method's own). Each method solved here is kept the same way."""

    names, weights = params.parsed()
    recs, reused = [], []
    with shared_starts():  # EM-PND and PR start from the same CSF2 reconstruction when points are missing
        for name in names:
            rec = remembered_solution(seq, name)
            if rec is not None:
                reused.append(name)
            else:
                try:
                    rec = get_solver(name).solve(seq)
                except NRSfMError as exc:
                    raise type(exc)(f"consensus: {exc}") from exc
                remember_solution(seq, name, rec)
            recs.append(rec)
    shapes, rotations, flipped = average_reconstructions(recs, weights)
    return Reconstruction(points_3d=shapes, rotations=rotations, method="consensus",
                          iterations=sum(r.iterations for r in recs), converged=all(r.converged for r in recs),
                          info={"methods": names, "weights": weights.tolist(), "frames_flipped": flipped,
                                "reused": reused, "component_seconds": [r.runtime_s for r in recs],
                                "component_iterations": [r.iterations for r in recs]})
