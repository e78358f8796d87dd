"""The true simulator as a world model: the ground-truth ceiling of GPC's planners.

It reads the observation ``sim`` (the full body state, velocities included, which the
5-entry ``state`` lacks) and replays each candidate chunk in a private ``PushTSim``
restored from it, returning states in the ``state`` layout so the same reward scores them.
It implements the ``WorldModel`` protocol structurally (tasks never import models); the replay loop is every planar
task's (``gpc.tasks.planar.sim_model``).

Exactness: body state is restored exactly, but pymunk's contact warm-start cache cannot be
saved, so a prediction can differ from what the episode's own scene then does by a small
amount once contacts persist across the decision (measured by ``gpc check-sim``: p95
0.01 px, max 0.21 px over 16 steps).
"""

from __future__ import annotations

import numpy as np

from gpc.tasks.planar.sim_model import SIM_KEY, ReplayModel
from gpc.tasks.pusht.sim import PushTSim, SimSnapshot

__all__ = ["SIM_DIM", "SIM_KEY", "SimulatorModel", "sim_vector", "snapshot_of"]
SIM_DIM = 10  # agent x, y, vx, vy; block x, y, angle, vx, vy, omega


def sim_vector(sim: PushTSim) -> np.ndarray:
    """The observation ``sim``: ``(10,)`` float64, everything ``restore`` needs."""
    snap = sim.snapshot()
    return np.array(snap.agent + snap.block, dtype=np.float64)


def snapshot_of(vector: np.ndarray) -> SimSnapshot:
    v = [float(x) for x in vector]
    return SimSnapshot(tuple(v[:4]), tuple(v[4:]))  # type: ignore[arg-type]


class SimulatorModel(ReplayModel):
    """``rollout(history (K, H, 10), actions (K, T, 2)) -> (K, T, 5)`` states, by exact replay."""

    def __init__(self) -> None:
        self._scene = PushTSim()
        super().__init__(self._scene, SIM_DIM, 5)

    def restore(self, vector: np.ndarray) -> None:
        self._scene.restore_clean(snapshot_of(vector))
