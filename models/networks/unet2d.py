"""A 2-D U-Net whose every residual block is conditioned through AdaGroupNorm (DIAMOND's inner model).

``InnerUNet(noisy, c_noise, context, cond)``: the noisy next frame ``(B, C, S, S)`` and the
context channels ``(B, X, S, S)`` (past frames, optional action maps) are concatenated and
pass an encoder-decoder of residual blocks; the conditioning vector is the Fourier embedding
of ``c_noise`` plus a linear embedding of ``cond`` (the flattened normalised actions of the
step), through a small MLP. Each block normalises with GroupNorm and then scales and shifts
by ``1 + scale(cond)`` and ``shift(cond)``. The output convolution starts at zero, so an
untrained denoiser returns ``c_skip * x``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import torch
import torch.nn.functional as F
from torch import nn


@dataclass(frozen=True)
class UNet2DConfig:
    """Sizes of the inner network (the paper's: channels (96, 96, 96, 96), depths 2, conditioning 256)."""

    channels: tuple[int, ...] = (32, 32, 64)  # width per resolution level (a 2x downsampling between levels)
    depths: tuple[int, ...] = (1, 1, 1)  # residual blocks per level (DIAMOND: 2)
    cond_channels: int = 128  # width of the conditioning vector (noise level + actions)
    mid_attention: bool = False  # self-attention in the two middle blocks (DIAMOND: yes)
    group_size: int = 32  # channels per GroupNorm group (at least one group)

    def __post_init__(self) -> None:
        if not self.channels or len(self.channels) != len(self.depths):
            raise ValueError(f"unet channels {self.channels} and depths {self.depths}: need one depth per level")
        if min(self.channels) < 1 or min(self.depths) < 1 or self.group_size < 1:
            raise ValueError("unet channels, depths and group_size must be at least 1")
        if self.cond_channels < 2 or self.cond_channels % 2:
            raise ValueError(f"cond_channels {self.cond_channels}: must be even and at least 2")

    @property
    def downsampling(self) -> int:
        return 2 ** (len(self.channels) - 1)


class AdaGroupNorm(nn.Module):
    """GroupNorm without affine parameters, then ``x (1 + scale(cond)) + shift(cond)``."""

    def __init__(self, channels: int, cond_channels: int, group_size: int) -> None:
        super().__init__()
        self.groups = max(1, channels // group_size)
        self.linear = nn.Linear(cond_channels, 2 * channels)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        scale, shift = self.linear(cond)[:, :, None, None].chunk(2, dim=1)
        return F.group_norm(x, self.groups, eps=1e-5) * (1 + scale) + shift


class SelfAttention2d(nn.Module):
    def __init__(self, channels: int, group_size: int, head_dim: int = 8) -> None:
        super().__init__()
        self.heads = max(1, channels // head_dim)
        self.norm = nn.GroupNorm(max(1, channels // group_size), channels)
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.out = nn.Conv2d(channels, channels, 1)
        nn.init.zeros_(self.out.weight)
        assert self.out.bias is not None  # Conv2d's default bias=True
        nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        q, k, v = self.qkv(self.norm(x)).reshape(b, 3, self.heads, c // self.heads, h * w).transpose(-1, -2).unbind(1)
        y = F.scaled_dot_product_attention(q, k, v)  # (B, heads, HW, c / heads)
        return x + self.out(y.transpose(-1, -2).reshape(b, c, h, w))


class ResBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int, cond_channels: int, group_size: int, attention: bool = False) -> None:
        super().__init__()
        self.skip = nn.Conv2d(c_in, c_out, 1) if c_in != c_out else nn.Identity()
        self.norm1 = AdaGroupNorm(c_in, cond_channels, group_size)
        self.conv1 = nn.Conv2d(c_in, c_out, 3, padding=1)
        self.norm2 = AdaGroupNorm(c_out, cond_channels, group_size)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1)
        nn.init.zeros_(self.conv2.weight)
        self.attn = SelfAttention2d(c_out, group_size) if attention else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x, cond)))
        h = self.conv2(F.silu(self.norm2(h, cond)))
        return self.attn(self.skip(x) + h)


class FourierFeatures(nn.Module):
    """``(B,)`` scalars -> ``(B, dim)`` random Fourier features (fixed, saved with the weights)."""

    weight: torch.Tensor  # registered buffer

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.register_buffer("weight", torch.randn(1, dim // 2))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = 2 * math.pi * x[:, None].to(self.weight.dtype) @ self.weight
        return torch.cat([f.cos(), f.sin()], dim=-1)


class InnerUNet(nn.Module):
    """``(noisy (B, C, S, S), c_noise (B,), context (B, X, S, S), cond (B, N)) -> (B, C, S, S)``."""

    def __init__(self, config: UNet2DConfig, img_channels: int, context_channels: int, cond_dim: int) -> None:
        super().__init__()
        c, e, g = config.channels, config.cond_channels, config.group_size
        self.config = config
        self.noise_emb = FourierFeatures(e)
        self.cond_emb = nn.Linear(cond_dim, e)
        self.cond_proj = nn.Sequential(nn.Linear(e, e), nn.SiLU(), nn.Linear(e, e))
        self.conv_in = nn.Conv2d(img_channels + context_channels, c[0], 3, padding=1)
        self.down, self.up = nn.ModuleList(), nn.ModuleList()
        self.downsample = nn.ModuleList([nn.Identity()] + [nn.Conv2d(ch, ch, 3, stride=2, padding=1) for ch in c[:-1]])
        self.upsample = nn.ModuleList([nn.Conv2d(ch, ch, 3, padding=1) for ch in c[1:]])  # after level l + 1
        skips = []  # channels of each saved activation, in order
        prev = c[0]
        for ch, depth in zip(c, config.depths):
            skips.append(prev)  # the (downsampled) input of the level
            blocks = nn.ModuleList()
            for _ in range(depth):
                blocks.append(ResBlock(prev, ch, e, g))
                prev = ch
                skips.append(ch)
            self.down.append(blocks)
        self.mid = nn.ModuleList([ResBlock(c[-1], c[-1], e, g, config.mid_attention) for _ in range(2)])
        for level in reversed(range(len(c))):
            blocks = nn.ModuleList()
            for _ in range(config.depths[level] + 1):
                blocks.append(ResBlock(prev + skips.pop(), c[level], e, g))
                prev = c[level]
            self.up.append(blocks)
        self.norm_out = nn.GroupNorm(max(1, c[0] // g), c[0])
        self.conv_out = nn.Conv2d(c[0], img_channels, 3, padding=1)
        nn.init.zeros_(self.conv_out.weight)
        assert self.conv_out.bias is not None  # Conv2d's default bias=True
        nn.init.zeros_(self.conv_out.bias)

    def forward(self, noisy: torch.Tensor, c_noise: torch.Tensor, context: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        emb = self.cond_proj(self.noise_emb(c_noise).to(cond.dtype) + self.cond_emb(cond))
        h, w = noisy.shape[-2:]
        m = self.config.downsampling
        x = torch.cat([context.to(noisy.dtype), noisy], dim=1)
        x = F.pad(x, (0, -w % m, 0, -h % m))
        x = self.conv_in(x)
        saved = []
        for down, blocks in zip(self.downsample, self.down):
            x = down(x)
            saved.append(x)
            for block in cast(nn.ModuleList, blocks):
                x = block(x, emb)
                saved.append(x)
        for block in self.mid:
            x = block(x, emb)
        for i, blocks in enumerate(self.up):
            if i:
                x = self.upsample[len(self.upsample) - i](F.interpolate(x, scale_factor=2.0, mode="nearest"))
            for block in cast(nn.ModuleList, blocks):
                x = block(torch.cat([x, saved.pop()], dim=1), emb)
        x = self.conv_out(F.silu(self.norm_out(x)))
        return x[..., :h, :w]
