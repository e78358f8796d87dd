"""Exponential moving average of a network's weights with Diffusion Policy's warm-up.

The decay after ``n`` updates (``step = n - update_after - 1``) is
``0`` while ``step <= 0``, else ``clip(1 - (1 + step / inv_gamma) ** -power, min, max)``;
with power 0.75 it reaches 0.999 after ~10k updates. Parameters that do not train (and
buffers) are copied, not averaged. The averaged copy and the update count are submodule
state, so they travel inside checkpoints and resume exactly.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class EMAConfig:
    """Diffusion Policy's EMA settings."""

    power: float = 0.75  # warm-up exponent
    inv_gamma: float = 1.0  # warm-up time scale
    min_decay: float = 0.0  # lower bound once warm-up has started
    max_decay: float = 0.9999  # upper bound
    update_after: int = 0  # updates before averaging starts (until then the copy follows the weights)

    def __post_init__(self) -> None:
        if self.power <= 0 or self.inv_gamma <= 0:
            raise ValueError(f"EMA power {self.power} and inv_gamma {self.inv_gamma} must be positive")
        if not 0.0 <= self.min_decay <= self.max_decay < 1.0:
            raise ValueError(f"EMA decay bounds ({self.min_decay}, {self.max_decay}) must satisfy 0 <= min <= max < 1")
        if self.update_after < 0:
            raise ValueError(f"EMA update_after {self.update_after}: must be >= 0")

    def decay(self, updates: int) -> float:
        """Decay applied at the update that follows ``updates`` earlier ones."""
        step = max(0, updates - self.update_after - 1)
        if step <= 0:
            return 0.0
        value = 1.0 - (1.0 + step / self.inv_gamma) ** -self.power
        return max(self.min_decay, min(value, self.max_decay))


class EMAWeights(nn.Module):
    """Holds ``model``: an averaged, frozen copy of the network passed at construction."""

    updates: torch.Tensor  # registered buffer: how many updates have been folded in

    def __init__(self, source: nn.Module, config: EMAConfig) -> None:
        super().__init__()
        self.config = config
        self.model = copy.deepcopy(source).requires_grad_(False).eval()
        self.register_buffer("updates", torch.zeros((), dtype=torch.long))

    @torch.no_grad()
    def update(self, source: nn.Module) -> float:
        """Fold ``source``'s current weights into the average; returns the decay used."""
        decay = self.config.decay(int(self.updates))
        for p_src, p_ema in zip(source.parameters(), self.model.parameters()):
            if p_src.requires_grad:
                p_ema.mul_(decay).add_(p_src.detach().to(p_ema.dtype), alpha=1.0 - decay)
            else:
                p_ema.copy_(p_src.detach())
        for b_src, b_ema in zip(source.buffers(), self.model.buffers()):
            b_ema.copy_(b_src)
        self.updates += 1
        return decay

    def train(self, mode: bool = True) -> EMAWeights:
        """The averaged copy always stays in evaluation mode (centre crops, no dropout)."""
        super().train(mode)
        self.model.eval()
        return self
