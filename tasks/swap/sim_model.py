"""The true swap simulator as a world model (the ground-truth ceiling): ``gpc.tasks.planar.sim_model``'s replay on a
private ``SwapSim``, restored from the observation ``sim`` (16) and returning 7-d states."""

from __future__ import annotations

import numpy as np

from gpc.tasks.planar.sim_model import SIM_KEY, ReplayModel
from gpc.tasks.swap.sim import SIM_DIM, STATE_DIM, SwapSim

__all__ = ["SIM_KEY", "SimulatorModel"]


class SimulatorModel(ReplayModel):
    """``rollout(history (K, H, 16), actions (K, T, 2)) -> (K, T, 7)`` states, by exact replay."""

    def __init__(self) -> None:
        self._scene = SwapSim()
        super().__init__(self._scene, SIM_DIM, STATE_DIM)

    def restore(self, vector: np.ndarray) -> None:
        self._scene.restore_clean(vector)
