"""Block Stacking: the paper's third vision task, in 3-D on MuJoCo (the paper publishes no simulator).

A table, a red and a blue 4 cm cube and a floating parallel-jaw gripper (``scene``); the goal is the red cube resting
centred on the blue one, the gripper open and clear. ``TASK`` is all the rest of gpc knows of it
(``gpc.tasks.base.Task``); ``gymnasium.make("gpc/Stack-v0", obs_type=...)`` builds the environment.

The layout: an 18-d state (gripper x, y, z, opening; each cube's position and quaternion, ``scene.StackSim.state``),
4-d actions (the gripper's target x, y, z and opening, in metres: every entry a target for the state entry of the
same index). The one object the goal compares is the red cube (x, y); its target moves with the blue cube, so every
step observes it as ``goal`` (the blue cube's x, y) and the layout gives no default. Planners score predicted states
with the task's own reward (``reward.StackReward``: the red cube's 3-D distance to one cube side above the blue one).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from gpc.datasets.layout import ActionBox, FrameLayout, ObjectLayout, StateLayout, TaskLayout
from gpc.tasks.base import Task
from gpc.tasks.planar.record import ScriptedCollectors
from gpc.tasks.stack import geometry, render, scene
from gpc.tasks.stack import record as stack_record
from gpc.tasks.stack.env import MAX_EPISODE_STEPS, MAX_YAW, MIN_APART, START_RANGE, StackEnv
from gpc.tasks.stack.sim_model import SIM_KEY, SimulatorModel

ENV_ID = "gpc/Stack-v0"

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="gpc.tasks.stack.env:StackEnv", max_episode_steps=MAX_EPISODE_STEPS)

_HALF = scene.CUBE_SIDE / 2
LAYOUT = TaskLayout(
    name="stack",
    state=StateLayout(dim=scene.STATE_DIM, agent_xy=(0, 1, 2, 3), action_targets=(0, 1, 2, 3)),
    action=ActionBox(dim=4, low=-0.2, high=0.2),  # holds every entry's range (scene.ACTION_LOW/HIGH); the env clips each
    objects=(ObjectLayout(name="red", pose=(4, 5), size=scene.CUBE_SIDE, height=6,
                          vertices=((-_HALF, -_HALF), (_HALF, -_HALF), (_HALF, _HALF), (-_HALF, _HALF))),),
    frame=FrameLayout(extent=(-0.2, 0.2), marker_size=0.01),  # a perspective camera: no planar extent; for action maps only
    unit="mm", unit_scale=1000.0,  # metres, reported as mm
)

# The paper's Table III row for this task (50 seeds, K=100, learned reward), keyed by gpc's controller labels.
PAPER = {"stack-vision": {"bc": 0.912, "rank K=100": 0.989, "vgps K=100": 0.972, "ladi K=100": 0.933, "dreamer K=100": 0.983}}


COLLECTORS = ScriptedCollectors(expert="gpc.tasks.stack.expert:StackExpert", explore="gpc.tasks.stack.explore:ExplorePolicy",
                                recorder="gpc.tasks.stack.record")
scripted_policy = COLLECTORS.policy  # the privileged controller behind `gpc collect --task stack` and `--explore`


def env_params(goal: str, max_steps: int) -> dict[str, Any]:
    return {
        "id": ENV_ID, "goal": "red on blue", "control_hz": scene.CONTROL_HZ, "timestep": scene.TIMESTEP, "cube_side": scene.CUBE_SIDE,
        "start_range": START_RANGE, "min_apart": MIN_APART, "max_yaw": float(MAX_YAW), "reward_distance": geometry.REWARD_DISTANCE,
        "render_size": 96, "max_steps": max_steps,
    }


def record_keys(images: bool, goal: str) -> list[str]:
    return sorted(["action", "goal", "n_contacts", "state"] + (["img"] if images else []))


def render_state(state: np.ndarray, goal: np.ndarray | None = None, size: int = 96) -> np.ndarray:
    """A (predicted) state drawn as the fixed camera would show it (the goal is the blue cube, drawn anyway)."""
    return render.draw_state(state, size)


def make_env(goal: str) -> StackEnv:
    return StackEnv(obs_type="state")


def stored_scores(arrays: Mapping[str, np.ndarray], ends: np.ndarray) -> np.ndarray:
    """Each stored episode's score, from its states."""
    return stack_record.episode_scores(arrays["state"], ends)


TASK = Task(
    layout=LAYOUT,
    description="stack the red cube on top of the blue cube, centred, then open the gripper and move it clear",
    goal_modes=("fixed",),  # red on blue; its target moves with the blue cube, observed as `goal`
    make_env=make_env,
    observe=stack_record.observe,  # type: ignore[arg-type]
    record_keys=record_keys,
    record=COLLECTORS.record,
    collector_params=COLLECTORS.params,
    env_params=env_params,
    simulator=SimulatorModel,
    sim_key=SIM_KEY,
    render_state=render_state,
    episode_scores=stored_scores,
    max_episode_steps=MAX_EPISODE_STEPS,
    succeeded=None,  # success is not a function of the score (see the env's is_success)
    state_reward="gpc.tasks.stack.reward:stack_reward",
    info_minima=("distance",),  # how close the red cube came to its place
    row_shapes={"n_contacts": (1,)},
    references=PAPER,
    fps=scene.CONTROL_HZ,
)

__all__ = ["ENV_ID", "LAYOUT", "MAX_EPISODE_STEPS", "TASK", "StackEnv"]
