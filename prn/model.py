"""PRN networks: PRN-FCN (2D points -> 3D) and PRN-CNN (images -> 3D).

PRN-FCN follows the official ``net_prn_fcn.prototxt``: 2P inputs -> FC
(width, no bias) -> BN -> ReLU; one shared residual block (FC-BN-ReLU-FC-BN,
+ skip, ReLU); then a separate residual block per head, the xy head -> FC 2P,
the z head -> FC P. Final layers are initialised with std 1e-3, the others
Xavier. The xy head is predicted (and compared with the input by the data
term); it is not replaced by the input at test time.
"""

from __future__ import annotations

import torch
from torch import nn

from nrsfm.errors import ValidationError


class ResBlock(nn.Module):
    """FC-BN-ReLU-FC-BN, plus the input, then ReLU; `(N, width) -> (N, width)`."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(width, width, bias=False)
        self.bn1 = nn.BatchNorm1d(width)
        self.fc2 = nn.Linear(width, width, bias=False)
        self.bn2 = nn.BatchNorm1d(width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = torch.relu(self.bn1(self.fc1(x)))
        return torch.relu(x + self.bn2(self.fc2(h)))


class Head(nn.Module):
    """The part after the input layer: shared block, then the xy and z heads -> `(N, P, 3)`."""

    def __init__(self, width: int, n_points: int) -> None:
        super().__init__()
        self.n_points = n_points
        self.shared = ResBlock(width)
        self.xy_block = ResBlock(width)
        self.xy_out = nn.Linear(width, 2 * n_points)
        self.z_block = ResBlock(width)
        self.z_out = nn.Linear(width, n_points)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        for m in (self.xy_out, self.z_out):
            nn.init.normal_(m.weight, std=1e-3)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        h = self.shared(h)
        xy = self.xy_out(self.xy_block(h)).reshape(-1, self.n_points, 2)
        z = self.z_out(self.z_block(h)).reshape(-1, self.n_points, 1)
        return torch.cat([xy, z], dim=-1)


class PRNFCN(nn.Module):
    """PRN-FCN.

    Args:
        n_points: output points `P` (17 for Human3.6M).
        n_inputs: input points (default `P`; 16 for Stacked Hourglass input).
        width: hidden width (1024; 4096 for dense data in the paper).

    Forward: `(N, P_in, 2)` normalised 2D (and optional `(N, P_in)`
    visibility, multiplied in so missing points read as 0) -> `(N, P, 3)`.
    """

    def __init__(self, n_points: int, n_inputs: int | None = None, width: int = 1024) -> None:
        super().__init__()
        if n_points < 1 or width < 1:
            raise ValidationError(f"PRNFCN: expected positive n_points and width, got {n_points}, {width}")
        self.n_points, self.n_inputs, self.width = n_points, n_inputs or n_points, width
        self.inp = nn.Linear(2 * self.n_inputs, width, bias=False)
        self.bn = nn.BatchNorm1d(width)
        nn.init.xavier_uniform_(self.inp.weight)
        self.head = Head(width, n_points)

    def forward(self, points_2d: torch.Tensor, visibility: torch.Tensor | None = None) -> torch.Tensor:
        if points_2d.ndim != 3 or points_2d.shape[1:] != (self.n_inputs, 2):
            raise ValidationError(f"PRNFCN input: expected (N, {self.n_inputs}, 2), got {tuple(points_2d.shape)}")
        if visibility is not None:
            points_2d = points_2d * (visibility > 0).unsqueeze(-1).to(points_2d.dtype)
        h = torch.relu(self.bn(self.inp(points_2d.flatten(1))))
        return self.head(h)


class PRNCNN(nn.Module):
    """PRN-CNN: an image backbone feeding the FCN's head (the paper: ResNet-50 features, 2048 x 7 x 7 at 224 px).

    Args:
        n_points: output points.
        backbone: a module mapping `(N, 3, H, W)` images to `(N, C, h, w)`
            features, or the name of a torchvision ResNet (:data:`prn.images.BACKBONES`).
        feature_dim: ``C * h * w`` of the backbone's output (default: measured on one ``image_size`` image).
        pretrained: ImageNet weights for a named backbone when they are available locally.
    """

    def __init__(self, n_points: int, *, backbone: nn.Module | str = "resnet50", feature_dim: int | None = None,
                 image_size: int = 224, width: int = 1024, pretrained: bool = False) -> None:
        super().__init__()
        from prn import images

        self.initialisation = "given module"
        if isinstance(backbone, str):
            backbone, self.initialisation = images.backbone(backbone, pretrained)
        self.backbone = backbone
        self.n_points = n_points
        feature_dim = feature_dim or images.feature_dim(backbone, image_size)
        self.inp = nn.Linear(feature_dim, width, bias=False)
        self.bn = nn.BatchNorm1d(width)
        nn.init.xavier_uniform_(self.inp.weight)
        self.head = Head(width, n_points)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValidationError(f"PRNCNN input: expected (N, 3, H, W) images, got {tuple(images.shape)}")
        f = self.backbone(images).flatten(1)
        return self.head(torch.relu(self.bn(self.inp(f))))
