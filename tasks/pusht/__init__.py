"""Push-T: Diffusion Policy's planar pushing task (simulator, renderer, expert, exploration).

The functions below are the task interface that collection and data inspection use.
"""

from __future__ import annotations

from dataclasses import asdict

import gymnasium as gym
import numpy as np

from tasks.pusht import geometry
from tasks.pusht.env import GOAL_MODES, MAX_EPISODE_STEPS, PushTEnv
from tasks.pusht.render import draw_futures, draw_plan, draw_state as render_state
from tasks.pusht.record import EpisodeStats, RecordConfig, ScriptedPolicy, episode_scores, observe, record_episode
from tasks.pusht.sim import CONTROL_HZ, K_P, K_V, SIM_HZ
from tasks.pusht.sim_model import SIM_KEY, SimulatorModel

ENV_ID = "gpc/PushT-v0"

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="tasks.pusht.env:PushTEnv", max_episode_steps=MAX_EPISODE_STEPS)


def scripted_policy(kind: str) -> ScriptedPolicy:
    """The privileged controller behind ``gpc collect`` (``expert``) and ``--explore``."""
    if kind == "expert":
        from tasks.pusht.expert import PushTExpert

        return PushTExpert()
    if kind == "explore":
        from tasks.pusht.explore import ExploreConfig, ExplorePolicy

        return ExplorePolicy(ExploreConfig())
    raise ValueError(f"collector {kind!r}: use expert or explore")


def collector_params(kind: str, max_steps: int) -> dict:
    policy = scripted_policy(kind)
    config = getattr(policy, "config", None)
    return {
        "policy": type(policy).__name__,
        "config": asdict(config) if config is not None else {},
        "stop_on_success": kind == "expert",
        "max_steps": max_steps,
    }


def record(kind: str, seed: int, goal: str, images: bool, max_steps: int) -> tuple[dict[str, np.ndarray], EpisodeStats]:
    config = RecordConfig(max_steps=max_steps, stop_on_success=kind == "expert", images=images, goal=goal)
    return record_episode(scripted_policy(kind), seed, config)


def env_params(goal: str, max_steps: int) -> dict:
    return {
        "id": ENV_ID, "goal": goal, "sim_hz": SIM_HZ, "control_hz": CONTROL_HZ, "k_p": K_P, "k_v": K_V,
        "goal_pose": geometry.GOAL_POSE.tolist() if goal == "fixed" else "per-seed", "render_size": 96,
        "max_steps": max_steps,
    }


def record_keys(images: bool, goal: str) -> list[str]:
    keys = ["action", "keypoint", "n_contacts", "state"] + (["img"] if images else [])
    return sorted(keys + (["goal", "goal_keypoint"] if goal == "random" else []))


def pose_coverage(states: np.ndarray, bins: tuple[int, int, int] = (16, 16, 12)) -> float:
    """Fraction of a (block x, block y, block angle) grid that the states visit."""
    return len(geometry.pose_cells(states, bins)) / float(np.prod(bins))


ACTION_LOW, ACTION_HIGH = 0.0, float(geometry.WORKSPACE)  # the action box (px targets)
REWARD_VERTICES = geometry.TEE_BOXES.reshape(-1, 2)  # the T's corners: what the registration reward compares
DEFAULT_GOAL = geometry.GOAL_POSE
TASK_DESCRIPTION = "push the grey T-shaped block so that it covers the green T-shaped goal exactly"


def render_future(state: np.ndarray, goal: np.ndarray | None = None, size: int = 96) -> np.ndarray:
    """A predicted state drawn as the camera would show it (the goal drawn too), for a VLM to judge."""
    return render_state(state, DEFAULT_GOAL if goal is None else np.asarray(goal, dtype=np.float64), size)


__all__ = [
    "ACTION_HIGH", "ACTION_LOW", "DEFAULT_GOAL", "ENV_ID", "GOAL_MODES", "REWARD_VERTICES", "SIM_KEY", "SimulatorModel", "TASK_DESCRIPTION", "EpisodeStats", "PushTEnv", "RecordConfig", "collector_params", "draw_futures", "draw_plan",
    "env_params", "episode_scores", "observe", "pose_coverage", "record", "record_keys", "render_future", "render_state",
    "scripted_policy",
]
