"""Recording swap episodes in the store layout Push-T's use (the loop is ``gpc.tasks.planar.record``'s).

Each step stores what was observed before acting: ``state`` (7), ``goal`` (4: the targets, every step, since they
differ per seed), ``keypoint`` (6x2: ``geometry.keypoints``), ``goal_keypoint`` (2x2: the cube's and the
sphere's targets as points, which a keypoint policy reads; the cube's orientation is no part of the goal), ``img``
(96x96x3 uint8), the ``action``, and ``n_contacts`` (1: contacts per tick, agent-object and object-object together)
of the step that led to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpc.tasks.base import EpisodeStats
from gpc.tasks.planar import record as planar_record
from gpc.tasks.planar.record import episode_maxima, record_from_reset, with_extras
from gpc.tasks.swap import geometry
from gpc.tasks.swap.env import MAX_EPISODE_STEPS, SwapEnv
from gpc.tasks.swap.sim import SwapSim

ScriptedPolicy = planar_record.ScriptedPolicy[SwapSim]


@dataclass(frozen=True)
class RecordConfig(planar_record.RecordConfig):
    """How long episodes run (this task's length by default) and what is stored."""

    max_steps: int = MAX_EPISODE_STEPS


def observe(env: SwapEnv, images: bool = True, sim: bool = False) -> dict[str, np.ndarray]:
    """One step's observation in the data layout; ``sim`` adds the full simulator state (16, never recorded) that the
    ground-truth world model restores from."""
    state = env.sim.state()
    obs = {"state": state.astype(np.float32), "goal": env.goal.astype(np.float32),
           "keypoint": geometry.keypoints(state).astype(np.float32),
           "goal_keypoint": env.goal.reshape(2, 2).astype(np.float32)}  # the targets as points: what a keypoint policy reads
    return with_extras(obs, env, images, sim)


def record_episode(policy: ScriptedPolicy, seed: int, config: RecordConfig) -> tuple[dict[str, np.ndarray], EpisodeStats]:
    """Run ``policy`` from the env's reset for ``seed``; return the arrays and their summary (``contact_fraction``:
    the share of steps with any agent-object or object-object contact)."""
    env = SwapEnv(obs_type="state")
    return record_from_reset(env, policy, lambda: policy.act(env.sim, env.goal), lambda: observe(env, config.images), seed,
                             config)


def episode_scores(states: np.ndarray, goals: np.ndarray, episode_ends: np.ndarray) -> np.ndarray:
    """Score (max reward) of each recorded episode, recomputed from its states and goals."""
    return episode_maxima(geometry.reward_from_coverages(geometry.coverages(states, goals)), episode_ends)
