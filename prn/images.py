"""Image inputs of PRN-CNN: lazily indexed image stacks, the ImageNet input transform and the torchvision
backbones.

An image source is anything with ``len()``, ``shape`` `(N, H, W, 3)` and ``source[idx]`` returning
`(n, H, W, 3)` uint8 for an integer index array: a numpy array (rendered stand-ins), or a file-backed source
that decodes and crops on demand (:class:`nrsfm.datasets.h36m.FrameImages`) so that a dataset larger than
memory can be trained on.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from torch import nn

from nrsfm.errors import ValidationError

log = logging.getLogger(__name__)

#: PRN-CNN's backbones: torchvision's ResNet-50 (the paper's) and ResNet-18, and ``"small"``, four strided
#: convolutions for CPU smoke runs on small images.
BACKBONES = ("resnet50", "resnet18", "small")
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)


class ImageStack:
    """Several image sources as one, indexed by flat frame index (the order of :func:`prn.data.build_training_set`)."""

    def __init__(self, sources: list) -> None:
        if not sources:
            raise ValidationError("ImageStack: expected at least one image source")
        shapes = {tuple(s.shape[1:]) for s in sources}
        if len(shapes) != 1 or next(iter(shapes))[-1] != 3:
            raise ValidationError(f"ImageStack: expected sources of (N, H, W, 3) images of one size, got {shapes}")
        self.sources = sources
        self.offsets = np.cumsum([0] + [len(s) for s in sources])
        self.shape = (int(self.offsets[-1]),) + next(iter(shapes))

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, idx) -> np.ndarray:
        idx = np.atleast_1d(np.asarray(idx, int))
        which = np.searchsorted(self.offsets, idx, side="right") - 1
        out = np.empty((len(idx),) + self.shape[1:], np.uint8)
        for k in np.unique(which):
            sel = which == k
            out[sel] = np.asarray(self.sources[k][idx[sel] - self.offsets[k]])
        return out


def stack_images(sources: list):
    """One source for per-sequence sources: a concatenated array when all are arrays, else an :class:`ImageStack`."""
    if all(isinstance(s, np.ndarray) for s in sources):
        return np.concatenate(sources)
    return ImageStack(sources)


def to_tensor(images: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    """`(n, H, W, 3)` uint8 -> `(n, 3, H, W)` float, normalised with ImageNet's mean and deviation."""
    x = torch.as_tensor(np.ascontiguousarray(images), device=device).permute(0, 3, 1, 2).float().div_(255)
    mean = torch.tensor(MEAN, device=x.device).view(1, 3, 1, 1)
    std = torch.tensor(STD, device=x.device).view(1, 3, 1, 1)
    return (x - mean) / std


def _weights(name: str):
    try:
        import torchvision
        ctor = getattr(torchvision.models, name)
        enum = getattr(torchvision.models, {"resnet50": "ResNet50_Weights", "resnet18": "ResNet18_Weights"}[name])
    except Exception as exc:  # ImportError, or an operator mismatch with the installed torch
        raise ValidationError(f"PRN-CNN needs torchvision matching your torch ({exc}); install it with "
                              "'pip install \".[vision]\"'") from None
    return ctor, enum.IMAGENET1K_V1


def initialisation(name: str, pretrained: bool = True) -> str:
    """How :func:`backbone` will initialise ``name``: ImageNet weights when ``pretrained`` and the weights file is
    already in torch's cache (``torch.hub.get_dir()/checkpoints``; nothing is downloaded), else random."""
    if name not in BACKBONES:
        raise ValidationError(f"backbone: expected one of {BACKBONES}, got {name!r}")
    if name == "small":
        return "small: four 3x3 convolutions of stride 2 (16-32-64-64 channels), random initialisation"
    _, weights = _weights(name)
    path = Path(torch.hub.get_dir()) / "checkpoints" / Path(weights.url).name
    if not pretrained:
        return f"{name}, random initialisation"
    if path.exists():
        return f"{name}, ImageNet weights ({path.name})"
    return f"{name}, random initialisation (ImageNet weights not found at {path})"


def backbone(name: str = "resnet50", pretrained: bool = True) -> tuple[nn.Module, str]:
    """A torchvision ResNet up to its last convolutional stage (or :func:`small_convnet`), and
    :func:`initialisation`'s line saying how it was initialised."""
    how = initialisation(name, pretrained)
    if name == "small":
        return small_convnet(), how
    ctor, weights = _weights(name)
    net = ctor(weights=weights if "ImageNet weights (" in how else None)
    return nn.Sequential(*list(net.children())[:-2]), how


def small_convnet() -> nn.Module:
    """Four 3x3 convolutions of stride 2 with batch norm and ReLU, 16-32-64-64 channels (`(N, 64, H/16, W/16)`)."""
    layers, c_in = [], 3
    for c in (16, 32, 64, 64):
        layers += [nn.Conv2d(c_in, c, 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(c), nn.ReLU(inplace=True)]
        c_in = c
    return nn.Sequential(*layers)


def feature_dim(module: nn.Module, image_size: int) -> int:
    """The flattened output size of ``module`` on one `(1, 3, image_size, image_size)` image."""
    was = module.training
    module.eval()
    with torch.no_grad():
        n = module(torch.zeros(1, 3, image_size, image_size)).flatten(1).shape[1]
    module.train(was)
    return int(n)
