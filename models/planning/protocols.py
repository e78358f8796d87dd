"""The small interfaces planners and the evaluation harness depend on (structural typing)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch


class ChunkTimeline(Protocol):
    """The action-chunk timeline a policy samples on (Diffusion Policy's, see ``PolicyConfig``)."""

    @property
    def horizon(self) -> int: ...  # actions per chunk

    @property
    def n_obs_steps(self) -> int: ...  # observation history length; the chunk's index n_obs_steps - 1 is "now"

    @property
    def n_action_steps(self) -> int: ...  # actions executed per decision

    @property
    def action_dim(self) -> int: ...


@runtime_checkable
class ActionProposer(Protocol):
    """A generative policy: K action chunks for one observation history in one batched call."""

    @property
    def config(self) -> ChunkTimeline: ...

    @property
    def obs_keys(self) -> tuple[str, ...]: ...  # the observation keys it reads

    def sample(
        self, obs_history: Mapping[str, Any], num_samples: int = 1, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """``{key: (T, ...)}`` raw observations -> ``(K, horizon, action_dim)`` raw actions."""
        ...

    def sample_batch(
        self, obs: Mapping[str, Any], num_samples: int = 1,
        generator: torch.Generator | Sequence[torch.Generator] | None = None, *,
        method: str | None = None, steps: int | None = None, spacing: str | None = None,
    ) -> torch.Tensor:
        """``{key: (B, T, ...)}`` -> ``(B, K, horizon, action_dim)``; one generator per history repeats ``sample``.
        ``method`` / ``steps`` / ``spacing``: another sampler than the policy's own (``None``: its own)."""
        ...


@dataclass
class Plan:
    """A controller's decision for B observation histories."""

    actions: np.ndarray  # (B, n_exec, A): to execute now (receding horizon)
    chunk: np.ndarray  # (B, T', A): the planned chunk from the current step on (actions is its head)
    seconds: dict[str, float] = field(default_factory=dict)  # time by part: policy, world_model, reward, optimizer
    scores: np.ndarray | None = None  # (B, K): each candidate's predicted reward (planners only)
    chosen: np.ndarray | None = None  # (B,): index of the executed candidate
    futures: np.ndarray | None = None  # (B, K, T, ...): each candidate's predicted future, when kept
    candidates: np.ndarray | None = None  # (B, K, T, A): the candidate chunks, when futures are kept


@runtime_checkable
class Controller(Protocol):
    """Anything that maps observation histories to action chunks: the policy itself (BC) or a planner."""

    obs_keys: tuple[str, ...]  # data keys it reads (state, keypoint, img, ...)
    n_obs_steps: int  # history length it needs

    def plan(self, obs: Mapping[str, np.ndarray], generators: Sequence[torch.Generator]) -> Plan:
        """``{key: (B, n_obs_steps, ...)}`` -> a Plan; ``generators[b]`` is history b's own random stream."""
        ...


@runtime_checkable
class WorldModel(Protocol):
    """Rolls out K action chunks from one (or K) observation histories in one batched, differentiable call.

    Planners read the history from the observation named by an optional ``obs_key``
    attribute (``state`` when absent; ``img`` for visual models, whose futures are frames
    ``(K, T', 3, S, S)``; the ground-truth simulator reads ``sim``). An ensemble also has
    ``rollout_members`` (``(E, K, T, ...)``) and ``combine`` (``(E, ...)`` member scores -> one):
    the objective then scores every member's future (``gpc.models.world_models.ensemble``).
    """

    @property
    def n_obs_steps(self) -> int: ...  # history length H the model reads

    def rollout(self, history: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """``(K, H, D)`` or ``(H, D)`` raw states, ``(K, T, A)`` raw actions -> ``(K, T, D)`` predicted raw
        states ``s_{t+1} .. s_{t+T}`` (state ``t + i + 1`` follows action ``i``)."""
        ...


@runtime_checkable
class Reward(Protocol):
    """Scores a batch of predicted futures; higher is better, differentiable for GPC-OPT."""

    def __call__(self, futures: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
        """``(K, T, ...)`` predicted futures (states or frames), goals ``(K, G)`` or None (the
        reward's own) -> ``(K,)`` scores. A reward with ``selects = True`` only ranks one
        history's candidates (it is called per history and never differentiated)."""
        ...


@runtime_checkable
class Scorer(Protocol):
    """Builds each decision's objective, ``(B, K, T, A)`` chunks -> ``(B, K)`` scores and ``(B, K, ...)`` predictions,
    from the observations: a world model with a reward (``objective.ModelScorer``), a Q-function, a latent model."""

    obs_keys: tuple[str, ...]  # the observations it reads (a goal is passed along when observed)
    n_obs_steps: int  # history length it needs
    differentiable: bool  # whether gradient planners may ascend its scores

    def objective(self, obs: Mapping[str, np.ndarray], timer: Any, episodes: Sequence[int] | None = None) -> Any:
        """``{key: (B, H, ...)}`` -> a callable of ``(B, K, T, A)`` chunks -> (scores, predictions); ``timer`` times parts."""
        ...
