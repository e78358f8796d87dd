"""Triangle Drawing: the paper's fourth vision task, on our own canvas (the paper publishes no simulator).

Push-T's PD-controlled agent (``gpc.tasks.planar``) is a pen, always down, on the 512 px canvas; every seed draws a
target triangle, shown faintly, and the pen starts on one of its vertices. Nothing is pushed: the scene's state is
the ink drawn so far, summarised in the ``state`` vector (``sim.DrawSim.state``: the pen, the triangle, each outline
bin's inked share and the ink off the outline) so a state world model must carry the whole stroke forward. The reward
is the F1 of the ink against the outline widened by the pen's width (``geometry``); its planning reward on predicted
states is ``reward.from_layout`` (the ink F1), named ``module:function``. Design: ``docs/tasks.md``.
``TASK`` is all the rest of gpc knows of it; ``gymnasium.make("gpc/Draw-v0", obs_type=...)`` builds the environment.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from gpc.datasets.layout import ActionBox, FrameLayout, RegionLook, StateLayout, TaskLayout
from gpc.tasks.base import Task
from gpc.tasks.draw import geometry, render
from gpc.tasks.draw import record as draw_record
from gpc.tasks.draw.env import MAX_EPISODE_STEPS, DrawEnv
from gpc.tasks.draw.sim import STATE_DIM
from gpc.tasks.draw.sim_model import SIM_KEY, SimulatorModel
from gpc.tasks.planar.draw import AGENT_EDGE, draw_plan
from gpc.tasks.planar.record import ScriptedCollectors
from gpc.tasks.planar.scene import CONTROL_HZ, K_P, K_V, SIM_HZ, WORKSPACE

ENV_ID = "gpc/Draw-v0"
STATE_REWARD = "gpc.tasks.draw.reward:from_layout"  # the F1 on predicted ink summaries, loaded by name

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="gpc.tasks.draw.env:DrawEnv", max_episode_steps=MAX_EPISODE_STEPS)

# State [pen x, y, triangle vertices (6), ink summary (25)]; actions are pen target positions on the 512 px canvas.
# No objects: nothing is placed, so no goal is observed (the triangle is in the state) and the reward is the task's own.
LAYOUT = TaskLayout(
    name="draw",
    # The ink off the outline (the last entry, a share of the band's cells) spans [0, 1] in the policy's normaliser: the
    # expert's tremor leaves at most 0.017 of it, one bad chunk of a policy 0.1 (which a data-fitted span made 10).
    state=StateLayout(dim=STATE_DIM, agent_xy=(0, 1), action_targets=(0, 1), spans=((STATE_DIM - 1, 0.0, 1.0),),
                      relabel="gpc.tasks.draw.reward:rotations",  # a picture shows the corners, not which came first
                      points=tuple(range(2, 8))),
    action=ActionBox(dim=2, low=0.0, high=WORKSPACE),
    objects=(),
    frame=FrameLayout(extent=(0.0, WORKSPACE), marker_size=geometry.PEN_RADIUS, agent_colours=(AGENT_EDGE,),
                      regions=(RegionLook("ink", (render.INK,), tolerance=100.0),)),  # ink: nearer ink than the pen's blue
)

# The paper's Table III row for this task (50 seeds, K=100, learned reward), keyed by gpc's controller labels.
PAPER = {"draw-vision": {"bc": 0.724, "rank K=100": 0.767, "vgps K=100": 0.593, "ladi K=100": 0.680, "dreamer K=100": 0.732}}


COLLECTORS = ScriptedCollectors(expert="gpc.tasks.draw.expert:DrawExpert", explore="gpc.tasks.draw.explore:ExplorePolicy",
                                recorder="gpc.tasks.draw.record")
scripted_policy = COLLECTORS.policy  # the privileged controller behind `gpc collect --task draw` and `--explore`


def env_params(goal: str, max_steps: int) -> dict[str, Any]:
    return {"id": ENV_ID, "goal": "triangle (per seed)", "sim_hz": SIM_HZ, "control_hz": CONTROL_HZ, "k_p": K_P, "k_v": K_V,
            "pen_radius": geometry.PEN_RADIUS, "ink_cell": geometry.CELL, "bins_per_edge": geometry.N_BINS,
            "success_f1": geometry.SUCCESS_F1, "render_size": 96, "max_steps": max_steps}


def record_keys(images: bool, goal: str) -> list[str]:
    return sorted(["action", "n_contacts", "state"] + (["img"] if images else []))


def render_state(state: np.ndarray, goal: np.ndarray | None = None, size: int = 96) -> np.ndarray:
    """A (predicted) state drawn as the camera would show it (ink shaded per outline bin; see ``render.draw_state``)."""
    return render.draw_state(state, goal, size)


def make_env(goal: str) -> DrawEnv:
    return DrawEnv(obs_type="state")


def stored_scores(arrays: Mapping[str, np.ndarray], ends: np.ndarray) -> np.ndarray:
    """Each stored episode's score, from its states' ink summaries."""
    return draw_record.episode_scores(arrays["state"], ends)


TASK = Task(
    layout=LAYOUT,
    description="draw the faint triangle's outline with the pen, every edge once, without ink off the outline",
    goal_modes=("fixed",),  # a triangle every seed draws, part of the state
    make_env=make_env,
    observe=draw_record.observe,  # type: ignore[arg-type]
    record_keys=record_keys,
    record=COLLECTORS.record,
    collector_params=COLLECTORS.params,
    env_params=env_params,
    simulator=SimulatorModel,
    sim_key=SIM_KEY,
    render_state=render_state,
    episode_scores=stored_scores,
    max_episode_steps=MAX_EPISODE_STEPS,
    succeeded=geometry.is_success,  # the score is the best F1; success is an F1 above 0.9
    state_reward=STATE_REWARD,
    info_metrics=("coverage", "off_outline"),
    draw_plan=draw_plan,
    row_shapes={"n_contacts": (1,)},
    references=PAPER,
    fps=CONTROL_HZ,
)

__all__ = ["ENV_ID", "LAYOUT", "MAX_EPISODE_STEPS", "TASK", "DrawEnv"]
