"""Recording Push-T episodes in Diffusion Policy's data layout.

Each step stores what was observed before acting and the action taken, as Diffusion
Policy's recorder does: ``state``, ``keypoint`` (9x2), ``img`` (96x96x3, uint8 here),
``action``, and ``n_contacts`` of the step that led to the observation. With a random
goal the per-step ``goal`` pose is stored too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpc.tasks.base import EpisodeStats
from gpc.tasks.planar import record as planar_record
from gpc.tasks.planar.record import episode_maxima, record_from_reset
from gpc.tasks.pusht import geometry
from gpc.tasks.pusht.env import MAX_EPISODE_STEPS, PushTEnv
from gpc.tasks.pusht.sim import PushTSim
from gpc.tasks.pusht.sim_model import SIM_KEY, sim_vector

ScriptedPolicy = planar_record.ScriptedPolicy[PushTSim]


@dataclass(frozen=True)
class RecordConfig(planar_record.RecordConfig):
    """How long episodes run (this task's length by default), what is stored, and the goal mode."""

    max_steps: int = MAX_EPISODE_STEPS
    goal: str = "fixed"

def observe(env: PushTEnv, images: bool = True, sim: bool = False) -> dict[str, np.ndarray]:
    """One step's observation in the data layout (``state``, ``keypoint``, ``img``; with a random
    goal also ``goal`` (its pose) and ``goal_keypoint`` (its keypoints, laid out like ``keypoint``)).

    Recording and closed-loop evaluation both use it, so a policy sees at test time exactly
    the keys, shapes and dtypes it was trained on. ``sim`` adds the full simulator state
    that the ground-truth world model restores from (never recorded).
    """
    state = env.sim.state()
    obs = {"state": state.astype(np.float32), "keypoint": geometry.block_keypoints(state[2:5]).astype(np.float32)}
    if images:
        obs["img"] = env.render()
    if sim:
        obs[SIM_KEY] = sim_vector(env.sim)
    if env.config.goal == "random":
        obs["goal"] = env.goal_pose.astype(np.float32)
        obs["goal_keypoint"] = geometry.block_keypoints(env.goal_pose).astype(np.float32)
    return obs

def record_episode(policy: ScriptedPolicy, seed: int, config: RecordConfig) -> tuple[dict[str, np.ndarray], EpisodeStats]:
    """Run ``policy`` from the env's reset for ``seed``; return the arrays and their summary."""
    env = PushTEnv(obs_type="state", goal=config.goal)
    return record_from_reset(env, policy, lambda: policy.act(env.sim, env.goal_pose), lambda: observe(env, config.images),
                             seed, config)

def episode_scores(states: np.ndarray, episode_ends: np.ndarray, goal_pose: np.ndarray = geometry.GOAL_POSE) -> np.ndarray:
    """Score (max reward) of each recorded episode, recomputed from its block poses."""
    rewards = np.array([geometry.reward_from_coverage(geometry.coverage(p, goal_pose)) for p in states[:, 2:5]])
    return episode_maxima(rewards, episode_ends)
