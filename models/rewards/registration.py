"""Rewards that score predicted futures by the negative registration loss of an object's pose.

The registration loss of a pose is the mean distance between an object's vertices placed
at that pose and at the goal pose (a pose ``(x, y, theta)`` maps an object point ``p`` to
``(x, y) + R(theta) p``; a pose ``(x, y)`` only translates it). The task's layout supplies
the vertices, the goal and where the pose sits in the state vector, so this module knows no task. Higher reward is better: the
reward is ``-registration`` (0 at the goal, negative elsewhere), differentiable and batched.

Both rewards share ``PoseReward``: a future becomes one object pose per step, the pose
becomes ``-registration`` against the goal, and ``aggregate`` turns the ``(K, T)`` per-step
rewards into ``(K,)`` scores. ``RegistrationReward`` reads the pose from predicted states;
``gpc.models.rewards.learned.ImageReward`` predicts it from predicted frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from gpc.datasets.layout import TaskLayout
from gpc.models.planning.protocols import Reward  # noqa: F401  (re-exported: the interface this module implements)

AGGREGATES = ("final", "discounted")


@dataclass(frozen=True)
class RewardConfig:
    """How per-step rewards of a predicted future become one score."""

    aggregate: str = "final"  # final: the last predicted step's reward; discounted: sum_t discount**t r_t
    discount: float = 0.99  # per-step factor of the discounted sum (t = 0 is the first predicted step)

    def __post_init__(self) -> None:
        if self.aggregate not in AGGREGATES:
            raise ValueError(f"reward aggregate {self.aggregate!r}: use one of {', '.join(AGGREGATES)}")
        if not 0.0 < self.discount <= 1.0:
            raise ValueError(f"discount {self.discount}: must lie in (0, 1]")


def place(points: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
    """Object-frame points ``(V, 2)`` at poses ``(..., 3)`` (or ``(..., 2)``: no turn) -> world points ``(..., V, 2)``."""
    x, y = points[:, 0], points[:, 1]  # (V,)
    if poses.shape[-1] == 2:
        return torch.stack([poses[..., 0:1] + x, poses[..., 1:2] + y], dim=-1)
    cos, sin = torch.cos(poses[..., 2:3]), torch.sin(poses[..., 2:3])  # (..., 1)
    wx = poses[..., 0:1] + cos * x - sin * y
    wy = poses[..., 1:2] + sin * x + cos * y
    return torch.stack([wx, wy], dim=-1)


def registration_distance(poses: torch.Tensor, goals: torch.Tensor, vertices: torch.Tensor,
                          eps: float = 1e-6) -> torch.Tensor:
    """Mean vertex distance between poses ``(..., 3)`` and goals (broadcastable) -> ``(...)``.

    ``sqrt(d^2 + eps^2) - eps`` keeps the gradient finite (zero) where a vertex sits exactly
    on its goal, and is 0 there.
    """
    d2 = (place(vertices, poses) - place(vertices, goals)).pow(2).sum(dim=-1)
    return (torch.sqrt(d2 + eps * eps) - eps).mean(dim=-1)


def aggregate(rewards: torch.Tensor, config: RewardConfig) -> torch.Tensor:
    """``(K, T)`` per-step rewards -> ``(K,)`` scores: the last step's, or ``sum_t discount**t r_t``."""
    if config.aggregate == "final":
        return rewards[:, -1]
    weights = config.discount ** torch.arange(rewards.shape[1], dtype=rewards.dtype, device=rewards.device)
    return (rewards * weights).sum(dim=1)


class PoseReward(nn.Module):
    """``-registration`` of an object pose read from each predicted step, aggregated over the steps.

    Subclasses say how a future ``(K, T, ...)`` becomes poses ``(K, T, 3)`` (``poses``): read
    from a state vector (``RegistrationReward``) or predicted from a frame (``ImageReward``
    in ``gpc.models.rewards.learned``). ``vertices``: ``(V, 2)`` object-frame points (Push-T:
    the T's 8 box corners); ``goal``: ``(P,)`` pose (``P`` = 3 with an angle, 2 without). A call
    may pass its own goals ``(P,)`` or ``(K, P)`` (a goal per candidate, for tasks whose goal
    varies per episode).
    """

    vertices: torch.Tensor  # registered buffers
    goal: torch.Tensor

    def __init__(self, vertices: torch.Tensor, goal: torch.Tensor, config: RewardConfig = RewardConfig()) -> None:
        super().__init__()
        vertices = torch.as_tensor(vertices, dtype=torch.float32).reshape(-1, 2)
        goal = torch.as_tensor(goal, dtype=torch.float32)
        if goal.shape not in ((2,), (3,)):
            raise ValueError(f"goal pose: expected (3,) = (x, y, theta) or (2,) = (x, y), got {tuple(goal.shape)}")
        self.config = config
        self.register_buffer("vertices", vertices)
        self.register_buffer("goal", goal)

    def poses(self, futures: torch.Tensor) -> torch.Tensor:
        """``(K, T, ...)`` predicted futures -> ``(K, T, P)`` object poses ``(x, y[, theta])``."""
        raise NotImplementedError

    def per_step(self, futures: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
        """``(K, T, ...)`` predicted futures -> ``(K, T)`` rewards (0 at the goal, negative elsewhere)."""
        poses = self.poses(futures)
        goal = self.goal if goal is None else torch.as_tensor(goal, dtype=poses.dtype, device=poses.device)
        if goal.dim() == 2:  # (K, 3): one goal per candidate, the same for all its steps
            goal = goal[:, None]
        return -registration_distance(poses, goal.to(poses.dtype), self.vertices.to(poses.dtype))

    def forward(self, futures: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
        """``(K, T, ...)`` predicted futures -> ``(K,)`` scores, higher is better."""
        if self.config.aggregate == "final":  # only the last step scores: read no other (an image reader costs T x)
            futures = futures[:, -1:]
        return aggregate(self.per_step(futures, goal), self.config)


class RegistrationReward(PoseReward):
    """``-registration`` of the predicted object pose against the goal, aggregated over the predicted steps.

    Futures are states ``(K, T, D)``; the pose sits at ``pose_dims``. See ``PoseReward`` for the
    vertices, the goal and per-candidate goals; ``from_layout`` takes all three from a task.
    """

    def __init__(self, vertices: torch.Tensor, goal: torch.Tensor, pose_dims: tuple[int, ...],
                 config: RewardConfig = RewardConfig()) -> None:
        super().__init__(vertices, goal, config)
        if len(pose_dims) != self.goal.shape[0] or len(set(pose_dims)) != len(pose_dims) or min(pose_dims) < 0:
            raise ValueError(f"pose_dims {pose_dims}: need {self.goal.shape[0]} distinct state indices, as the goal has")
        self.pose_dims = tuple(pose_dims)

    @classmethod
    def from_layout(cls, layout: TaskLayout, config: RewardConfig = RewardConfig()) -> RegistrationReward:
        """The task's object outline, default goal and pose entries."""
        return cls(torch.tensor(layout.target.vertices), torch.tensor(layout.target.goal), layout.state.object_pose, config)

    def poses(self, states: torch.Tensor) -> torch.Tensor:
        if states.dim() != 3 or states.shape[-1] <= max(self.pose_dims):
            raise ValueError(f"states: expected (K, T, D > {max(self.pose_dims)}), got {tuple(states.shape)}")
        return states[..., list(self.pose_dims)]
