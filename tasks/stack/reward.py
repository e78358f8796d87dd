"""The stacking reward on predicted states, differentiable, for planners (``Task.state_reward`` names it).

Per step: minus the red cube's distance to its target one cube side above the blue cube, over ``REWARD_DISTANCE``
(0 on target, -1 at 10 cm: the environment's reward before clipping, so ranking agrees with it where it counts and
gradients do not vanish far away), the distance smoothed at 0 so its gradient stays finite. Both cubes come from
the prediction, so a plan that moves the blue cube is scored against where the blue cube goes; the ``goal``
observation is not needed. Torch only (tasks import no ``gpc.models``); ``gpc.models.rewards.state`` imports it by
name.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from gpc.tasks.stack.geometry import BLUE, RED, REWARD_DISTANCE
from gpc.tasks.stack.scene import CUBE_SIDE

EPS = 1e-4  # m: the distance's smoothing at 0


class StackReward(nn.Module):
    """``(K, T, 18)`` predicted states -> ``(K,)`` scores, higher is better (``aggregate``: final or discounted)."""

    def __init__(self, aggregate: str = "final", discount: float = 0.99) -> None:
        super().__init__()
        if aggregate not in ("final", "discounted"):
            raise ValueError(f"aggregate {aggregate!r}: use final or discounted")
        self.aggregate, self.discount = aggregate, discount

    def per_step(self, futures: torch.Tensor) -> torch.Tensor:
        """``(K, T, 18)`` -> ``(K, T)`` rewards."""
        if futures.dim() != 3 or futures.shape[-1] != 18:
            raise ValueError(f"states: expected (K, T, 18) stacking states, got {tuple(futures.shape)}")
        lift = torch.tensor([0.0, 0.0, CUBE_SIDE], dtype=futures.dtype, device=futures.device)
        d2 = (futures[..., RED] - futures[..., BLUE] - lift).pow(2).sum(dim=-1)
        return -(torch.sqrt(d2 + EPS * EPS) - EPS) / REWARD_DISTANCE

    def forward(self, futures: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
        rewards = self.per_step(futures)
        if self.aggregate == "final":
            return rewards[:, -1]
        weights = self.discount ** torch.arange(rewards.shape[1], dtype=rewards.dtype, device=rewards.device)
        return (rewards * weights).sum(dim=1)


def stack_reward(layout: Any, config: Any) -> StackReward:
    """The factory ``gpc.models.rewards.state`` calls with the task's layout and a ``RewardConfig``."""
    return StackReward(config.aggregate, config.discount)
