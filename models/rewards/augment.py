"""Frame augmentation for the image reward's training (and the resize every reader of frames shares).

Predicted frames are blurry and a little off where recorded ones are sharp, so the reward's network trains on
randomly shifted and blurred frames; ``resize`` lets any frame size meet the size a network was trained at.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def resize(frames: torch.Tensor, size: int) -> torch.Tensor:
    """``(N, C, H, W)`` -> ``(N, C, size, size)``, antialiased bilinear (differentiable); unchanged if already that size."""
    if frames.shape[-2:] == (size, size):
        return frames
    return F.interpolate(frames, size=(size, size), mode="bilinear", align_corners=False, antialias=True)


def random_shift(x: torch.Tensor, max_px: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Translate each ``(N, C, S, S)`` image by up to ``max_px`` px (edges repeated) -> images, ``(N, 2)`` shifts (x, y) px."""
    n, s = x.shape[0], x.shape[-1]
    shift = (torch.rand(n, 2, device=x.device) * 2.0 - 1.0) * max_px
    theta = torch.zeros(n, 2, 3, device=x.device, dtype=x.dtype)
    theta[:, 0, 0] = theta[:, 1, 1] = 1.0
    theta[:, :, 2] = -2.0 * shift.to(x.dtype) / s  # output(p) = input(p - shift): the content moves by +shift
    grid = F.affine_grid(theta, list(x.shape), align_corners=False)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False), shift


def random_blur(x: torch.Tensor, prob: float, max_sigma: float) -> torch.Tensor:
    """Blur a random ``prob`` share of ``(N, C, H, W)`` images with a Gaussian of sigma ~ U(0, max_sigma) px."""
    n, c, h, w = x.shape
    radius = max(1, math.ceil(2.0 * max_sigma))
    sigma = torch.rand(n, device=x.device) * max_sigma * (torch.rand(n, device=x.device) < prob)
    taps = torch.arange(-radius, radius + 1, device=x.device, dtype=x.dtype)
    kernel = torch.exp(-taps.pow(2) / (2.0 * sigma.clamp_min(1e-3).to(x.dtype)[:, None] ** 2))
    kernel = (kernel / kernel.sum(dim=1, keepdim=True)).repeat_interleave(c, dim=0)  # (N * C, K)
    flat = F.pad(x.reshape(1, n * c, h, w), (radius,) * 4, mode="replicate")
    flat = F.conv2d(flat, kernel[:, None, None, :], groups=n * c)
    flat = F.conv2d(flat, kernel[:, None, :, None], groups=n * c)
    return flat.reshape(n, c, h, w)
