"""The PRN training recipe, with checkpoints, resume and progress.

Defaults are the paper's (ECCV 2020, supplementary): Adam (0.9, 0.999), lr
1e-4 multiplied by 0.8 every 5000 iterations, lambda = 0.05, minibatch 128 =
4 groups x 32 frames, 70k iterations with batch-norm statistics frozen for
the last 30%. Two choices come from the authors' released code, not the
paper: weight decay 1e-4, and the learning-rate schedule restarting where the
batch-norm statistics freeze (their code trains 50k iterations, then starts a
new solver with frozen statistics whose counter and schedule begin again;
50k + 20k for the default 70k).

Checkpoints are written atomically every ``checkpoint_every`` iterations to
``<out>/checkpoint.pt``; :func:`train` continues from it when ``resume`` is
True. A NaN/inf loss stops training with :class:`TrainingError` naming the
iteration and the last good checkpoint (on a GPU the loss is checked at the
logged iterations and before every checkpoint, so that the device never waits
for the host otherwise).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from nrsfm.device import indices_to, pick_device, restore_rng_state, rng_state
from nrsfm.errors import NRSfMError, ValidationError
from prn.data import TrainingSet
from prn.loss import PRLossParts, pr_loss
from prn.model import PRNCNN, PRNFCN

log = logging.getLogger(__name__)


class TrainingError(NRSfMError, RuntimeError):
    """Training cannot continue (e.g. the loss became NaN)."""


@dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (paper defaults).

    ``missing_points`` > 0 reproduces the missing-points experiment
    (supplementary Table 1): in every training sample each point goes missing
    with that probability, set to 0 in the input and given weight 0 in the
    data term (the same points, as inputs and outputs correspond one to one).
    With ``missing_in_loss=False`` they go missing from the input only and the
    data term keeps every point's 2D, as the paper's Stacked Hourglass
    networks read detections and are trained against ground-truth 2D. Under
    another ``objective`` (a supervised 3D loss) they leave the input only.
    ``missing_normalise="visible"`` normalises each such sample again on the
    points it keeps (:func:`renormalise`: its input and its 2D targets, and a
    supervised objective's 3D target), as a test frame whose points were never
    observed must be; ``"all"`` keeps the normalisation of all its points, the
    dropped ones included (their 2D enters through the centre and the scale).

    ``point_groups`` > 1 is the paper's recipe for dense shapes (SURREAL, 6,890
    points): every iteration the points are split at random into that many
    groups of equal size (the remainder sits the iteration out) and the PR
    loss is summed over them, each group aligned on its own points.

    ``label_weight`` > 0 adds pseudo-labels to the PR loss (``train(...,
    labels=...)``: one 3D shape per training frame, e.g. a per-sequence
    NRSfM solver's, normalised as :func:`prn.data.normalize_3d` does): the
    term ``label_weight * 1/2 sum ||X - L||^2`` over the labelled points of
    each minibatch, on the scale of the data term. ``label_decay="linear"``
    lowers its weight linearly to 0 at the last iteration, so that the PR loss
    alone shapes the end of training; ``"none"`` keeps it.

    ``ema`` in (0, 1) keeps an exponential moving average of the weights,
    ``A <- ema * A + (1 - ema) * W`` after every step from the BN freeze on
    (``phase_boundary``; the first such step copies), and returns and saves it
    instead of the last iterate: the average of the last ``~1 / (1 - ema)``
    iterations, less tied to the last minibatches. Every averaged step was
    trained against the same frozen BN statistics, which the average keeps;
    averaging the statistics too, or recomputing them from the data, does not
    match weights that were tuned to the frozen ones. 0 (the default, the
    paper's) keeps the last iterate.

    ``network``: ``"fcn"`` (PRN-FCN on 2D points) or a torchvision backbone
    name (:data:`prn.images.BACKBONES`, ``"resnet50"`` as the paper) for
    PRN-CNN on the training set's images; ``pretrained`` starts the backbone
    from ImageNet weights when they are in torch's local cache.
    """

    iterations: int = 70_000
    bn_freeze_fraction: float = 0.3
    lr: float = 1e-4
    lr_decay: float = 0.8
    lr_step: int = 5000
    weight_decay: float = 1e-4
    lam: float = 0.05
    groups: int = 4
    group_size: int = 32
    frame_gap: int = 5
    width: int = 1024
    seed: int = 0
    checkpoint_every: int = 2000
    device: str = "auto"
    missing_points: float = 0.0
    missing_in_loss: bool = True
    missing_normalise: str = "all"
    point_groups: int = 1
    network: str = "fcn"
    pretrained: bool = True
    label_weight: float = 0.0
    label_decay: str = "none"
    ema: float = 0.0

    def __post_init__(self) -> None:
        if self.iterations < 1 or self.groups < 1 or self.group_size < 2:
            raise ValidationError(f"TrainConfig: expected iterations >= 1, groups >= 1, group_size >= 2, got "
                                  f"{self.iterations}, {self.groups}, {self.group_size}")
        if not 0 <= self.bn_freeze_fraction < 1:
            raise ValidationError(f"bn_freeze_fraction: expected [0, 1), got {self.bn_freeze_fraction}")
        if self.point_groups < 1:
            raise ValidationError(f"point_groups: expected an integer >= 1, got {self.point_groups}")
        if not 0 <= self.missing_points < 1:
            raise ValidationError(f"missing_points: expected a fraction in [0, 1), got {self.missing_points}")
        if self.missing_normalise not in ("all", "visible"):
            raise ValidationError(f"missing_normalise: expected 'all' or 'visible', got {self.missing_normalise!r}")
        if self.network != "fcn" and self.network not in _backbones():
            raise ValidationError(f"network: expected 'fcn' or one of {_backbones()}, got {self.network!r}")
        if self.lam < 0 or self.lr <= 0:
            raise ValidationError(f"TrainConfig: expected lam >= 0 and lr > 0, got {self.lam}, {self.lr}")
        if not 0 <= self.ema < 1:
            raise ValidationError(f"ema: expected a decay in [0, 1) (0: the last iterate), got {self.ema}")
        if self.ema > 0 and self.phase_boundary >= self.iterations:
            raise ValidationError(f"ema: the weights are averaged after the BN freeze, and bn_freeze_fraction "
                                  f"{self.bn_freeze_fraction} of {self.iterations} iterations leaves none; raise "
                                  "bn_freeze_fraction or set ema=0")
        if self.label_weight < 0 or self.label_decay not in ("none", "linear"):
            raise ValidationError(f"TrainConfig: expected label_weight >= 0 and label_decay 'none' or 'linear', "
                                  f"got {self.label_weight}, {self.label_decay!r}")

    def label_weight_at(self, iteration: int) -> float:
        """The pseudo-labels' weight at ``iteration`` (``label_decay``)."""
        if self.label_decay == "linear":
            return self.label_weight * max(0.0, 1.0 - iteration / self.iterations)
        return self.label_weight

    @property
    def phase_boundary(self) -> int:
        """The iteration at which BN statistics freeze and the lr schedule restarts."""
        return int(round(self.iterations * (1 - self.bn_freeze_fraction)))

    def lr_at(self, iteration: int) -> float:
        local = iteration if iteration < self.phase_boundary else iteration - self.phase_boundary
        return self.lr * self.lr_decay ** (local // self.lr_step)


_DEFAULTS = dataclasses.asdict(TrainConfig())


def _backbones() -> tuple[str, ...]:
    from prn.images import BACKBONES

    return BACKBONES


def build_model(config: TrainConfig, n_points: int, n_inputs: int, image_size: int | None = None) -> torch.nn.Module:
    """PRN-FCN, or PRN-CNN for ``config.network`` other than ``"fcn"`` (images of side ``image_size``)."""
    if config.network == "fcn":
        return PRNFCN(n_points, n_inputs, config.width)
    if image_size is None:
        raise ValidationError(f"network {config.network!r}: the training set carries no images; pass images= to "
                              "build_training_set, or train network='fcn'")
    return PRNCNN(n_points, backbone=config.network, image_size=image_size, width=config.width,
                  pretrained=config.pretrained)


def adam(params, *, lr: float, weight_decay: float) -> torch.optim.Adam:
    """Adam (0.9, 0.999) as one fused kernel where torch has it for the parameters' device (ten times faster on a
    CPU than the default per-tensor loop, the same arithmetic), else the default implementation."""
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, betas=(0.9, 0.999), weight_decay=weight_decay, fused=True)
    except (RuntimeError, TypeError, ValueError):
        return torch.optim.Adam(params, lr=lr, betas=(0.9, 0.999), weight_decay=weight_decay)


