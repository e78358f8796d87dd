"""The planners' objective: world model and reward as one function of candidate chunks, timed by part.

DINO-WM's planner interface: a planner receives an objective and asks it for one score per
candidate; it never calls the world model or the reward itself. A ``Scorer`` builds the objective
of each decision from its observations: ``ModelScorer`` (GPC's: a world model's futures scored by a
reward) here, a Q-function (``gpc.models.values``) or a latent model elsewhere.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch

from gpc.models.planning.protocols import Reward, WorldModel

GOAL_KEY = "goal"  # the observation holding a per-episode goal, passed to the reward


class PartTimer:
    """Seconds spent per part of a decision (policy, world_model, reward, optimizer)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, part: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[part] = self.seconds.get(part, 0.0) + time.perf_counter() - t0


class Objective:
    """World model + reward as one function of ``(B, K, T, A)`` chunks -> ``(B, K)`` scores."""

    def __init__(self, world_model: WorldModel, reward: Reward, history: torch.Tensor,
                 goal: torch.Tensor | None, timer: PartTimer, episodes: Sequence[int] | None = None) -> None:
        self.world_model, self.reward, self.timer = world_model, reward, timer
        self.history, self.goal = history, goal  # (B, H, D), (B, G) or None
        self.episodes = episodes  # ids of the B histories' episodes (a selector warns once per episode)

    def __call__(self, chunks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(B, K, T, A)`` -> scores ``(B, K)`` and predicted futures ``(B, K, T', ...)``.

        An ensemble (``gpc.models.world_models.ensemble``) scores every member's future and combines the scores; its
        futures here are the members' mean (a selecting reward, which only ranks, reads those).
        """
        b, k = chunks.shape[:2]
        history = self.history[:, None].expand(b, k, *self.history.shape[1:]).flatten(0, 1)
        members = getattr(self.world_model, "rollout_members", None)
        with self.timer("world_model"):
            if members is None:
                futures = self.world_model.rollout(history, chunks.flatten(0, 1)).unflatten(0, (b, k))  # the reward
                # reads these very tensors, so a gradient on them is the score's (the ascent's diagnostics read it)
            else:
                each = members(history, chunks.flatten(0, 1))  # (E, B*K, T', ...)
                futures = each.mean(0).unflatten(0, (b, k))
        goal = None if self.goal is None else self.goal[:, None].expand(b, k, -1).flatten(0, 1)
        with self.timer("reward"):
            if getattr(self.reward, "selects", False):  # a selector ranks one history's candidates at a time
                goals = [None if self.goal is None else self.goal[i] for i in range(b)]
                ids = self.episodes if self.episodes is not None and len(self.episodes) == b else range(b)
                select: Any = self.reward  # a selector also takes the episode id (it warns once per episode)
                scores = torch.stack([select(futures[i], goals[i], episode=int(ids[i])) for i in range(b)])
            elif members is None:
                scores = self.reward(futures.flatten(0, 1), goal).unflatten(0, (b, k))
            else:
                e = each.shape[0]  # every member's futures in one call
                per_member = self.reward(each.flatten(0, 1), None if goal is None else goal.repeat(e, 1)).unflatten(0, (e, b * k))
                ensemble: Any = self.world_model
                scores = ensemble.combine(per_member).unflatten(0, (b, k))
        return scores, futures


class ModelScorer:
    """GPC's scorer: roll each candidate out with the world model and score its future with the reward.

    ``world_model.obs_key`` (default ``state``) names the observation the world model reads; an
    observation ``goal`` (tasks with a per-episode goal) is passed to the reward. Both are frozen
    here (``requires_grad_(False)``): gradient ascent moves actions only.
    """

    def __init__(self, world_model: WorldModel, reward: Reward) -> None:
        self.world_model, self.reward = world_model, reward
        for frozen in (world_model, reward):
            if isinstance(frozen, torch.nn.Module):
                frozen.requires_grad_(False)
        self.key = getattr(world_model, "obs_key", "state")
        self.obs_keys: tuple[str, ...] = (self.key,)
        self.n_obs_steps: int = world_model.n_obs_steps
        self.differentiable = not getattr(reward, "selects", False)  # a selecting reward (a VLM) only ranks

    def objective(self, obs: Mapping[str, np.ndarray], timer: PartTimer, episodes: Sequence[int] | None = None) -> Objective:
        history = torch.as_tensor(np.asarray(obs[self.key]))
        goal = torch.as_tensor(np.asarray(obs[GOAL_KEY])[:, -1], dtype=torch.float32) if GOAL_KEY in obs else None
        return Objective(self.world_model, self.reward, history, goal, timer, episodes)

    def stats(self) -> dict[str, Any]:
        """Counters of the reward (a VLM's queries and fallbacks), summed over every decision so far."""
        stats = getattr(self.reward, "stats", None)
        return dict(stats() if callable(stats) else stats or {})
