"""The PRN-FCN network trained with a supervised 3D loss: the "+NN" rows (pseudo-labels) and the "GT 3D" row.

The network, its width, input normalisation, optimiser, learning-rate schedule, batch-norm freeze and checkpoints
are PRN-FCN's (:mod:`prn.train`); only the loss changes: the mean squared 3D error of the predicted `(P, 3)`
shape against the target, over minibatches of ``batch`` frames drawn uniformly from the labelled training frames.
Targets are normalised as the PRN protocol normalises ground truth: centred on the joints' mean and divided by
their own xy Frobenius norm (:func:`prn.data.normalize_3d`), so predictions are scaled back to millimetres by the
test ground truth's xy norm exactly like PRN's.

Frames without a label (their NRSfM cut failed) are left out; points without a label (a point the cut never saw:
NaN in the target) are left out of the loss, and such a target is normalised on its labelled points as a test input
is on its visible ones (:func:`prn.data.normalize_2d`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np
import torch

from nrsfm.errors import ValidationError
from nrsfm.sequence import Sequence
from prn.data import TrainingSet, build_training_set, normalize_2d, normalize_3d
from prn.train import TrainConfig, TrainResult, train

log = logging.getLogger(__name__)


@dataclass
class Supervised3D:
    """The supervised objective (:class:`prn.train.Objective`).

    Attributes:
        targets: `(N, P, 3)` normalised target shapes, one per training frame (NaN: an unlabelled frame or point).
        batch: frames per minibatch (PRN's 128 = 4 groups x 32).
    """

    targets: np.ndarray
    batch: int = 128

    def __post_init__(self) -> None:
        mask = np.isfinite(self.targets).all(axis=2)  # (N, P) labelled points
        self.labelled = np.flatnonzero(mask.any(axis=1))
        if not len(self.labelled):
            raise ValidationError("Supervised3D: no training frame has a label (every NRSfM cut failed)")
        self.every_point = bool(mask[self.labelled].all())
        self._targets = torch.as_tensor(np.nan_to_num(self.targets), dtype=torch.float32)
        self._mask = torch.as_tensor(mask, dtype=torch.float32)

    def to(self, device: torch.device) -> "Supervised3D":
        self._targets, self._mask = self._targets.to(device), self._mask.to(device)
        return self

    def sample(self, rng: np.random.Generator) -> np.ndarray:
        return rng.choice(self.labelled, size=self.batch, replace=len(self.labelled) < self.batch)

    def loss(self, pred: torch.Tensor, idx: torch.Tensor, visible: torch.Tensor | None = None) -> torch.Tensor:
        target = self._targets[idx]
        if visible is not None:  # the input was normalised on these points: the target alike
            from prn.train import renormalise

            if not self.every_point:
                raise ValidationError("Supervised3D: targets with unlabelled points cannot be renormalised on "
                                      "the visible points of a training input; train without missing_points")
            target = renormalise(target, visible, zero_missing=False)
        if self.every_point:
            return ((pred - target) ** 2).sum(dim=2).mean()
        mask = self._mask[idx]
        return (((pred - target) ** 2).sum(dim=2) * mask).sum() / mask.sum().clamp_min(1.0)


def normalised_targets(shapes: list[np.ndarray]) -> np.ndarray:
    """`(N, P, 3)` targets from per-sequence `(F, P, 3)` shapes: :func:`normalize_3d`; a frame with NaN points is
    centred on its finite points and divided by their xy norm times ``sqrt(P / finite)``, as
    :func:`prn.data.normalize_2d` treats an input's visible points (its NaN points and NaN frames stay NaN)."""
    out = []
    for s in shapes:
        t = np.full(s.shape, np.nan)
        has = np.isfinite(s).all(axis=2)  # (F, P)
        full = has.all(axis=1)
        if full.any():
            t[full] = normalize_3d(s[full])[0]
        part = has.any(axis=1) & ~full
        if part.any():
            x, w = s[part], has[part]
            _, scale = normalize_2d(x[..., :2], w)
            centre = np.nan_to_num(x).sum(axis=1, keepdims=True) / w.sum(axis=1)[:, None, None]
            t[part] = (x - centre) / scale[:, None, None]
        out.append(t)
    return np.concatenate(out)


def train_supervised(inputs: list[Sequence], shapes: list[np.ndarray], config: TrainConfig,
                     out_dir: str | os.PathLike | None, *, targets_2d: list[Sequence] | None = None,
                     resume: bool = True, progress: bool = True, images: list | None = None
                     ) -> tuple[TrainResult, TrainingSet]:
    """Train PRN-FCN on ``inputs`` to predict ``shapes`` (per sequence `(F, P, 3)`, camera frame; NaN frames are
    skipped), or, with ``images`` (one image source per sequence) and ``config.network`` a CNN backbone, to predict
    them from the images. Returns the training result and the :class:`~prn.data.TrainingSet` (its input
    normalisation is the one to apply to test inputs)."""
    if len(shapes) != len(inputs):
        raise ValidationError(f"shapes: expected one array per input sequence ({len(inputs)}), got {len(shapes)}")
    data = build_training_set(inputs, targets_2d, sampling="random", images=images)
    objective = Supervised3D(normalised_targets(shapes), batch=config.groups * config.group_size)
    log.info("supervised 3D: %d of %d training frames labelled", len(objective.labelled), len(data.inputs))
    return train(data, config, out_dir, resume=resume, progress=progress, objective=objective), data
