"""C3DPO: canonical 3D pose networks for non-rigid structure from motion (Novotny, Ravi, Graham, Neverova &
Vedaldi, ICCV 2019), reimplemented after the authors' code (``c3dpo_nrsfm``, ``model.py``, ``cfgs/h36m.yaml``).

Model, for `(N, P, 2)` keypoints ``w`` and visibilities ``v`` (orthographic camera, no translation or scale):

* the factorisation network ``phi``: ``[w * v, v]`` `(3P)` -> a 1x1-convolution trunk (``3P -> width``, BN,
  ReLU, then ``n_layers`` bottleneck residual blocks ``width -> width/4 -> width/4 -> width``) -> K shape
  coefficients ``alpha`` and a log-rotation ``r`` `(3)`; the canonical shape is ``X = S(alpha)`` `(3, P)` (a
  learned linear basis with a bias), the camera-frame shape ``R X`` with ``R = exp([r]_x)``;
* the reprojection loss: the pseudo-Huber distance ``c (sqrt(1 + |d|^2 / c^2) - 1)`` (``c = huber``) between the
  first two rows of ``R X`` and ``w``, averaged over every visible keypoint of the minibatch;
* the canonicalisation loss (transversality): ``n_rand`` copies of every canonical shape, each rotated by a random
  rotation (angle up to ``pi``), go through a second network ``psi`` (the same trunk, 3D input) whose coefficients,
  through the same basis ``S``, must give back the unrotated shape (pseudo-Huber);
* in-plane augmentation: the rotation head sees ``w`` turned about the optical axis by up to ``z_angle`` (the
  prediction is turned back), and the coefficients come from a second copy turned again (``z_equivariance``:
  they must not depend on an in-plane rotation); the two copies go through ``phi`` separately, as in the authors'
  Human3.6M configuration (``independent_phi_for_aug``);
* at test time the image coordinates of visible points are the input's; only the depth comes from the network.

Training (the authors' Human3.6M settings): SGD, momentum 0.9, lr 1e-3, weight decay 5e-4, batch 1024, 90 epochs
of 1,249,280 samples with the lr divided by 10 after epochs 60 and 80: about 110k iterations
(:data:`PAPER_ITERATIONS`); :class:`C3DPOConfig` scales the milestones with ``iterations``. Weights start as in
their code: 1x1 convolutions normal(0, 0.01), biases 0, batch-norm scales uniform(0, 1).

The authors' loader as it ran (``repeat``): their dataset draws each sample's index with NumPy's global generator
inside the data-loader workers (``rand_sample``), and the PyTorch they pinned (1.1) forked its 8 workers
(``num_workers: 8``) with the same NumPy state (PyTorch seeds NumPy per worker only from 1.9). Worker ``w`` builds
batches ``w, w + 8, ...``, so every batch came 8 times in a row, each time with fresh augmentation and random
rotations (drawn by the model, not the workers). ``repeat = 8`` trains that way: each drawn minibatch is used for
8 consecutive iterations. The same state also replayed one epoch's draws in every epoch (the workers are forked
anew each epoch), which restricts the data to about 156,000 draws; that part is not reproduced (a smaller training
set alone left the error unchanged, ``benchmarks/RESULTS.md``).

Inputs: the model reads the keypoints it is given (centred on the visible ones inside the model). The benchmark
harness gives it the authors' Human3.6M inputs by default (``benchmarks.methods.c3dpo_inputs``, ``"hip"``): as
the C3DPO authors answered on their issue tracker, their ``kp_loc`` follows Kudo et al. ("Unsupervised Adversarial
Learning of 3D Human Pose from 2D Joint Locations", ``pose_dataset.py``): each frame centred on the hip and divided
by its mean hip-to-joint distance, and the 3D scaled alike, that scale turning errors back into millimetres. Two
other normalisations stay selectable for comparison: one global scale for every frame (``"centred"``) and PRN's
per-frame xy norm (``"prn"``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from nrsfm.device import indices_to, pick_device, restore_rng_state, rng_state
from nrsfm.errors import ValidationError
from nrsfm.procrustes import rotation_exp
from prn.train import atomic_save

log = logging.getLogger(__name__)

#: The authors' Human3.6M schedule in iterations: 90 epochs x 1,249,280 samples / 1024 per batch.
PAPER_ITERATIONS = 90 * 1_249_280 // 1024


@dataclass(frozen=True)
class C3DPOConfig:
    """C3DPO's model and training settings (the authors' Human3.6M values).

    Attributes:
        basis: K, the number of shape coefficients; width, n_layers: the trunks' width and residual blocks.
        huber: the pseudo-Huber scale ``c``; n_rand: rotated copies per shape in the canonicalisation loss.
        z_angle: the largest in-plane rotation of the augmentation (radians).
        keypoint_rescale: the centred keypoints are multiplied by it before the networks and the shapes divided
            by it after (the authors' ``keypoint_rescale``); with a fixed ``huber`` it sets the scale at which
            the reprojection loss turns from quadratic to linear.
        iterations, batch, lr, momentum, weight_decay: the optimiser's settings; the lr is divided by 10 at 2/3
            and 8/9 of ``iterations`` (epochs 60 and 80 of 90).
        optimizer: ``"sgd"`` (the authors' Human3.6M choice, with ``momentum``) or ``"adam"`` (their code's
            other breed: betas 0.9 and 0.999, the same lr and weight decay).
        repeat: each drawn minibatch is used for this many consecutive iterations (module docstring: 8 is how
            the authors' loader ran; 1 draws a new minibatch every iteration).
        precision: ``"fp32"``, or ``"bf16"``: the two trunks (almost all of the arithmetic) run under bfloat16
            autocast, the heads, the basis, the rotations and the losses in float32 (on CPUs with AVX-512 BF16
            or AMX, and on GPUs, several times faster; the weights and the optimiser stay float32).
        seed, device, checkpoint_every: as :class:`prn.train.TrainConfig`.
    """

    basis: int = 10
    width: int = 1024
    n_layers: int = 6
    huber: float = 0.01
    n_rand: int = 4
    z_angle: float = math.pi / 8
    keypoint_rescale: float = 1.0
    iterations: int = PAPER_ITERATIONS
    batch: int = 1024
    lr: float = 1e-3
    momentum: float = 0.9
    weight_decay: float = 5e-4
    optimizer: str = "sgd"
    repeat: int = 1
    precision: str = "fp32"
    seed: int = 0
    device: str = "auto"
    checkpoint_every: int = 2000

    def __post_init__(self) -> None:
        if self.basis < 1 or self.width < 4 or self.n_layers < 0 or self.iterations < 1 or self.batch < 2 \
                or self.repeat < 1:
            raise ValidationError(f"C3DPOConfig: expected basis >= 1, width >= 4, n_layers >= 0, iterations >= 1, "
                                  f"batch >= 2, repeat >= 1, got {self.basis}, {self.width}, {self.n_layers}, "
                                  f"{self.iterations}, {self.batch}, {self.repeat}")
        if not self.keypoint_rescale > 0:
            raise ValidationError(f"C3DPOConfig: expected keypoint_rescale > 0, got {self.keypoint_rescale}")
        if self.optimizer not in ("sgd", "adam"):
            raise ValidationError(f"C3DPOConfig: expected optimizer 'sgd' or 'adam', got {self.optimizer!r}")
        if self.precision not in ("fp32", "bf16"):
            raise ValidationError(f"C3DPOConfig: expected precision 'fp32' or 'bf16', got {self.precision!r}")

    def key(self) -> dict:
        """The settings as a dict (a checkpoint's or a cache's key); ``repeat`` only where it is not 1, so that
        models saved before the setting existed keep their key."""
        out = dataclasses.asdict(self)
        if self.repeat == 1:
            del out["repeat"]
        return out

    def lr_at(self, iteration: int) -> float:
        drops = sum(iteration >= round(self.iterations * f) for f in (60 / 90, 80 / 90))
        return self.lr * 0.1**drops


def _linear(n_in: int, n_out: int, std: float = 0.01) -> nn.Linear:
    layer = nn.Linear(n_in, n_out)
    nn.init.normal_(layer.weight, 0.0, std)
    nn.init.zeros_(layer.bias)
    return layer


def _bn(n: int) -> nn.BatchNorm1d:
    bn = nn.BatchNorm1d(n)
    nn.init.uniform_(bn.weight, 0.0, 1.0)
    return bn


class _Bottleneck(nn.Module):
    """``width -> width/4 -> width/4 -> width`` (1x1 convolutions with BN, ReLU), plus the input, then ReLU."""

    def __init__(self, width: int) -> None:
        super().__init__()
        inner = width // 4
        self.body = nn.Sequential(_linear(width, inner), _bn(inner), nn.ReLU(),
                                  _linear(inner, inner), _bn(inner), nn.ReLU(),
                                  _linear(inner, width), _bn(width))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.body(x) + x)


def _trunk(n_in: int, width: int, n_layers: int) -> nn.Sequential:
    return nn.Sequential(_linear(n_in, width), _bn(width), nn.ReLU(), *[_Bottleneck(width) for _ in range(n_layers)])


def pseudo_huber(sq: torch.Tensor, scale: float) -> torch.Tensor:
    """``c (sqrt(1 + d^2 / c^2 + 1e-4) - 1)`` of squared distances ``sq`` (the authors' ``huber``)."""
    return (torch.clamp(1 + sq / scale**2, min=0.0) + 1e-4).sqrt().sub(1.0).mul(scale)


def random_rotations(n: int, max_angle: float, axes: tuple[float, float, float], *, like: torch.Tensor
                     ) -> torch.Tensor:
    """`(n, 3, 3)` rotations about random axes (masked by ``axes``) by angles uniform in ``[0, max_angle]``."""
    mask = torch.zeros(3, dtype=like.dtype, device=like.device)  # filled on the device: a CUDA graph can hold it
    for i, a in enumerate(axes):
        if a:
            mask.narrow(0, i, 1).fill_(float(a))
    axis = torch.randn(n, 3, dtype=like.dtype, device=like.device) * mask
    axis = axis / axis.norm(dim=1, keepdim=True).clamp_min(1e-12)
    angle = torch.rand(n, dtype=like.dtype, device=like.device) * max_angle
    return rotation_exp(axis * angle[:, None])


class C3DPO(nn.Module):
    """The two networks and the shared shape basis (module docstring)."""

    def __init__(self, n_points: int, config: C3DPOConfig = C3DPOConfig()) -> None:
        super().__init__()
        self.n_points, self.config = n_points, config
        self.phi = _trunk(3 * n_points, config.width, config.n_layers)
        self.alpha = _linear(config.width, config.basis)
        self.basis = _linear(config.basis, 3 * n_points)
        self.rot = _linear(config.width, 3)
        self.psi = _trunk(3 * n_points, config.width, config.n_layers)
        self.alpha_psi = _linear(config.width, config.basis)

    def canonical(self, coefficients: torch.Tensor) -> torch.Tensor:
        """`(N, K)` coefficients -> `(N, 3, P)` canonical shapes."""
        return self.basis(coefficients).view(-1, 3, self.n_points)

    def _trunk(self, trunk: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
        with torch.autocast(x.device.type, dtype=torch.bfloat16, enabled=self.config.precision == "bf16",
                            cache_enabled=False):  # no cast cache: CUDA graphs capture this region
            return trunk(x).float()

    def _phi(self, w: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return self._trunk(self.phi, torch.cat([(w * v[:, None]).reshape(len(w), -1), v], dim=1))

    def forward(self, w: torch.Tensor, v: torch.Tensor) -> dict[str, torch.Tensor]:
        """Shapes for `(N, 2, P)` centred keypoints ``w`` and `(N, P)` visibilities ``v``.

        Returns ``camera`` `(N, 3, P)` (camera-frame shapes), ``canonical`` `(N, 3, P)` and ``rotation``
        `(N, 3, 3)`; in training mode with the augmentation of the module docstring.
        """
        n = len(w)
        if self.training:
            r_aug = random_rotations(n, self.config.z_angle, (0.0, 0.0, 1.0), like=w)
            r_eq = random_rotations(n, self.config.z_angle, (0.0, 0.0, 1.0), like=w)
            w_aug = r_aug[:, :2, :2] @ w
            feats = self._phi(w_aug, v)  # the rotation head's input
            coefficients = self.alpha(self._phi(r_eq[:, :2, :2] @ w_aug, v))  # invariant to in-plane turns
        else:
            feats = self._phi(w, v)
            coefficients = self.alpha(feats)
        canonical = self.canonical(coefficients)
        rotation = rotation_exp(self.rot(feats))
        camera = rotation @ canonical
        if self.training:  # undo the augmentation: back into the frame of w
            rotation = r_aug.transpose(1, 2) @ rotation
            camera = r_aug.transpose(1, 2) @ camera
        return {"camera": camera, "canonical": canonical, "rotation": rotation}

    def canonicalisation_loss(self, canonical: torch.Tensor) -> torch.Tensor:
        """The pseudo-Huber distance between `(N, 3, P)` canonical shapes and ``psi``'s reconstruction of them
        from ``n_rand`` randomly rotated copies (0 for a shape ``psi`` maps back exactly)."""
        unrotated = canonical.repeat(self.config.n_rand, 1, 1)
        rotated = random_rotations(len(unrotated), math.pi, (1.0, 1.0, 1.0), like=canonical) @ unrotated
        back = self.canonicalise(rotated)
        return pseudo_huber(((back - unrotated) ** 2).sum(dim=1), self.config.huber).mean()

    def canonicalise(self, shapes: torch.Tensor) -> torch.Tensor:
        """``psi``: `(N, 3, P)` shapes in any orientation -> `(N, 3, P)` canonical shapes."""
        return self.canonical(self.alpha_psi(self._trunk(self.psi, shapes.reshape(len(shapes), -1))))

    def reprojection_loss(self, camera: torch.Tensor, w: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Pseudo-Huber reprojection error averaged over the visible keypoints of the minibatch."""
        dist = pseudo_huber(((camera[:, :2] - w) ** 2).sum(dim=1), self.config.huber)  # (N, P)
        return (dist * v).sum() / v.sum().clamp_min(1.0)


def _centre(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """`(N, P, 2)` keypoints centred on the visible ones, as `(N, 2, P)`."""
    mass = np.maximum(v.sum(axis=1, keepdims=True), 1e-4)
    mean = (w * v[..., None]).sum(axis=1, keepdims=True) / mass[..., None]
    return (w - mean).transpose(0, 2, 1)


def make_optimizer(model: C3DPO, config: C3DPOConfig) -> torch.optim.Optimizer:
    """``config``'s optimiser over ``model``'s parameters (SGD with momentum, or Adam)."""
    if config.optimizer == "adam":
        return torch.optim.Adam(model.parameters(), lr=config.lr, betas=(0.9, 0.999), weight_decay=config.weight_decay)
    return torch.optim.SGD(model.parameters(), lr=config.lr, momentum=config.momentum, weight_decay=config.weight_decay)


def training_losses(model: C3DPO, w: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The reprojection and canonicalisation losses of one training minibatch: `(N, 2, P)` centred keypoints ``w``,
    `(N, P)` visibilities ``v``."""
    pred = model(w, v)
    return model.reprojection_loss(pred["camera"], w, v), model.canonicalisation_loss(pred["canonical"])


class TrainStep:
    """C3DPO's training iteration on rows of `(N, 2, P)` centred keypoints ``w_all`` and `(N, P)` visibilities
    ``v_all``: ``step(idx, lr)`` takes `(B,)` row indices (numpy) and the learning rate, runs the forward pass, the
    backward pass and the optimiser's step, and returns the reprojection and canonicalisation losses (device
    tensors, not synchronised).

    With ``cuda_graph`` the iteration is captured as a CUDA graph, once per learning rate, and replayed: one launch
    in place of the many small kernel launches that dominate an op-by-op iteration on a GPU. The replay does the
    same arithmetic on the same rows; its random rotations come from another part of the CUDA generator's stream.
    Each capture first runs :func:`warm_up` (three iterations, then the model, its batch-norm statistics, the
    momentum and the random generator put back as they were), as CUDA graphs need. SGD only (Adam keeps its step
    count on the host).

    With ``compile`` the forward and backward passes are compiled by ``torch.compile`` (Inductor fuses the
    batch norms, ReLUs, casts and losses into fewer kernels; the first iterations pay the compilation). Its random
    numbers are drawn by the same operators as op by op (``fallback_random``), so that a CUDA graph replays them
    afresh and a seed gives the same rotations either way.
    """

    def __init__(self, model: C3DPO, opt: torch.optim.Optimizer, w_all: torch.Tensor, v_all: torch.Tensor,
                 batch: int, cuda_graph: bool = False, compile: bool = False) -> None:
        if cuda_graph and (w_all.device.type != "cuda" or not isinstance(opt, torch.optim.SGD)):
            raise ValidationError(f"C3DPO: a CUDA graph needs a CUDA device and SGD, got {w_all.device.type} and "
                                  f"{type(opt).__name__}; train without cuda_graph")
        self.model, self.opt, self.w_all, self.v_all, self.cuda_graph = model, opt, w_all, v_all, cuda_graph
        self.idx = torch.zeros(batch, dtype=torch.long, device=w_all.device)  # the graph's input
        self.graph, self.graph_lr, self.out = None, None, None
        self.losses = (torch.compile(training_losses, options={"fallback_random": True}) if compile
                       else training_losses)

    def eager(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One iteration on `(B,)` device indices, launched op by op (compiled kernels with ``compile``)."""
        loss_rep, loss_can = self.losses(self.model, self.w_all[idx], self.v_all[idx])
        self.opt.zero_grad(set_to_none=True)
        (loss_rep + loss_can).backward()
        self.opt.step()
        return loss_rep, loss_can

    def __call__(self, idx: np.ndarray, lr: float) -> tuple[torch.Tensor, torch.Tensor]:
        for g in self.opt.param_groups:
            g["lr"] = lr
        rows = indices_to(idx, self.w_all.device)
        if not self.cuda_graph:
            return self.eager(rows)
        self.idx.copy_(rows)
        if self.graph is None or lr != self.graph_lr:
            self._capture(lr)
        self.graph.replay()
        return self.out

    def _capture(self, lr: float) -> None:
        self.graph = self.out = None  # the previous graph's memory goes back first
        stream = torch.cuda.Stream(self.idx.device)
        stream.wait_stream(torch.cuda.current_stream(self.idx.device))
        with torch.cuda.stream(stream):
            warm_up(self, 3)
        torch.cuda.current_stream(self.idx.device).wait_stream(stream)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            self.out = self.eager(self.idx)
        self.graph, self.graph_lr = graph, lr


def warm_up(step: TrainStep, n: int) -> None:
    """Run ``n`` iterations of ``step`` on its ``idx`` rows, then put the model's parameters and batch-norm
    statistics, the optimiser's momentum and the device's random generator back as they were (in place, so that
    their memory stays where a CUDA graph reads it); momentum that did not exist before is zero, which gives SGD's
    first step exactly. The random numbers that follow are thus those an iteration without the warm-up draws, and a
    training resumed from a checkpoint (which captures anew) draws the rotations of an uninterrupted one."""
    model, opt = step.model, step.opt
    saved = {k: t.detach().clone() for k, t in model.state_dict().items()}
    params = [p for group in opt.param_groups for p in group["params"]]
    momentum = [opt.state[p].get("momentum_buffer") if p in opt.state else None for p in params]
    momentum = [None if b is None else b.clone() for b in momentum]
    device = step.idx.device
    with torch.random.fork_rng(devices=[device.index] if device.type == "cuda" else [], device_type="cuda"):
        for _ in range(n):
            step.eager(step.idx)
    with torch.no_grad():
        for k, t in model.state_dict().items():
            t.copy_(saved[k])
        for p, b in zip(params, momentum):
            buf = opt.state[p].get("momentum_buffer") if p in opt.state else None
            if buf is not None:
                buf.copy_(b) if b is not None else buf.zero_()


def train_c3dpo(inputs: np.ndarray, weights: np.ndarray, config: C3DPOConfig, out_dir: str | os.PathLike | None,
                *, resume: bool = True, progress: bool = True,
                monitor: Callable[[C3DPO], dict] | None = None,
                cuda_graph: bool | None = None, compile: bool = False) -> tuple[C3DPO, dict]:
    """Train C3DPO on `(N, P, 2)` normalised keypoints and `(N, P)` visibilities; checkpoints every
    ``checkpoint_every`` iterations to ``out_dir/checkpoint.pt`` (resumed when ``resume``), the final model to
    ``out_dir/model.pt``. Returns the model (eval mode) and a record of the run.

    ``monitor``, when given, is called with the model (in eval mode) at every checkpoint; its dict goes into the
    record's ``monitor`` list with the iteration (for example a held-out error along training). ``cuda_graph``:
    replay each iteration as a CUDA graph (:class:`TrainStep`); by default on a CUDA device with SGD. ``compile``:
    compile the forward and backward passes (:class:`TrainStep`)."""
    from tqdm.auto import tqdm

    device = pick_device(config.device)
    if cuda_graph is None:
        cuda_graph = device.type == "cuda" and config.optimizer == "sgd"
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    model = C3DPO(inputs.shape[1], config).to(device)
    opt = make_optimizer(model, config)
    out = Path(out_dir) if out_dir is not None else None
    ckpt = out / "checkpoint.pt" if out is not None else None
    start, history, monitored, rows = 0, [], [], None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    if ckpt is not None and resume and ckpt.exists():
        state = torch.load(ckpt, map_location=device, weights_only=False)
        if state["config"] != config.key():
            raise ValidationError(f"{ckpt}: the checkpoint was made with another configuration")
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        start, history, monitored = state["iteration"], state["history"], state.get("monitor", [])
        rows = state.get("rows")
        rng.bit_generator.state = state["numpy_rng"]
        restore_rng_state(state, device)  # on a GPU the rotations are drawn by its generator
    w_all = torch.as_tensor(_centre(inputs, weights) * config.keypoint_rescale, dtype=torch.float32, device=device)
    v_all = torch.as_tensor(weights > 0, dtype=torch.float32, device=device)
    model.train()
    step = TrainStep(model, opt, w_all, v_all, config.batch, cuda_graph, compile)
    t0 = time.perf_counter()
    bar = tqdm(total=config.iterations, initial=start, desc="C3DPO", disable=not progress, mininterval=2.0)
    for it in range(start, config.iterations):
        if rows is None or it % config.repeat == 0:
            rows = rng.integers(0, len(inputs), config.batch)
        loss_rep, loss_can = step(rows, config.lr_at(it))
        loss = loss_rep + loss_can
        logged = (it + 1) % 100 == 0 or it == start
        at_checkpoint = (it + 1) % config.checkpoint_every == 0 or it + 1 == config.iterations
        if (logged or at_checkpoint) and not torch.isfinite(loss):  # the loop's only host synchronisations
            raise ValidationError(f"C3DPO: the loss became {loss.item()} by iteration {it + 1}; lower the learning "
                                  f"rate")
        if logged:
            history.append({"iteration": it + 1, "reprojection": loss_rep.item(), "canonicalisation": loss_can.item(),
                            "lr": config.lr_at(it)})
            bar.set_postfix(rep=f"{loss_rep.item():.3g}", can=f"{loss_can.item():.3g}")
        bar.update(1)
        if monitor is not None and at_checkpoint:
            monitored.append({"iteration": it + 1, **monitor(model.eval())})
            model.train()
        if ckpt is not None and at_checkpoint:
            atomic_save({"model": model.state_dict(), "optimizer": opt.state_dict(), "iteration": it + 1,
                         "history": history, "monitor": monitored, "config": config.key(), "rows": rows,
                         "numpy_rng": rng.bit_generator.state, **rng_state(device)}, ckpt)
    bar.close()
    record = {"seconds": time.perf_counter() - t0, "iterations_run": config.iterations - start,
              "cuda_graph": cuda_graph, "compile": compile, "history": history, "monitor": monitored}
    if out is not None:
        atomic_save({"model": model.state_dict(), "config": config.key(), "n_points": inputs.shape[1]},
                    out / "model.pt")
        (out / "train.json").write_text(json.dumps({"config": config.key(), **record}, indent=2))
    return model.eval(), record


def load_c3dpo(path: str | os.PathLike, device: str = "auto") -> C3DPO:
    """The model written by :func:`train_c3dpo` (``model.pt``)."""
    state = torch.load(Path(path), map_location=pick_device(device), weights_only=False)
    model = C3DPO(state["n_points"], C3DPOConfig(**state["config"]))
    model.load_state_dict(state["model"])
    return model.to(pick_device(device)).eval()


@torch.no_grad()
def predict_c3dpo(model: C3DPO, inputs: np.ndarray, weights: np.ndarray, batch: int = 4096,
                  replace_keypoints_with_input: bool = True) -> np.ndarray:
    """`(N, P, 3)` shapes for `(N, P, 2)` normalised keypoints: the input's image coordinates where a point is
    visible (the network's reprojection elsewhere) and the network's depth; with ``replace_keypoints_with_input``
    False (the authors' option of that name) the network's camera-frame shapes ``R X`` as they are, whose image
    coordinates show how well the shapes fit the input."""
    model.eval()
    device = next(model.parameters()).device
    out = []
    for s in range(0, len(inputs), batch):
        x, v = inputs[s:s + batch], weights[s:s + batch]
        w = torch.as_tensor(_centre(x, v), dtype=torch.float32, device=device)
        vis = torch.as_tensor(v > 0, dtype=torch.float32, device=device)
        rescale = model.config.keypoint_rescale
        cam = model(w * rescale, vis)["camera"] / rescale  # (n, 3, P)
        keep = vis[:, None] if replace_keypoints_with_input else torch.zeros_like(vis[:, None])
        xy = keep * w + (1 - keep) * cam[:, :2]
        out.append(torch.cat([xy, cam[:, 2:]], dim=1).transpose(1, 2).double().cpu().numpy())
    return np.concatenate(out) if out else np.zeros((0, model.n_points, 3))
