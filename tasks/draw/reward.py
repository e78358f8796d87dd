"""The drawing's reward on predicted states, differentiable (torch): the F1 the ink summary implies.

Registration places objects' outlines, which ink has none of; here a state's summary holds each bin's inked share
of the band and the share inked off it, so ``F1 = 2 R / (R + off + 1)`` with ``R`` the bins' sum
(``geometry.f1_from_summary``, exact on true states). A predicted summary can stray below 0; the shares are
clamped there, so the score stays a ratio. The task names it ``gpc.tasks.draw.reward:from_layout``, which
``gpc.models.rewards.state`` imports on first use (tasks never import models).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from gpc.tasks.draw.geometry import N_SUMMARY

SUMMARY_START = 8  # pen (2) and vertices (6) come first


class InkReward(nn.Module):
    """``(K, T, D)`` predicted states -> ``(K,)`` scores: the last step's F1 (``aggregate="final"``) or the
    discounted sum of every step's (``"discounted"``); the goal is unused (the triangle is in the state)."""

    def __init__(self, aggregate: str = "final", discount: float = 0.99) -> None:
        super().__init__()
        self.aggregate, self.discount = aggregate, discount

    def per_step(self, futures: torch.Tensor) -> torch.Tensor:
        if futures.dim() != 3 or futures.shape[-1] < SUMMARY_START + N_SUMMARY:
            raise ValueError(f"states: expected (K, T, D >= {SUMMARY_START + N_SUMMARY}), got {tuple(futures.shape)}")
        summary = futures[..., SUMMARY_START:SUMMARY_START + N_SUMMARY].clamp(min=0.0)
        recall = summary[..., :-1].sum(dim=-1)
        return 2.0 * recall / (recall + summary[..., -1] + 1.0)

    def forward(self, futures: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
        if self.aggregate == "final":
            return self.per_step(futures[:, -1:])[:, 0]
        rewards = self.per_step(futures)
        weights = self.discount ** torch.arange(rewards.shape[1], dtype=rewards.dtype, device=rewards.device)
        return (rewards * weights).sum(dim=1)


def from_layout(layout: Any, config: Any) -> InkReward:
    """The factory ``register_state_reward`` takes: ``config`` is a ``gpc.models.rewards.registration.RewardConfig``."""
    return InkReward(config.aggregate, config.discount)
