"""Cube & Sphere Swapping: the paper's second vision task, on our own planar simulator (the paper publishes none).

Push-T's workspace, agent and physics (``gpc.tasks.planar``), a square cube and a round sphere; the goal is to swap
their places. ``TASK`` is all the rest of gpc knows of it (``gpc.tasks.base.Task``);
``gymnasium.make("gpc/Swap-v0", obs_type=...)`` builds the environment.

The goal is drawn per seed (each object's target is where the other started), so every observation carries it
(``goal``: cube target x, y, then sphere target x, y) and the layout gives no default goal. The cube's orientation
does not count: the goal compares the objects' positions (``docs/tasks.md``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from gpc.datasets.errors import DataError
from gpc.datasets.layout import ActionBox, FrameLayout, ObjectLayout, ObjectLook, StateLayout, TaskLayout
from gpc.tasks.base import Task
from gpc.tasks.planar.draw import AGENT_EDGE, AGENT_FILL, draw_plan
from gpc.tasks.planar.record import ScriptedCollectors
from gpc.tasks.planar.scene import AGENT_RADIUS, CONTROL_HZ, K_P, K_V, SIM_HZ, WORKSPACE
from gpc.tasks.swap import geometry, render
from gpc.tasks.swap import record as swap_record
from gpc.tasks.swap.env import AGENT_CLEARANCE, MAX_EPISODE_STEPS, MIN_APART, SwapEnv
from gpc.tasks.swap.sim_model import SIM_KEY, SimulatorModel

ENV_ID = "gpc/Swap-v0"

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="gpc.tasks.swap.env:SwapEnv", max_episode_steps=MAX_EPISODE_STEPS)

# State [agent x, y, cube x, y, cube angle, sphere x, y]; actions are agent target positions in the 512 px workspace.
LAYOUT = TaskLayout(
    name="swap",
    state=StateLayout(dim=7, agent_xy=(0, 1), angle_dims=(4,), action_targets=(0, 1)),
    action=ActionBox(dim=2, low=0.0, high=WORKSPACE),
    objects=(
        ObjectLayout(name="cube", pose=(2, 3), angle=4, size=geometry.CUBE_SIDE,
                     vertices=tuple((float(x), float(y)) for x, y in geometry.CUBE_KEYPOINTS[:4])),
        ObjectLayout(name="sphere", pose=(5, 6), vertices=((0.0, 0.0),), size=2 * geometry.SPHERE_RADIUS),
    ),
    # The readout looks for the fills only, closely (RGB distance 20): the targets are outlines in the edge colours,
    # which a 96 px frame blends towards white, near the fills. A square looks the same turned by 90 degrees; its 4th
    # angular moment reads pi at angle 0 (corners at 45 degrees), hence the offset.
    frame=FrameLayout(extent=(0.0, WORKSPACE), marker_size=AGENT_RADIUS, agent_colours=(AGENT_FILL, AGENT_EDGE),
                      objects=(ObjectLook(colours=(render.CUBE_FILL,), symmetry=4, angle_offset=-math.pi / 4, tolerance=20.0),
                               ObjectLook(colours=(render.SPHERE_FILL,), tolerance=20.0))),
)

# The paper's Table III row for this task (50 seeds, K=100, learned reward), keyed by gpc's controller labels.
PAPER = {"swap-vision": {"bc": 0.680, "rank K=100": 0.730, "vgps K=100": 0.650, "ladi K=100": 0.410, "dreamer K=100": 0.700}}


COLLECTORS = ScriptedCollectors(expert="gpc.tasks.swap.expert:SwapExpert", explore="gpc.tasks.swap.explore:ExplorePolicy",
                                recorder="gpc.tasks.swap.record")
scripted_policy = COLLECTORS.policy  # the privileged controller behind `gpc collect --task swap` and `--explore`


def env_params(goal: str, max_steps: int) -> dict[str, Any]:
    return {
        "id": ENV_ID, "goal": "swap (per seed)", "sim_hz": SIM_HZ, "control_hz": CONTROL_HZ, "k_p": K_P, "k_v": K_V,
        "cube_side": geometry.CUBE_SIDE, "sphere_radius": geometry.SPHERE_RADIUS, "min_apart": MIN_APART,
        "agent_clearance": AGENT_CLEARANCE, "render_size": 96, "max_steps": max_steps,
    }


def record_keys(images: bool, goal: str) -> list[str]:
    return sorted(["action", "goal", "goal_keypoint", "keypoint", "n_contacts", "state"] + (["img"] if images else []))


def render_state(state: np.ndarray, goal: np.ndarray | None = None, size: int = 96) -> np.ndarray:
    """A (predicted) state drawn as the camera would show it, with the targets when the goal is given."""
    return render.draw_state(state, goal, size)


def make_env(goal: str) -> SwapEnv:
    return SwapEnv(obs_type="state")


def stored_scores(arrays: Mapping[str, np.ndarray], ends: np.ndarray) -> np.ndarray:
    """Each stored episode's score, from its states and the goal recorded with them."""
    if "goal" not in arrays:
        raise DataError("a swap store records each step's goal (data/goal); this one has none to score against")
    return swap_record.episode_scores(arrays["state"], arrays["goal"], ends)


TASK = Task(
    layout=LAYOUT,
    description="swap the red square and the green disc: push each onto the outline where the other one started",
    goal_modes=("fixed",),  # the swap: a goal every seed draws, observed as `goal`
    make_env=make_env,
    observe=swap_record.observe,  # type: ignore[arg-type]
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
    state_reward="registration",  # the mean of the two objects' distances to their targets (positions only)
    info_metrics=("coverage",),
    draw_plan=draw_plan,
    row_shapes={"keypoint": (geometry.N_KEYPOINTS, 2), "goal_keypoint": (2, 2), "n_contacts": (1,)},
    references=PAPER,
    fps=CONTROL_HZ,
)

__all__ = ["ENV_ID", "LAYOUT", "MAX_EPISODE_STEPS", "TASK", "SwapEnv"]
