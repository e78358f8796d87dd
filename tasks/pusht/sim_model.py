"""The true simulator as a world model: the ground-truth ceiling of GPC's planners.

It reads the observation ``sim`` (the full body state, velocities included, which the
5-entry ``state`` lacks) and replays each candidate chunk in a private ``PushTSim``
restored from it, returning states in the ``state`` layout so the same reward scores them.
It implements the ``WorldModel`` protocol structurally (tasks never import models).

Exactness: body state is restored exactly, but pymunk's contact warm-start cache cannot be
saved, so a prediction can differ from what the episode's own scene then does by a small
amount once contacts persist across the decision (measured by ``gpc check-sim``: p95
0.01 px, max 0.21 px over 16 steps).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from gpc.tasks.pusht.sim import PushTSim, SimSnapshot

if TYPE_CHECKING:
    import torch

SIM_KEY = "sim"
SIM_DIM = 10  # agent x, y, vx, vy; block x, y, angle, vx, vy, omega


def sim_vector(sim: PushTSim) -> np.ndarray:
    """The observation ``sim``: ``(10,)`` float64, everything ``restore`` needs."""
    snap = sim.snapshot()
    return np.array(snap.agent + snap.block, dtype=np.float64)


def snapshot_of(vector: np.ndarray) -> SimSnapshot:
    v = [float(x) for x in vector]
    return SimSnapshot(tuple(v[:4]), tuple(v[4:]))  # type: ignore[arg-type]


class SimulatorModel:
    """``rollout(history (K, H, 10), actions (K, T, 2)) -> (K, T, 5)`` states, by exact replay."""

    obs_key = SIM_KEY
    n_obs_steps = 1

    def __init__(self) -> None:
        self._sim = PushTSim()

    def rollout(self, history: torch.Tensor | np.ndarray, actions: torch.Tensor | np.ndarray) -> torch.Tensor:
        import torch  # here, not at the top: recording, `gpc data` and `gpc compare` read this module without torch

        history = np.asarray(torch.as_tensor(history).detach().cpu(), dtype=np.float64)
        actions = np.asarray(torch.as_tensor(actions).detach().cpu(), dtype=np.float64)
        if actions.ndim != 3 or actions.shape[-1] != 2:
            raise ValueError(f"actions: expected (K, T, 2), got {actions.shape}")
        if history.ndim == 2:
            history = np.broadcast_to(history, (actions.shape[0],) + history.shape)
        if history.ndim != 3 or history.shape[-1] != SIM_DIM or history.shape[0] != actions.shape[0]:
            raise ValueError(f"history: expected (K={actions.shape[0]}, H, {SIM_DIM}) simulator states, got {history.shape}")
        out = np.empty(actions.shape[:2] + (5,), dtype=np.float64)
        sim = self._sim
        for k in range(actions.shape[0]):
            sim.restore_clean(snapshot_of(history[k, -1]))
            for t, action in enumerate(actions[k]):
                sim.step(action)
                out[k, t] = sim.state()
        return torch.as_tensor(out, dtype=torch.float32)
