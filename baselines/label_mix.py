"""Mixed pseudo-labels: the frame-by-frame weighted mean of several solvers' label sets.

Two per-sequence solvers built on different shape models (PR: a low-rank log-determinant of the aligned shapes;
EM-PND: a Procrustean normal distribution) make partly independent depth errors on the same cut, so their mean can
be closer to the truth than either: the label-level counterpart of the ``consensus`` solver
(:mod:`nrsfm.solvers.consensus`), made from label sets already solved and cached, at no extra solving cost.

Every set holds camera-frame shapes of the same frames (:func:`baselines.labels.make_labels`), each already
mirrored to one handedness within its set. Frame by frame, each shape is centred and, when the reflection
``z -> -z`` brings it closer to the first set's, mirrored; then the shapes are averaged with the given weights.
Where a set has no label (a failed cut, a point its cut never saw) the others' weights are scaled up; an entry
no set labels stays NaN. No ground truth takes part; the weights are a setting.
"""

from __future__ import annotations

import numpy as np

from baselines.labels import _MIRROR, LabelSet, label_error, labelled_frames
from nrsfm.errors import ValidationError


def parse_label_solvers(text: str) -> list[str]:
    """``"pr+empnd"`` -> ``["pr", "empnd"]``: the solvers of a mixed label set (one name: a plain set)."""
    names = [n.strip() for n in text.split("+")]
    if not all(names) or len(set(names)) != len(names):
        raise ValidationError(f"label solver: expected a registered solver or distinct solvers joined by '+' "
                              f"(e.g. 'pr+empnd'), got {text!r}")
    return names


def mix_shapes(shapes: list[np.ndarray], weights: np.ndarray) -> np.ndarray:
    """The weighted mean of `(F, P, 3)` camera-frame shapes of the same frames, each frame centred and its depth
    sign matched to the first array's.

    Args:
        shapes: one `(F, P, 3)` array per set, NaN where that set has no label.
        weights: `(len(shapes),)` non-negative weights, not all zero.

    Returns:
        `(F, P, 3)`: at each (frame, point) the weighted mean of the sets labelling it (weights rescaled over
        them), NaN where none does.
    """
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != (len(shapes),) or (weights < 0).any() or weights.sum() <= 0:
        raise ValidationError(f"mix_shapes: expected {len(shapes)} non-negative weights, not all 0, got "
                              f"{weights.tolist()}")
    if len({s.shape for s in shapes}) != 1:
        raise ValidationError(f"mix_shapes: expected label arrays of one shape (F, P, 3), got "
                              f"{[s.shape for s in shapes]}")
    centred = []
    for s in shapes:
        ok = np.isfinite(s).all(axis=2, keepdims=True)  # (F, P, 1)
        count = ok.sum(axis=1, keepdims=True)  # (F, 1, 1)
        centre = np.where(ok, s, 0.0).sum(axis=1, keepdims=True) / np.maximum(count, 1)
        centred.append(np.where(ok, s - centre, np.nan))
    ref = centred[0]
    total = np.zeros_like(ref)
    weight_sum = np.zeros(ref.shape[:2] + (1,))
    for x, w in zip(centred, weights):
        both = np.isfinite(ref).all(axis=2, keepdims=True) & np.isfinite(x).all(axis=2, keepdims=True)
        same = np.where(both, (x - ref) ** 2, 0.0).sum(axis=(1, 2))  # (F,)
        mirrored = np.where(both, (x * _MIRROR - ref) ** 2, 0.0).sum(axis=(1, 2))
        x = np.where((mirrored < same)[:, None, None], x * _MIRROR, x)
        ok = np.isfinite(x).all(axis=2, keepdims=True)
        total += w * np.where(ok, x, 0.0)
        weight_sum += w * ok
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(weight_sum > 0, total / weight_sum, np.nan)


def mix_labels(sets: list[LabelSet], weights=None, truth: list | None = None) -> LabelSet:
    """The frame-by-frame weighted mean (:func:`mix_shapes`) of label sets of the same training sequences.

    Args:
        sets: two or more :class:`~baselines.labels.LabelSet` of the same sequences (the first sets the depth sign).
        weights: one non-negative weight per set (default: equal).
        truth: sequences frame for frame with the labels whose ``points_3d`` score the mixture (``label_mpjpe``).

    Returns:
        A :class:`LabelSet` whose summary names the methods, their weights and parameters, the cuts that failed in
        every set, and the summed solving time.
    """
    if len(sets) < 2:
        raise ValidationError(f"mix_labels: expected two or more label sets, got {len(sets)}")
    weights = np.full(len(sets), 1.0 / len(sets)) if weights is None else np.asarray(weights, dtype=np.float64)
    if any(len(s.labels) != len(sets[0].labels) for s in sets):
        raise ValidationError("mix_labels: expected label sets of the same sequences, got "
                              f"{[len(s.labels) for s in sets]} sequences")
    labels = [mix_shapes([s.labels[i] for s in sets], weights) for i in range(len(sets[0].labels))]
    failed = {k: "; ".join(s.failed[k] for s in sets) for k in sets[0].failed if all(k in s.failed for s in sets)}
    first = sets[0].summary
    labelled = int(sum(labelled_frames(lab).sum() for lab in labels))
    summary = {**first, "method": "+".join(s.summary["method"] for s in sets),
               "params": {s.summary["method"]: s.summary["params"] for s in sets},
               "weights": (weights / weights.sum()).tolist(), "failed": len(failed),
               "labelled_frames": labelled,
               "unlabelled_points": int(sum((~np.isfinite(lab[labelled_frames(lab)]).all(axis=2)).sum()
                                            for lab in labels)),
               "seconds": float(sum(s.summary["seconds"] for s in sets)),
               "label_mpjpe": label_error(labels, truth) if truth is not None else None,
               "components": [{k: s.summary[k] for k in ("method", "failed", "label_mpjpe", "seconds")}
                              for s in sets]}
    return LabelSet(labels, summary, failed)
