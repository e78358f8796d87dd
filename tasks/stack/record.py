"""Recording stacking episodes in the store layout every task uses (the loop is ``gpc.tasks.planar.record``'s).

Each step stores what was observed before acting: ``state`` (18), ``goal`` (2: the red cube's target on the table
plane, the blue cube's x, y, which moves with it), ``img`` (96x96x3 uint8), the ``action`` (4) and ``n_contacts`` (1:
how many of the pairs gripper-red, gripper-blue, red-blue touched) of the step that led to it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from gpc.tasks.base import EpisodeStats
from gpc.tasks.planar import record as planar_record
from gpc.tasks.planar.record import episode_maxima, record_from_reset, with_extras
from gpc.tasks.stack import geometry
from gpc.tasks.stack.env import MAX_EPISODE_STEPS, StackEnv
from gpc.tasks.stack.scene import ACTION_HIGH, ACTION_LOW, StackSim


class ScriptedPolicy(Protocol):
    """A privileged controller: reads the true scene, returns a gripper target."""

    def reset(self, seed: int) -> None: ...

    def act(self, sim: StackSim) -> np.ndarray: ...


@dataclass(frozen=True)
class RecordConfig(planar_record.RecordConfig):
    """How long episodes run (this task's length by default) and what is stored."""

    max_steps: int = MAX_EPISODE_STEPS


def observe(env: StackEnv, images: bool = True, sim: bool = False) -> dict[str, np.ndarray]:
    """One step's observation in the data layout; ``sim`` adds MuJoCo's full state (never recorded) that the
    ground-truth world model restores from."""
    state = env.sim.state()
    obs = {"state": state.astype(np.float32), "goal": state[geometry.BLUE][:2].astype(np.float32)}
    return with_extras(obs, env, images, sim)


def record_episode(policy: ScriptedPolicy, seed: int, config: RecordConfig) -> tuple[dict[str, np.ndarray], EpisodeStats]:
    """Run ``policy`` from the env's reset for ``seed``; return the arrays and their summary (``contact_fraction``:
    the share of steps with any gripper-cube or cube-cube contact)."""
    env = StackEnv(obs_type="state")
    return record_from_reset(env, policy, lambda: policy.act(env.sim), lambda: observe(env, config.images), seed, config,
                             ACTION_LOW, ACTION_HIGH)


def episode_scores(states: np.ndarray, episode_ends: np.ndarray) -> np.ndarray:
    """Score (max reward) of each recorded episode, recomputed from its states."""
    return episode_maxima(geometry.reward(states), episode_ends)
