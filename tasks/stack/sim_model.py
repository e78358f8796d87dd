"""The true stacking simulator as a world model (the ground-truth ceiling): ``gpc.tasks.planar.sim_model``'s replay
on a private ``StackSim``, restored exactly from the observation ``sim`` (MuJoCo's whole state) and returning 18-d
states."""

from __future__ import annotations

import numpy as np

from gpc.tasks.planar.sim_model import SIM_KEY, ReplayModel
from gpc.tasks.stack.scene import STATE_DIM, StackSim

__all__ = ["SIM_KEY", "SimulatorModel"]


class SimulatorModel(ReplayModel):
    """``rollout(history (K, H, sim), actions (K, T, 4)) -> (K, T, 18)`` states, by exact replay."""

    def __init__(self) -> None:
        self._scene = StackSim()
        super().__init__(self._scene, self._scene.vector_size, STATE_DIM, action_dim=4)

    def restore(self, vector: np.ndarray) -> None:
        self._scene.restore(vector)