def _freeze_bn_stats(model: torch.nn.Module) -> None:
    for m in model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.eval()  # running statistics frozen; affine scale/shift still trained


def atomic_save(obj: dict, path: Path) -> None:
    """``torch.save`` to a temporary file beside ``path``, then renamed onto it."""
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


@dataclass
class TrainResult:
    """A trained model, its history (loss every ``log_every`` iterations) and timings
    (``benchmarks.studies.speed_prn`` measures the loss's own share of an iteration)."""

    model: PRNFCN
    config: TrainConfig
    history: list[dict]
    seconds: float
    iterations_run: int
    iterations_per_second: float


class Objective(Protocol):
    """Another training objective for the same network and recipe (the supervised "+NN" baselines).

    ``to(device)`` returns the objective with its tensors on ``device``; ``sample(rng)`` the `(N,)` training frames
    of one minibatch; ``loss(pred, idx)`` the scalar loss of the `(N, P, 3)` predictions for frames ``idx``, and
    ``loss(pred, idx, visible=w)`` the same for inputs normalised on the points of nonzero `(N, P)` weight ``w``
    (``TrainConfig.missing_normalise``), whose targets must be normalised alike.
    """

    def to(self, device: torch.device) -> "Objective": ...

    def sample(self, rng: np.random.Generator) -> np.ndarray: ...

    def loss(self, pred: torch.Tensor, idx: torch.Tensor, visible: torch.Tensor | None = None) -> torch.Tensor: ...


