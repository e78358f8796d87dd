"""Recording drawing episodes in the store layout the other tasks use (the loop is ``gpc.tasks.planar.record``'s).

Each step stores what was observed before acting: ``state`` (33: the pen, the triangle, the ink summary), ``img``
(96x96x3 uint8), the ``action``, and ``n_contacts`` (always 0: nothing is touched; kept so every store has it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpc.tasks.base import EpisodeStats
from gpc.tasks.draw import geometry
from gpc.tasks.draw.env import MAX_EPISODE_STEPS, DrawEnv
from gpc.tasks.draw.sim import DrawSim
from gpc.tasks.planar import record as planar_record
from gpc.tasks.planar.record import episode_maxima, record_from_reset, with_extras

ScriptedPolicy = planar_record.ScriptedPolicy[DrawSim]


@dataclass(frozen=True)
class RecordConfig(planar_record.RecordConfig):
    """How long episodes run (this task's length by default) and what is stored."""

    max_steps: int = MAX_EPISODE_STEPS


def observe(env: DrawEnv, images: bool = True, sim: bool = False) -> dict[str, np.ndarray]:
    """One step's observation in the data layout; ``sim`` adds the full scene (pen, triangle, ink grid; never
    recorded) that the ground-truth world model restores from."""
    return with_extras({"state": env.sim.state().astype(np.float32)}, env, images, sim)


def record_episode(policy: ScriptedPolicy, seed: int, config: RecordConfig) -> tuple[dict[str, np.ndarray], EpisodeStats]:
    """Run ``policy`` from the env's reset for ``seed``; return the arrays and their summary."""
    env = DrawEnv(obs_type="state")
    return record_from_reset(env, policy, lambda: policy.act(env.sim, np.zeros(0)), lambda: observe(env, config.images),
                             seed, config)


def episode_scores(states: np.ndarray, episode_ends: np.ndarray) -> np.ndarray:
    """Score (max reward) of each recorded episode, from its states' ink summaries.

    A store holds what was observed before each action, so an episode's last stroke is not in it: the score of a
    recorded episode can fall short of the one its recording reported by that stroke.
    """
    return episode_maxima(geometry.f1_from_summary(np.asarray(states, dtype=np.float64)[:, 8:]), episode_ends)
