"""ResNet18 with GroupNorm (trained from scratch) and spatial-softmax keypoint pooling.

The layout is He et al.'s ResNet18 (7x7 stem, max-pool, four stages of two basic blocks,
widths w, 2w, 4w, 8w with w = 64 for the standard network) without the average pool and
classifier. As in Diffusion Policy's vision encoder, every BatchNorm is a GroupNorm with
``channels // 16`` groups (batch statistics misbehave with EMA weights and small batches),
and the feature map is pooled by a spatial softmax (robomimic's): a 1x1 convolution to K
maps, a softmax over each map, and the expected (x, y) of each, in [-1, 1]. ``norm="batch"``
keeps BatchNorm instead, and ``relu`` follows the linear map, for policies trained elsewhere
(LeRobot's current defaults).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

NORMS = ("group", "batch")


def group_norm(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(max(1, channels // 16), channels)


def norm_layer(kind: str, channels: int) -> nn.Module:
    if kind not in NORMS:
        raise ValueError(f"image norm {kind!r}: use one of {', '.join(NORMS)}")
    return group_norm(channels) if kind == "group" else nn.BatchNorm2d(channels)


class BasicBlock(nn.Module):
    """Two 3x3 convolutions with a residual connection (1x1 projection when the shape changes)."""

    def __init__(self, cin: int, cout: int, stride: int, norm: str = "group") -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)
        self.norm1 = norm_layer(norm, cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1, bias=False)
        self.norm2 = norm_layer(norm, cout)
        self.project = None
        if stride != 1 or cin != cout:
            self.project = nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride, bias=False), norm_layer(norm, cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = F.relu(self.norm1(self.conv1(x)))
        h = self.norm2(self.conv2(h))
        return F.relu(h + (x if self.project is None else self.project(x)))


class ResNet18Trunk(nn.Module):
    """``(N, C, H, W)`` -> ``(N, 8 * width, H / 32, W / 32)`` (rounded up)."""

    def __init__(self, in_channels: int = 3, width: int = 64, norm: str = "group") -> None:
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, width, 7, stride=2, padding=3, bias=False), norm_layer(norm, width), nn.ReLU(),
            nn.MaxPool2d(3, stride=2, padding=1),
        )
        stages, cin = [], width
        for i, cout in enumerate((width, width * 2, width * 4, width * 8)):
            stride = 1 if i == 0 else 2
            stages.append(nn.Sequential(BasicBlock(cin, cout, stride, norm), BasicBlock(cout, cout, 1, norm)))
            cin = cout
        self.stages = nn.Sequential(*stages)
        self.out_channels = cin
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.stages(self.stem(x))


class SpatialSoftmax(nn.Module):
    """``(N, C, H, W)`` -> ``(N, 2 * keypoints)``: expected (x, y) of each softmax-normalised map."""

    def __init__(self, channels: int, keypoints: int, temperature: float = 1.0) -> None:
        super().__init__()
        self.to_maps = nn.Conv2d(channels, keypoints, 1)
        self.temperature = temperature

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        maps = self.to_maps(features)
        n, k, h, w = maps.shape
        attention = torch.softmax(maps.reshape(n, k, h * w) / self.temperature, dim=-1)
        ys, xs = torch.meshgrid(
            torch.linspace(-1.0, 1.0, h, device=maps.device, dtype=maps.dtype),
            torch.linspace(-1.0, 1.0, w, device=maps.device, dtype=maps.dtype),
            indexing="ij",
        )
        grid = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)  # (H*W, 2)
        return (attention @ grid).reshape(n, k * 2)


class ResNet18Keypoints(nn.Module):
    """ResNet18 trunk, spatial softmax and a linear map (then a ReLU if ``relu``): ``(N, C, H, W)`` -> ``(N, out_dim)``."""

    def __init__(self, in_channels: int, width: int, keypoints: int, out_dim: int, norm: str = "group",
                 relu: bool = False) -> None:
        super().__init__()
        self.trunk = ResNet18Trunk(in_channels, width, norm)
        self.pool = SpatialSoftmax(self.trunk.out_channels, keypoints)
        self.head = nn.Linear(2 * keypoints, out_dim)
        self.relu = relu

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.head(self.pool(self.trunk(x)))
        return F.relu(out) if self.relu else out