def train(data: TrainingSet, config: TrainConfig = TrainConfig(), out_dir: str | os.PathLike | None = None, *,
          resume: bool = True, progress: bool = True, log_every: int = 100,
          stop_after: int | None = None, objective: Objective | None = None,
          labels: np.ndarray | None = None) -> TrainResult:
    """Train PRN-FCN on ``data`` with the PR loss (or ``objective``).

    Args:
        data: from :func:`prn.data.build_training_set`.
        config: hyper-parameters; ``lam = 0`` trains "PRN w/o reg".
        objective: replaces the PR loss and the group sampling (same network, optimiser, schedule, checkpoints).
        labels: with ``config.label_weight`` > 0, `(N, P, 3)` normalised pseudo-labels, one per training frame
            of ``data`` (NaN: an unlabelled frame or point), pulled towards beside the PR loss.
        out_dir: where ``checkpoint.pt`` and ``model.pt`` go (None: no files).
        resume: continue from ``out_dir/checkpoint.pt`` when it exists.
        progress: show a tqdm bar (quiet when stderr is not a terminal).
        stop_after: stop (with a checkpoint) after this many iterations in this
            call, as an interruption would; a later call with ``resume`` goes on.

    Returns:
        :class:`TrainResult`.
    """
    with no_denormals():
        return _train(data, config, out_dir, resume=resume, progress=progress, log_every=log_every,
                      stop_after=stop_after, objective=objective, labels=labels)


def _point_groups(pred: torch.Tensor, y: torch.Tensor, w: torch.Tensor, k: int):
    """Split the points of `(N, P, 3)` shapes, `(N, P, 2)` targets and `(N, P)` weights at random into ``k``
    groups of ``P // k`` points, stacked along the frame axis point-group-major: `(k N, P // k, ...)`, so that every
    frame group of the PR loss lies within one point group."""
    n, p = w.shape
    m = p // k
    if m < 1:
        raise ValidationError(f"point_groups: expected at most P = {p} groups, got {k}")
    perm = torch.randperm(p, device=pred.device)[: k * m].reshape(k, m)

    def split(t):
        return t[:, perm].transpose(0, 1).reshape(k * n, m, *t.shape[2:])

    return split(pred), split(y), split(w)


