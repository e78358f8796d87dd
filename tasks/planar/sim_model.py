"""The true simulator as a world model (the ground-truth ceiling of GPC's planners), for any planar scene.

It reads the observation ``sim`` (the full body state, velocities included, which ``state`` lacks) and replays each
candidate chunk in a private scene restored from it, returning states in the ``state`` layout so the task's reward
scores them. It implements the ``WorldModel`` protocol structurally (tasks never import models).

Exactness: body state is restored exactly, but pymunk's contact warm-start cache cannot be saved, so a prediction
can differ from what the episode's own scene then does by a small amount once contacts persist across the decision.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    import torch

SIM_KEY = "sim"


class ReplayScene(Protocol):
    """A scene that steps one action and reports its ``state``."""

    def step(self, action: np.ndarray) -> Any: ...

    def state(self) -> np.ndarray: ...


class ReplayModel:
    """``rollout(history (K, H, sim_dim), actions (K, T, action_dim)) -> (K, T, state_dim)`` states, by exact replay.

    A task's model gives its private scene and sizes, and says how the scene returns to a ``sim`` vector (``restore``,
    cached contacts forgotten).
    """

    obs_key = SIM_KEY
    n_obs_steps = 1

    def __init__(self, scene: ReplayScene, sim_dim: int, state_dim: int, action_dim: int = 2) -> None:
        self._sim, self.sim_dim, self.state_dim, self.action_dim = scene, sim_dim, state_dim, action_dim

    def restore(self, vector: np.ndarray) -> None:
        raise NotImplementedError

    def rollout(self, history: torch.Tensor | np.ndarray, actions: torch.Tensor | np.ndarray) -> torch.Tensor:
        import torch  # here, not at the top: recording, `gpc data` and `gpc compare` read this module without torch

        history = np.asarray(torch.as_tensor(history).detach().cpu(), dtype=np.float64)
        actions = np.asarray(torch.as_tensor(actions).detach().cpu(), dtype=np.float64)
        if actions.ndim != 3 or actions.shape[-1] != self.action_dim:
            raise ValueError(f"actions: expected (K, T, {self.action_dim}), got {actions.shape}")
        if history.ndim == 2:
            history = np.broadcast_to(history, (actions.shape[0],) + history.shape)
        if history.ndim != 3 or history.shape[-1] != self.sim_dim or history.shape[0] != actions.shape[0]:
            raise ValueError(f"history: expected (K={actions.shape[0]}, H, {self.sim_dim}) simulator states, got {history.shape}")
        out = np.empty(actions.shape[:2] + (self.state_dim,), dtype=np.float64)
        sim = self._sim
        for k in range(actions.shape[0]):
            self.restore(history[k, -1])
            for t, action in enumerate(actions[k]):
                sim.step(action)
                out[k, t] = sim.state()
        return torch.as_tensor(out, dtype=torch.float32)
