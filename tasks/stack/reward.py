"""The stacking reward on predicted states, differentiable, for planners (``Task.state_reward`` names it).

Per step: minus the red cube's distance to its target one cube side above the blue cube, over ``REWARD_DISTANCE``
(0 on target, -1 at 10 cm: the environment's reward before clipping, so ranking agrees with it where it counts and
gradients do not vanish far away), the distance smoothed at 0 so its gradient stays finite; plus a bonus of up to
``RELEASE`` for a release near the target (the red cube within about ``NEAR`` of it, the gripper open and its
fingertips clear: soft versions of ``geometry.released``). Success needs the cube let go, and the distance alone
scores holding it over the target as well as letting go, so gradient planners held it (docs/stack.md). Both cubes
come from the prediction, so a plan that moves the blue cube is scored against where the blue cube goes; the
``goal`` observation is not needed. Torch only (tasks import no ``gpc.models``); ``gpc.models.rewards.state``
imports it by name.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from gpc.tasks.stack.geometry import ASIDE, BLUE, CLEAR, GRIPPER, OPEN, OPENING, RED, REWARD_DISTANCE
from gpc.tasks.stack.scene import CUBE_SIDE, FINGER, FINGER_Z

EPS = 1e-4  # m: the distance's smoothing at 0
RELEASE = 1.0  # the release bonus's weight (in units of the distance term: 1 = 10 cm)
NEAR = 0.015  # m: the bonus falls as exp(-(distance / NEAR)^2)
SOFT_OPEN, SOFT_CLEAR, SOFT_ASIDE = 0.003, 0.005, 0.01  # m: the sigmoids' widths around OPEN, CLEAR and ASIDE


class StackReward(nn.Module):
    """``(K, T, 18)`` predicted states -> ``(K,)`` scores, higher is better (``aggregate``: final or discounted)."""

    def __init__(self, aggregate: str = "final", discount: float = 0.99, release: float | None = None) -> None:
        super().__init__()
        if aggregate not in ("final", "discounted"):
            raise ValueError(f"aggregate {aggregate!r}: use final or discounted")
        self.aggregate, self.discount = aggregate, discount
        self.release = RELEASE if release is None else release

    def per_step(self, futures: torch.Tensor) -> torch.Tensor:
        """``(K, T, 18)`` -> ``(K, T)`` rewards."""
        if futures.dim() != 3 or futures.shape[-1] != 18:
            raise ValueError(f"states: expected (K, T, 18) stacking states, got {tuple(futures.shape)}")
        lift = torch.tensor([0.0, 0.0, CUBE_SIDE], dtype=futures.dtype, device=futures.device)
        d2 = (futures[..., RED] - futures[..., BLUE] - lift).pow(2).sum(dim=-1)
        distance = torch.sqrt(d2 + EPS * EPS) - EPS
        rewards = -distance / REWARD_DISTANCE
        if self.release:
            rewards = rewards + self.release * torch.exp(-(distance / NEAR) ** 2) * self.let_go(futures)
        return rewards

    @staticmethod
    def let_go(futures: torch.Tensor) -> torch.Tensor:
        """Soft ``geometry.released``: open, and fingertips above the red cube's top or the hand aside, in (0, 1)."""
        gripper, red = futures[..., GRIPPER], futures[..., RED]
        opened = torch.sigmoid((futures[..., OPENING] - OPEN) / SOFT_OPEN)
        tips = gripper[..., 2] + FINGER_Z - FINGER[2]
        above = torch.sigmoid((tips - red[..., 2] - CUBE_SIDE / 2 - CLEAR) / SOFT_CLEAR)
        apart = torch.sqrt((gripper[..., :2] - red[..., :2]).pow(2).sum(dim=-1) + EPS * EPS)
        aside = torch.sigmoid((apart - ASIDE) / SOFT_ASIDE)
        return opened * (1 - (1 - above) * (1 - aside))

    def forward(self, futures: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
        rewards = self.per_step(futures)
        if self.aggregate == "final":
            return rewards[:, -1]
        weights = self.discount ** torch.arange(rewards.shape[1], dtype=rewards.dtype, device=rewards.device)
        return (rewards * weights).sum(dim=1)


def stack_reward(layout: Any, config: Any) -> StackReward:
    """The factory ``gpc.models.rewards.state`` calls with the task's layout and a ``RewardConfig``."""
    return StackReward(config.aggregate, config.discount)