def renormalise(points: torch.Tensor, weights: torch.Tensor, zero_missing: bool = True) -> torch.Tensor:
    """`(N, P, D)` points centred on the points of nonzero `(N, P)` weight and divided by their xy Frobenius norm
    times ``sqrt(P / kept)``: :func:`prn.data.normalize_2d` of the kept points, the others set to 0 (or, without
    ``zero_missing``, moved and scaled with the rest: a 3D target shape)."""
    w = (weights > 0).to(points.dtype).unsqueeze(-1)  # (N, P, 1)
    count = w.sum(dim=1, keepdim=True).clamp_min(1.0)  # (N, 1, 1)
    c = points - (points * w).sum(dim=1, keepdim=True) / count
    scale = (c[..., :2] * w).flatten(1).norm(dim=1) * torch.sqrt(points.shape[1] / count[:, 0, 0])
    return (c * w if zero_missing else c) / scale.clamp_min(1e-12)[:, None, None]


@contextlib.contextmanager
def no_denormals():
    """Flush denormal floats to zero inside the block, restoring the default after.

    Without the regulariser the z head gets no data-term gradient and weight
    decay drives it into denormal floats, which are ~100x slower on CPUs (PRN
    w/o reg fell from 8 to under 2 it/s). The setting is process-global, so it
    is scoped here rather than left on.
    """
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


