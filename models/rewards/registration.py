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

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

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
    """``-registration`` of the objects' poses read from each predicted step, aggregated over the steps.

    Subclasses say how a future ``(K, T, ...)`` becomes poses ``(K, T, P)`` (``poses``): read
    from a state vector (``RegistrationReward``) or predicted from a frame (``ImageReward``
    in ``gpc.models.rewards.learned``). ``vertices``: one object's ``(V, 2)`` object-frame points
    (Push-T: the T's 8 box corners), or a sequence of them, one per object; ``sizes``: each object's
    pose entries (3 with an angle, 2 without; default: the goal's length, one object). A step's
    registration is the mean over the objects. ``goal``: ``(P,)``, the objects' poses laid out in
    order, or None where the task draws a goal per episode: a call passes its goals ``(P,)`` or
    ``(K, P)`` (a goal per candidate).
    """

    goal: torch.Tensor | None  # registered buffers

    def __init__(self, vertices: torch.Tensor | Sequence[torch.Tensor], goal: torch.Tensor | None,
                 config: RewardConfig = RewardConfig(), sizes: Sequence[int] | None = None) -> None:
        super().__init__()
        shapes = [vertices] if _points(vertices) else list(vertices)
        goal = None if goal is None else torch.as_tensor(goal, dtype=torch.float32)
        if sizes is None:
            if goal is None or len(shapes) != 1:
                raise ValueError("pose sizes: give each object's (sizes) where there are several objects or no default goal")
            sizes = (goal.shape[0],)
        if len(sizes) != len(shapes) or any(n not in (2, 3) for n in sizes):
            raise ValueError(f"pose sizes {tuple(sizes)}: need 2 (x, y) or 3 (x, y, theta) for each of {len(shapes)} objects")
        if goal is not None and goal.shape != (sum(sizes),):
            raise ValueError(f"goal pose: expected ({sum(sizes)},) = the objects' poses laid out in order, got {tuple(goal.shape)}")
        self.config = config
        self.sizes = tuple(int(n) for n in sizes)
        for i, points in enumerate(shapes):
            self.register_buffer(f"vertices_{i}", torch.as_tensor(points, dtype=torch.float32).reshape(-1, 2))
        self.register_buffer("goal", goal)

    @property
    def vertices(self) -> list[torch.Tensor]:
        """Each object's ``(V, 2)`` points."""
        return [getattr(self, f"vertices_{i}") for i in range(len(self.sizes))]

    def poses(self, futures: torch.Tensor) -> torch.Tensor:
        """``(K, T, ...)`` predicted futures -> ``(K, T, P)`` object poses ``(x, y[, theta])``, object after object."""
        raise NotImplementedError

    def per_step(self, futures: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
        """``(K, T, ...)`` predicted futures -> ``(K, T)`` rewards (0 at the goal, negative elsewhere)."""
        poses = self.poses(futures)
        if goal is None and self.goal is None:
            raise ValueError("this reward's goal varies per episode: pass the episode's goal (an observation 'goal')")
        goal = self.goal if goal is None else torch.as_tensor(goal, dtype=poses.dtype, device=poses.device)
        assert goal is not None
        if goal.dim() == 2:  # (K, P): one goal per candidate, the same for all its steps
            goal = goal[:, None]
        return -registration(poses, goal.to(poses.dtype), [v.to(poses.dtype) for v in self.vertices], self.sizes)

    def forward(self, futures: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
        """``(K, T, ...)`` predicted futures -> ``(K,)`` scores, higher is better."""
        if self.config.aggregate == "final":  # only the last step scores: read no other (an image reader costs T x)
            futures = futures[:, -1:]
        return aggregate(self.per_step(futures, goal), self.config)


def _points(value: Any) -> bool:
    """Whether ``value`` is one object's points (an array, or pairs of numbers) rather than a sequence of objects' points."""
    if hasattr(value, "ndim"):
        return True
    first = value[0] if len(value) else None
    return first is not None and len(first) == 2 and all(isinstance(x, (int, float)) for x in first)


def registration(poses: torch.Tensor, goals: torch.Tensor, vertices: Sequence[torch.Tensor], sizes: Sequence[int]) -> torch.Tensor:
    """Mean over the objects of their registration distance: poses ``(..., P)``, goals broadcastable, each
    object's points ``(V_i, 2)`` and pose entries ``sizes[i]`` -> ``(...)``."""
    if len(sizes) == 1:  # one object (Push-T): its distance as it is
        return registration_distance(poses, goals, vertices[0])
    start, parts = 0, []
    for points, n in zip(vertices, sizes):
        parts.append(registration_distance(poses[..., start:start + n], goals[..., start:start + n], points))
        start += n
    return torch.stack(parts).mean(dim=0)


def layout_registration(a: torch.Tensor, b: torch.Tensor, layout: TaskLayout) -> torch.Tensor:
    """Registration distance between the objects in states ``a`` and ``b`` ``(..., D)`` of a task -> ``(...)``."""
    pose = list(layout.pose_dims)
    vertices = [torch.tensor(o.vertices, dtype=a.dtype, device=a.device) for o in layout.objects]
    return registration(a[..., pose], b[..., pose], vertices, [len(o.pose) for o in layout.objects])


def pose_errors(pred: torch.Tensor, true: torch.Tensor, vertices: torch.Tensor | Sequence[torch.Tensor],
                goal: torch.Tensor | None, sizes: Sequence[int] | None = None) -> dict[str, torch.Tensor]:
    """``(N, P)`` predicted and true poses -> per-frame errors ``(N,)``, each the mean over the objects (``sizes``:
    their pose entries; default one object): position px, angle deg (objects with an angle; NaN where none has one),
    vertex px (mean vertex distance between the two poses), and the registration loss against ``goal`` ``(P,)`` or
    ``(N, P)`` (true, predicted, absolute error px; left out without a goal)."""
    sizes = tuple(sizes or (pred.shape[1],))
    shapes = [vertices] if isinstance(vertices, torch.Tensor) else list(vertices)
    starts = [sum(sizes[:i]) for i in range(len(sizes))]
    position = torch.stack([(pred[:, s : s + 2] - true[:, s : s + 2]).norm(dim=1) for s in starts]).mean(dim=0)
    turns = [torch.remainder(pred[:, s + 2] - true[:, s + 2] + math.pi, 2 * math.pi) - math.pi for s, n in zip(starts, sizes) if n == 3]
    angle = torch.stack(turns).abs().mean(dim=0) if turns else torch.full_like(position, float("nan"))
    out = {"position_px": position, "angle_deg": angle * (180.0 / math.pi), "vertex_px": registration(pred, true, shapes, sizes)}
    if goal is not None:
        true_reg, pred_reg = registration(true, goal, shapes, sizes), registration(pred, goal, shapes, sizes)
        out.update(registration_true_px=true_reg, registration_pred_px=pred_reg, registration_abs_err_px=(pred_reg - true_reg).abs())
    return out


class RegistrationReward(PoseReward):
    """``-registration`` of the predicted objects' poses against the goal, aggregated over the predicted steps.

    Futures are states ``(K, T, D)``; the poses sit at ``pose_dims`` (every object's entries, in order).
    See ``PoseReward`` for the vertices, the goal and per-candidate goals; ``from_layout`` takes all from a task.
    """

    def __init__(self, vertices: torch.Tensor | Sequence[torch.Tensor], goal: torch.Tensor | None, pose_dims: tuple[int, ...],
                 config: RewardConfig = RewardConfig(), sizes: Sequence[int] | None = None) -> None:
        super().__init__(vertices, goal, config, sizes)
        if len(pose_dims) != sum(self.sizes) or len(set(pose_dims)) != len(pose_dims) or min(pose_dims) < 0:
            raise ValueError(f"pose_dims {pose_dims}: need {sum(self.sizes)} distinct state indices, as the goal has")
        self.pose_dims = tuple(pose_dims)

    @classmethod
    def from_layout(cls, layout: TaskLayout, config: RewardConfig = RewardConfig()) -> RegistrationReward:
        """The task's objects: their outlines, default goals (if fixed) and pose entries."""
        goal = None if layout.goal is None else torch.tensor(layout.goal)
        return cls([torch.tensor(o.vertices) for o in layout.objects], goal, layout.pose_dims, config,
                   [len(o.pose) for o in layout.objects])

    def poses(self, states: torch.Tensor) -> torch.Tensor:
        if states.dim() != 3 or states.shape[-1] <= max(self.pose_dims):
            raise ValueError(f"states: expected (K, T, D > {max(self.pose_dims)}), got {tuple(states.shape)}")
        return states[..., list(self.pose_dims)]
