"""The table rows' registry and what they share: the data split, the run's options, predictions, the schedule.

A method is a function ``run(split, ctx) -> list of (F, P, 3)`` normalised predictions for ``split.test_inputs``
(scaled back to millimetres by :func:`millimetres`). Baselines become table rows by calling
:func:`register_method`; the table code never changes. The built-in rows live in :mod:`benchmarks.methods`,
whose :func:`~benchmarks.methods.methods` lists every registered row.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmarks.common import config_hash
from nrsfm.errors import ValidationError
from nrsfm.sequence import Sequence

log = logging.getLogger(__name__)


#: ``--quick``: the per-sequence solvers (pseudo-labels and the rows on the test data) with light settings, stated
#: in each table's labels table and timings: PR with one continuation stage of 50 iterations and EM-PND with 20 EM
#: iterations (smoke runs of the pipeline, not their accuracy), SPM's shape step by ADMM in place of cvxpy (the same
#: labels to 0.01 mm on the synthetic humans, 16 times faster).
QUICK_LABEL_PARAMS = {"pr": {"max_iter": 50, "stages": 1}, "spm": {"shape_solver": "admm"},
                      "empnd": {"max_iter": 20}}


@dataclass
class Split:
    """Train / test data of one input type.

    Attributes:
        train_inputs / train_targets: network inputs and the 2D the data term
            compares with (the same sequences unless e.g. SH inputs with GT 2D).
        test_inputs: test 2D; test_truth: the same frames with ``points_3d``.
        input_type: ``gt-ortho``, ``gt-persp``, ``sh``, or ``rgb`` (images, with 2D for the data term and the
            pseudo-labels); sampling: group sampling.
        tag: identifies the data (part of every cache key).
        train_images / test_images: for ``rgb``, one image source per sequence (:mod:`prn.images`).
        labels_tag: identifies the 2D the pseudo-labels are solved from (default ``tag``), so that tables on the
            same 2D share them.
        targets_labels_tag: the same for ``train_targets`` where they are other sequences than ``train_inputs``
            (SH: the ground-truth 2D that the data term compares with).
    """

    train_inputs: list[Sequence]
    train_targets: list[Sequence]
    test_inputs: list[Sequence]
    test_truth: list[Sequence]
    input_type: str
    sampling: str = "multiview"
    tag: str = ""
    train_images: list | None = None
    test_images: list | None = None
    labels_tag: str = ""
    targets_labels_tag: str = ""


class NotRun(Exception):
    """Raised by a row that cannot run on the data it was given; the table prints ``not run: <message>``."""


class Predictions(list):
    """A row's test predictions: one `(F, P, 3)` array per test sequence in PRN's per-frame units.

    ``millimetres``, where set, holds the same shapes scaled back to the ground truth's units by the method's own
    rule (C3DPO on the authors' inputs: each frame's mean hip distance; inputs normalised on their visible points:
    the ground truth's statistic over those points); otherwise :func:`millimetres` applies the PRN protocol's
    (each frame by the ground truth's xy Frobenius norm)."""

    millimetres: list[np.ndarray] | None = None


def millimetres(preds: list[np.ndarray], truth: list[Sequence]) -> list[np.ndarray]:
    """`(F, P, 3)` predictions of ``preds`` in the ground truth's units, one per test sequence
    (:class:`Predictions`)."""
    from prn.data import denormalize

    own = getattr(preds, "millimetres", None)
    if own is not None:
        return list(own)
    return [denormalize(p, t.points_3d) for p, t in zip(preds, truth)]


@dataclass
class RunContext:
    """Options of one harness run: output folder (caches), iterations, seed, progress bars, parallel jobs (the
    pseudo-label solves), C3DPO's minibatch, the PRN rows' missing-point rate and point groups in training,
    the networks' width.

    By default a cached model is reused and an interrupted training resumes
    from its checkpoint; ``retrain`` ignores both and trains from scratch.
    """

    out_dir: Path
    iterations: int
    seed: int = 0
    progress: bool = True
    device: str = "auto"
    retrain: bool = False
    jobs: int = 1
    c3dpo_batch: int = 1024
    c3dpo_iterations: int | None = None
    c3dpo_rescale: float = 1.0
    c3dpo_lr: float = 1e-3  # the authors' Human3.6M lr
    c3dpo_precision: str = "fp32"  # "bf16": the trunks under bfloat16 autocast
    c3dpo_monitor: bool = False  # the test split's MPJPE at every checkpoint (a diagnostic)
    c3dpo_cuda_graph: bool = True  # on a GPU, replay C3DPO's iterations as CUDA graphs (False: op by op)
    c3dpo_compile: bool = False  # compile C3DPO's forward and backward passes with torch.compile
    c3dpo_optimizer: str = "sgd"  # the authors' Human3.6M breed; "adam" is their code's other
    c3dpo_repeat: int = 1  # each C3DPO minibatch used for this many iterations (8: the authors' loader as it ran)
    c3dpo_inputs: str = "hip"  # methods.C3DPO_INPUTS: the authors' per-frame hip normalisation, "centred", "prn"
    missing_points: float = 0.0  # PRN rows: the fraction of points dropped per training sample (Table S1)
    missing_in_loss: bool = True  # PRN rows: dropped points weigh 0 in the data term too (False: input only)
    normalise_on: str = "visible"  # PRN rows: test inputs normalised on their visible points, or "all" (Table S1)
    width: int = 1024  # the network's hidden width (4096 for SURREAL, Table 4)
    point_groups: int = 1  # PRN rows: random point groups of the PR loss per iteration (dense shapes, Table 4)
    compress_schedule: bool = False  # the lr step scaled by iterations / 70,000 (registry.schedule)
    groups: int = 4  # PRN rows: alignment groups per minibatch (4 on Human3.6M and SURREAL; 1 on 300-VW's faces)
    group_size: int = 32  # frames per group (4 x 32 = 1 x 128: PRN's minibatch)
    label_params: dict = field(default_factory=dict)  # "+NN" rows: solver name -> its parameters for the labels
    label_solver: str = "empnd"  # PRN-L: the solver of its pseudo-labels (chosen on S8 held out: RESULTS.md)
    label_weight: float = 1.0  # PRN-L: the labels' weight beside the PR loss (prn.train.TrainConfig.label_weight)
    label_decay: str = "none"  # PRN-L: "none" (chosen on S8 held out) or "linear" (to 0 at the end of training)
    ema: float | None = None  # the networks' weight averaging (prn.train.TrainConfig.ema); None: each row's own
    label_frames: str = "as-is"  # "+NN" rows and PRN-L: solve the 2D as it is, or "unit" (prn.data.unit_frames)
    mirror_test: bool | None = None  # test-time mirroring (prn.train.predict_mirrored); None: each row's own
    mirror_train: bool | None = None  # mirrored copies of the training frames (and labels); None: each row's own
    label_source: str | None = None  # pseudo-labels solved from the "inputs" or the data term's "targets"; None: row's
    network: str = "resnet50"  # rgb input: PRN-CNN's backbone (prn.images.BACKBONES)
    labels_dir: Path | None = None  # "+NN" rows: the pseudo-labels' cache (default: out_dir / "labels")
    timings: dict = field(default_factory=dict)

    def cache_dir(self, method: str, config: dict) -> Path:
        return self.out_dir / "cache" / f"{method.replace(' ', '_').replace('/', '_')}-{config_hash(config)}"


@dataclass(frozen=True)
class Method:
    name: str
    run: Callable[[Split, RunContext], list[np.ndarray]]
    inputs: tuple[str, ...]
    description: str


_METHODS: dict[str, Method] = {}


def register_method(name: str, inputs: tuple[str, ...], description: str):
    """Decorator registering ``run(split, ctx)`` as a table row named ``name``."""

    def deco(fn):
        _METHODS[name] = Method(name, fn, inputs, description)
        return fn

    return deco


def registered() -> dict[str, Method]:
    """The rows registered so far (:func:`benchmarks.methods.methods` adds the built-in ones)."""
    return dict(_METHODS)


def schedule(iterations: int, compress: bool = False, **overrides):
    """The paper's :class:`~prn.train.TrainConfig` for ``iterations``: lr x0.8 every 5,000 iterations whatever the
    count (the paper's schedule); ``compress`` scales that step by ``iterations / 70,000`` instead (a shorter run
    that ends as far down the schedule as the paper's 70k do)."""
    from prn.train import TrainConfig

    step = max(1, round(TrainConfig.lr_step * iterations / 70_000)) if compress else TrainConfig.lr_step
    return dataclasses.replace(TrainConfig(), iterations=iterations, lr_step=step,
                               checkpoint_every=max(100, iterations // 20), **overrides)


def schedule_text(iterations: int, compress: bool) -> str:
    """How a table states its learning-rate schedule."""
    cfg = schedule(iterations, compress)
    if compress:
        return (f"lr x0.8 every {cfg.lr_step:,} iterations (the paper's 5,000 compressed to {iterations:,} of its "
                "70,000)")
    return "lr x0.8 every 5,000 iterations (the paper's)"