def _train(data: TrainingSet, config: TrainConfig, out_dir, *, resume: bool, progress: bool, log_every: int,
           stop_after: int | None, objective: Objective | None, labels: np.ndarray | None) -> TrainResult:
    from tqdm.auto import tqdm

    device = pick_device(config.device)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    image_size = None if data.images is None else int(data.images.shape[1])
    model = build_model(config, data.n_points, data.n_inputs, image_size).to(device)
    if config.network != "fcn":
        log.info("PRN-CNN backbone: %s", model.initialisation)
    opt = adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    averaged = None
    if config.ema > 0:
        from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

        averaged = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(config.ema), use_buffers=False)
    start, history = 0, []
    out = Path(out_dir) if out_dir is not None else None
    ckpt_path = out / "checkpoint.pt" if out is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    if ckpt_path is not None and resume and ckpt_path.exists():
        state = torch.load(ckpt_path, map_location=device, weights_only=False)
        if {**_DEFAULTS, **state["config"]} != dataclasses.asdict(config):  # fields added later: their defaults
            raise ValidationError(f"{ckpt_path}: the checkpoint was made with another configuration; use another "
                                  "output folder or resume=False")
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        if averaged is not None:
            averaged.load_state_dict(state["ema"])
        start, history = state["iteration"], state["history"]
        rng.bit_generator.state = state["numpy_rng"]
        restore_rng_state(state, device)
        log.info("resumed from %s at iteration %d", ckpt_path, start)

    if objective is not None:
        objective = objective.to(device)
        if config.missing_points > 0 and config.missing_normalise == "visible" and data.n_inputs != data.n_points:
            raise ValidationError(f"missing_normalise='visible' with a supervised objective: expected the inputs to "
                                  f"be the output points, got {data.n_inputs} inputs for {data.n_points} outputs")
    x_all = torch.as_tensor(data.inputs, dtype=torch.float32, device=device)
    xw_all = torch.as_tensor(data.input_weights, dtype=torch.float32, device=device)

    def forward(idx: torch.Tensor, xw: torch.Tensor, x: torch.Tensor | None = None) -> torch.Tensor:
        if config.network == "fcn":
            return model(x_all[idx] if x is None else x, xw)
        from prn.images import to_tensor

        return model(to_tensor(data.images[idx.cpu().numpy()], device))

    if config.label_weight > 0:
        if config.missing_points > 0:
            raise ValidationError("label_weight > 0 with missing_points > 0: the pseudo-labels would need the "
                                  "dropped points' normalisation; train one or the other")
        if labels is None or objective is not None or np.shape(labels) != (len(data.inputs), data.n_points, 3):
            raise ValidationError(f"label_weight > 0: expected labels of shape ({len(data.inputs)}, {data.n_points}, "
                                  f"3) beside the PR loss, got {None if labels is None else np.shape(labels)}"
                                  + (" with another objective" if objective is not None else ""))
        labelled = torch.as_tensor(np.isfinite(labels).all(axis=2), device=device)  # (N, P) labelled points
        label_all = torch.as_tensor(np.nan_to_num(labels), dtype=torch.float32, device=device)
    y_all = torch.as_tensor(data.targets, dtype=torch.float32, device=device)
    yw_all = torch.as_tensor(data.target_weights, dtype=torch.float32, device=device)
    parts = PRLossParts()
    model.train()
    if start >= config.phase_boundary:
        _freeze_bn_stats(model)
    t_begin = time.perf_counter()
    desc = f"PRN lam={config.lam}" if objective is None else type(objective).__name__
    bar = tqdm(total=config.iterations, initial=start, desc=desc, disable=not progress, mininterval=2.0)
    end = config.iterations if stop_after is None else min(config.iterations, start + stop_after)
    for it in range(start, end):
        if it == config.phase_boundary:
            _freeze_bn_stats(model)
        for g in opt.param_groups:
            g["lr"] = config.lr_at(it)
        logged = (it + 1) % log_every == 0 or it == start
        at_checkpoint = (it + 1) % config.checkpoint_every == 0 or it + 1 == end
        visible = config.missing_points > 0 and config.missing_normalise == "visible"
        if objective is not None:
            idx = indices_to(objective.sample(rng), device)
            xw, x = xw_all[idx], None
            if config.missing_points > 0 and config.network == "fcn":  # the objective keeps every point's target
                xw = xw * (torch.rand(xw.shape, device=device) >= config.missing_points).to(xw.dtype)
                if visible:
                    x = renormalise(x_all[idx], xw)
            pred = forward(idx, xw, x)
            loss = objective.loss(pred, idx) if x is None else objective.loss(pred, idx, visible=xw)
        else:
            idx = indices_to(data.sample_groups(rng, config.groups, config.group_size, config.frame_gap), device)
            xw, yw = xw_all[idx], yw_all[idx]
            x, y = None, y_all[idx]
            if config.missing_points > 0:
                keep = (torch.rand(len(idx), yw.shape[1], device=device) >= config.missing_points).to(yw.dtype)
                if config.missing_in_loss:
                    yw = yw * keep
                if data.input_points is not None and len(data.input_points) == yw.shape[1]:
                    xw = xw * keep
                if visible:
                    x, y = renormalise(x_all[idx], xw), renormalise(y, yw)
            pred = forward(idx, xw, x)
            pulled = None
            if config.label_weight > 0:  # 1/2 sum ||X - L||^2 over the labelled points
                pulled = 0.5 * (((pred - label_all[idx]) * labelled[idx].to(pred.dtype)[:, :, None]) ** 2).sum()
            if config.point_groups > 1:
                pred, y, yw = _point_groups(pred, y, yw, config.point_groups)
            loss = pr_loss(pred, y, yw, lam=config.lam, group_size=config.group_size,
                           parts=parts if logged else None)  # filling it waits for the device
            if pulled is not None:
                loss = loss + config.label_weight_at(it) * pulled
        opt.zero_grad(set_to_none=True)
        loss.backward()
        # on a GPU the check waits for the queued work, so it runs at the logged iterations and checkpoints only
        if (device.type != "cuda" or logged or at_checkpoint) and not torch.isfinite(loss):
            where = f"; the last good checkpoint is {ckpt_path}" if ckpt_path and ckpt_path.exists() else ""
            raise TrainingError(f"the loss became {loss.item()} at iteration {it}{where}; lower the learning rate "
                                "or check the inputs for NaN")
        opt.step()
        if averaged is not None and it >= config.phase_boundary:
            averaged.update_parameters(model)
        if logged:
            entry = {"iteration": it + 1, "loss": loss.item(), "lr": config.lr_at(it)}
            if objective is None:  # the PR loss's two terms
                entry.update(data=parts.data, nuclear=parts.nuclear)
            history.append(entry)
            bar.set_postfix(loss=f"{history[-1]['loss']:.4g}")
        bar.update(1)
        if ckpt_path is not None and at_checkpoint:
            atomic_save({"model": model.state_dict(), "optimizer": opt.state_dict(), "iteration": it + 1,
                          "history": history, "config": dataclasses.asdict(config),
                          "numpy_rng": rng.bit_generator.state, **rng_state(device),
                          **({"ema": averaged.state_dict()} if averaged is not None else {})}, ckpt_path)
    bar.close()
    if averaged is not None and averaged.n_averaged.item() > 0:
        with torch.no_grad():  # the frozen BN statistics every averaged step was trained with
            for name, buf in model.named_buffers():
                averaged.module.get_buffer(name).copy_(buf)
        model = averaged.module
    seconds = time.perf_counter() - t_begin
    run = max(end - start, 0)
    if out is not None and end == config.iterations:
        atomic_save({"model": model.state_dict(), "config": dataclasses.asdict(config), "n_points": data.n_points,
                      "n_inputs": data.n_inputs, "image_size": image_size, "history": history}, out / "model.pt")
        (out / "train.json").write_text(json.dumps({"config": dataclasses.asdict(config), "seconds": seconds,
                                                    "iterations_run": run, "data": data.description,
                                                    "history": history}, indent=1))
    model.eval()
    return TrainResult(model=model, config=config, history=history, seconds=seconds, iterations_run=run,
                       iterations_per_second=run / seconds if seconds > 0 else float("nan"))


