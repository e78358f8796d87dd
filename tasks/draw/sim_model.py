"""The true drawing simulator as a world model (the ground-truth ceiling): ``gpc.tasks.planar.sim_model``'s replay on
a private ``DrawSim``, restored from the observation ``sim`` (pen, triangle, ink grid) and returning 33-d states."""

from __future__ import annotations

import numpy as np

from gpc.tasks.draw.sim import SIM_DIM, STATE_DIM, DrawSim
from gpc.tasks.planar.sim_model import SIM_KEY, ReplayModel

__all__ = ["SIM_KEY", "SimulatorModel"]


class SimulatorModel(ReplayModel):
    """``rollout(history (K, H, SIM_DIM), actions (K, T, 2)) -> (K, T, 33)`` states, by exact replay (the pen touches
    nothing, so there is no contact cache to forget)."""

    def __init__(self) -> None:
        self._scene = DrawSim()
        super().__init__(self._scene, SIM_DIM, STATE_DIM)

    def restore(self, vector: np.ndarray) -> None:
        self._scene.restore(vector)
