"""Diffusion Policy's 1-D temporal U-Net with FiLM conditioning (a plain ``nn.Module``).

Architecture as in Chi et al. 2023 (``ConditionalUnet1D``): each level holds two conditional
residual blocks (Conv1d -> GroupNorm -> Mish, twice; FiLM scale and bias from the
conditioning vector between them), then a stride-2 downsampling; two blocks in the middle;
the way up concatenates the skip of the same resolution. The conditioning vector is the
diffusion step's sinusoidal embedding (through a small MLP) concatenated with the global
observation features. Diffusion Policy's quirk is kept so parameter counts match the
paper: the finest level's skip is never used and every up level upsamples.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import cast

import torch
from torch import nn


@dataclass(frozen=True)
class UNetConfig:
    """Widths and kernel of the 1-D U-Net."""

    down_dims: tuple[int, ...] = (256, 512, 1024)  # channels per level, finest first (DP state: 256,512,1024)
    kernel_size: int = 5  # temporal convolution kernel (odd)
    n_groups: int = 8  # GroupNorm groups in every block; each width must be a multiple
    step_embed_dim: int = 256  # width of the diffusion-step embedding (DP: 256 state, 128 image)
    cond_predict_scale: bool = True  # FiLM predicts scale and bias (True, DP's setting) or bias only
    final_groups: int = 0  # GroupNorm groups of the output block; 0: n_groups (Diffusion Policy and LeRobot: always 8)

    def __post_init__(self) -> None:
        if not self.down_dims or any(d < 1 for d in self.down_dims):
            raise ValueError(f"down_dims {self.down_dims}: need at least one positive width")
        if any(d % self.n_groups for d in self.down_dims):
            raise ValueError(f"down_dims {self.down_dims}: every width must be a multiple of n_groups {self.n_groups}")
        if self.final_groups < 0 or (self.final_groups and self.down_dims[0] % self.final_groups):
            raise ValueError(f"final_groups {self.final_groups}: must be 0 or divide the first width {self.down_dims[0]}")
        if self.kernel_size < 1 or self.kernel_size % 2 == 0:
            raise ValueError(f"kernel_size {self.kernel_size}: must be odd and positive")
        if self.step_embed_dim < 4 or self.step_embed_dim % 2:
            raise ValueError(f"step_embed_dim {self.step_embed_dim}: must be even and at least 4")

    def check_horizon(self, horizon: int) -> None:
        """Every level but the last halves the sequence, so the horizon must divide evenly."""
        factor = 2 ** (len(self.down_dims) - 1)
        if horizon % factor:
            raise ValueError(f"horizon {horizon} must be a multiple of {factor} for {len(self.down_dims)} U-Net levels")


def sinusoidal_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """``(B,)`` diffusion steps -> ``(B, dim)``: sines then cosines of geometric frequencies."""
    half = dim // 2
    freqs = torch.exp(torch.arange(half, device=t.device, dtype=torch.float32) * (-math.log(10000.0) / (half - 1)))
    angles = t.float()[:, None] * freqs[None, :]
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


class ConvBlock(nn.Sequential):
    """Conv1d -> GroupNorm -> Mish, length preserving."""

    def __init__(self, cin: int, cout: int, kernel: int, groups: int) -> None:
        super().__init__(nn.Conv1d(cin, cout, kernel, padding=kernel // 2), nn.GroupNorm(groups, cout), nn.Mish())


class FiLMResBlock(nn.Module):
    """Two conv blocks; the conditioning vector scales and shifts the first one's output."""

    def __init__(self, cin: int, cout: int, cond_dim: int, kernel: int, groups: int, predict_scale: bool) -> None:
        super().__init__()
        self.conv1 = ConvBlock(cin, cout, kernel, groups)
        self.conv2 = ConvBlock(cout, cout, kernel, groups)
        self.cout, self.predict_scale = cout, predict_scale
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, cout * 2 if predict_scale else cout))
        self.skip = nn.Conv1d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """``x (B, cin, T)``, ``cond (B, cond_dim)`` -> ``(B, cout, T)``."""
        h = self.conv1(x)
        film = self.film(cond)[:, :, None]
        if self.predict_scale:
            h = film[:, : self.cout] * h + film[:, self.cout :]
        else:
            h = h + film
        return self.conv2(h) + self.skip(x)


class ConditionalUnet1D(nn.Module):
    """Predicts the noise in an action sequence given the diffusion step and global features."""

    def __init__(self, config: UNetConfig, input_dim: int, global_cond_dim: int) -> None:
        super().__init__()
        c = config
        self.step_embed_dim = c.step_embed_dim
        self.step_mlp = nn.Sequential(
            nn.Linear(c.step_embed_dim, c.step_embed_dim * 4), nn.Mish(), nn.Linear(c.step_embed_dim * 4, c.step_embed_dim)
        )
        cond_dim = c.step_embed_dim + global_cond_dim

        def block(cin: int, cout: int) -> FiLMResBlock:
            return FiLMResBlock(cin, cout, cond_dim, c.kernel_size, c.n_groups, c.cond_predict_scale)

        dims = (input_dim,) + tuple(c.down_dims)
        pairs = list(zip(dims[:-1], dims[1:]))
        self.down = nn.ModuleList()
        for i, (cin, cout) in enumerate(pairs):
            last = i == len(pairs) - 1
            resample = nn.Identity() if last else nn.Conv1d(cout, cout, 3, stride=2, padding=1)
            self.down.append(nn.ModuleList([block(cin, cout), block(cout, cout), resample]))
        mid = dims[-1]
        self.mid = nn.ModuleList([block(mid, mid), block(mid, mid)])
        self.up = nn.ModuleList()
        for cin, cout in reversed(pairs[1:]):
            upsample = nn.ConvTranspose1d(cin, cin, 4, stride=2, padding=1)
            self.up.append(nn.ModuleList([block(cout * 2, cin), block(cin, cin), upsample]))
        self.final = nn.Sequential(
            ConvBlock(c.down_dims[0], c.down_dims[0], c.kernel_size, c.final_groups or c.n_groups),
            nn.Conv1d(c.down_dims[0], input_dim, 1),
        )

    def forward(self, sample: torch.Tensor, timestep: torch.Tensor, global_cond: torch.Tensor) -> torch.Tensor:
        """``sample (B, T, A)``, ``timestep (B,)`` or scalar, ``global_cond (B, G)`` -> ``(B, T, A)``."""
        x = sample.transpose(1, 2)
        t = torch.as_tensor(timestep, device=x.device).reshape(-1).expand(x.shape[0])
        cond = torch.cat([self.step_mlp(sinusoidal_embedding(t, self.step_embed_dim)), global_cond], dim=-1)
        skips = []
        for res1, res2, downsample in cast(Iterable[nn.ModuleList], self.down):  # (block, block, resample) each
            x = res2(res1(x, cond), cond)
            skips.append(x)
            x = downsample(x)
        for res in self.mid:
            x = res(x, cond)
        for res1, res2, upsample in cast(Iterable[nn.ModuleList], self.up):
            x = torch.cat([x, skips.pop()], dim=1)
            x = upsample(res2(res1(x, cond), cond))
        return self.final(x).transpose(1, 2)