def load_model(path: str | os.PathLike, device: str = "auto") -> torch.nn.Module:
    """Load ``model.pt`` written by :func:`train` (PRN-FCN or PRN-CNN)."""
    state = torch.load(Path(path), map_location=pick_device(device), weights_only=False)
    cfg = state["config"]
    config = TrainConfig(**{k: v for k, v in cfg.items() if k in TrainConfig.__dataclass_fields__})
    model = build_model(dataclasses.replace(config, pretrained=False), state["n_points"], state["n_inputs"],
                        state.get("image_size"))
    model.load_state_dict(state["model"])
    return model.to(pick_device(device)).eval()


@torch.no_grad()
def predict(model: PRNFCN, inputs: np.ndarray, input_weights: np.ndarray | None = None,
            batch: int = 4096) -> np.ndarray:
    """Normalised `(N, P_in, 2)` inputs -> `(N, P, 3)` normalised shapes (model in eval mode)."""
    model.eval()
    device = next(model.parameters()).device
    out = []
    with no_denormals():
        for s in range(0, len(inputs), batch):
            x = torch.as_tensor(inputs[s:s + batch], dtype=torch.float32, device=device)
            w = None if input_weights is None else torch.as_tensor(input_weights[s:s + batch],
                                                                    dtype=torch.float32, device=device)
            out.append(model(x, w).double().cpu().numpy())
    return np.concatenate(out) if out else np.zeros((0, model.n_points, 3))


def predict_mirrored(model: PRNFCN, inputs: np.ndarray, input_weights: np.ndarray | None, input_perm: np.ndarray,
                     output_perm: np.ndarray, batch: int = 4096) -> np.ndarray:
    """The mean of the shapes :func:`predict` gives for the `(N, P_in, 2)` inputs and, mirrored back, for their
    mirror images (test-time mirroring; ``input_perm`` `(P_in,)` and ``output_perm`` `(P,)` pair each input and
    output point with its mirror partner, :func:`prn.data.mirror_permutation`). One frame at a time, like
    :func:`predict`: `(N, P, 3)` normalised shapes."""
    from prn.data import mirror_points

    plain = predict(model, inputs, input_weights, batch)
    weights = None if input_weights is None else np.asarray(input_weights)[:, input_perm]
    mirrored = predict(model, mirror_points(inputs, input_perm), weights, batch)
    return 0.5 * (plain + mirror_points(mirrored, output_perm))


@torch.no_grad()
def predict_images(model: torch.nn.Module, images, batch: int = 64) -> np.ndarray:
    """`(N, H, W, 3)` uint8 images (any image source, :mod:`prn.images`) -> `(N, P, 3)` normalised shapes."""
    from prn.images import to_tensor

    model.eval()
    device = next(model.parameters()).device
    out = [model(to_tensor(images[np.arange(s, min(s + batch, len(images)))], device)).double().cpu().numpy()
           for s in range(0, len(images), batch)]
    return np.concatenate(out) if out else np.zeros((0, model.n_points, 3))
