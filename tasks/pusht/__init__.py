"""Push-T: Diffusion Policy's planar pushing task (simulator, renderer, expert, exploration).

``TASK`` is all the rest of gpc knows of it (``gpc.tasks.base.Task``); every constant lives in
this package.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from gpc.datasets.layout import ActionBox, FrameLayout, ObjectLayout, ObjectLook, StateLayout, TaskLayout
from gpc.tasks.base import ActionNoise, EpisodeStats, Task
from gpc.tasks.planar import draw
from gpc.tasks.planar.record import scripted_params
from gpc.tasks.planar.scene import AGENT_RADIUS, CONTROL_HZ, K_P, K_V, SIM_HZ
from gpc.tasks.pusht import geometry, render
from gpc.tasks.pusht.env import GOAL_MODES, MAX_EPISODE_STEPS, PushTEnv
from gpc.tasks.pusht.foreign import FOREIGN_FEATURES, from_lerobot, outline_vertices, to_lerobot
from gpc.tasks.pusht.record import RecordConfig, ScriptedPolicy, episode_scores, observe, record_episode
from gpc.tasks.pusht.sim_model import SIM_KEY, SimulatorModel

ENV_ID = "gpc/PushT-v0"

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="gpc.tasks.pusht.env:PushTEnv", max_episode_steps=MAX_EPISODE_STEPS)

# State [agent x, y, block x, y, block angle]; actions are agent target positions in the 512 px workspace.
LAYOUT = TaskLayout(
    name="pusht",
    state=StateLayout(dim=5, agent_xy=(0, 1), angle_dims=(4,), action_targets=(0, 1)),
    action=ActionBox(dim=2, low=0.0, high=float(geometry.WORKSPACE)),
    objects=(ObjectLayout(name="tee", pose=(2, 3, 4), angle=4,
                          vertices=tuple((float(x), float(y)) for x, y in geometry.TEE_BOXES.reshape(-1, 2)),
                          goal=tuple(float(g) for g in geometry.GOAL_POSE),
                          centroid=(float(geometry.TEE_CENTROID[0]), float(geometry.TEE_CENTROID[1])),
                          size=50.0),),  # about the T's size in px
    # The T's stem runs along its body +y axis, its principal axis: body angle = axis angle - pi / 2.
    frame=FrameLayout(extent=(0.0, float(geometry.WORKSPACE)), marker_size=AGENT_RADIUS,
                      objects=(ObjectLook(colours=(render.BLOCK_FILL, render.BLOCK_EDGE), angle_offset=-math.pi / 2),),
                      agent_colours=(draw.AGENT_FILL, draw.AGENT_EDGE)),
)


# GPC's tables (Qi et al. 2026; 100 seeds, Table III's 50; vision: IoU score), keyed by gpc's controller labels (`gpc compare --paper`).
PAPER = {
    "pusht-vision": {"bc": 0.642, "rank K=50": 0.698, "rank K=100": 0.739, "opt M=25": 0.791, "rank-opt 10x25": 0.882,
                     "vgps K=100": 0.620, "ladi K=100": 0.683, "dreamer K=100": 0.649},  # Table III: 50 seeds
    "pusht-state": {
        "bc": 0.812, "rank K=100": 0.898, "rank K=1000": 0.932, "rank K=5000": 0.934, "opt M=30": 0.886,
        "rank-opt 10x30": 0.912, "rank-opt 20x30": 0.914, "rank-opt 30x20": 0.891, "gt-sim K=100": 0.952,
    },
}


def scripted_policy(kind: str) -> ScriptedPolicy:
    """The privileged controller behind ``gpc collect`` (``expert``) and ``--explore``."""
    if kind == "expert":
        from gpc.tasks.pusht.expert import PushTExpert

        return PushTExpert()
    if kind == "explore":
        from gpc.tasks.pusht.explore import ExploreConfig, ExplorePolicy

        return ExplorePolicy(ExploreConfig())
    raise ValueError(f"collector {kind!r}: use expert or explore")


def collector_params(kind: str, max_steps: int) -> dict[str, Any]:
    return scripted_params(scripted_policy(kind), kind, max_steps)


def record(kind: str, seed: int, goal: str, images: bool, max_steps: int,
           noise: ActionNoise | None = None) -> tuple[dict[str, np.ndarray], EpisodeStats]:
    config = RecordConfig(max_steps=max_steps, stop_on_success=kind == "expert", images=images, goal=goal, noise=noise)
    return record_episode(scripted_policy(kind), seed, config)


def env_params(goal: str, max_steps: int) -> dict[str, Any]:
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


def stored_scores(arrays: Mapping[str, np.ndarray], ends: np.ndarray) -> np.ndarray:
    """Each stored episode's score from its block poses, against its own goal where the store holds one (--goal random)."""
    if "goal" not in arrays:
        return episode_scores(arrays["state"], ends)
    starts = np.concatenate([[0], ends[:-1]]).astype(int)
    return np.array([episode_scores(arrays["state"][a:b], np.array([b - a]), arrays["goal"][a].astype(np.float64))[0]
                     for a, b in zip(starts, np.asarray(ends).astype(int))])


def render_state(state: np.ndarray, goal: np.ndarray | None = None, size: int = 96) -> np.ndarray:
    """A (predicted) state drawn as the camera would show it, the goal drawn too."""
    return render.draw_state(state, geometry.GOAL_POSE if goal is None else np.asarray(goal, dtype=np.float64), size)


def make_env(goal: str) -> PushTEnv:
    return PushTEnv(obs_type="state", goal=goal)


def check_replay(path: Any, episodes: int = 0, frame_stride: int = 10) -> dict[str, Any]:
    from gpc.tasks.pusht.fidelity import check_store

    return check_store(path, episodes, frame_stride)


TASK = Task(
    layout=LAYOUT,
    description="push the grey T-shaped block so that it covers the green T-shaped goal exactly",
    goal_modes=GOAL_MODES,
    make_env=make_env,
    observe=observe,  # type: ignore[arg-type]
    record_keys=record_keys,
    record=record,
    collector_params=collector_params,
    env_params=env_params,
    simulator=SimulatorModel,
    sim_key=SIM_KEY,
    render_state=render_state,
    episode_scores=stored_scores,
    max_episode_steps=MAX_EPISODE_STEPS,
    state_reward="registration",  # the T's mean vertex distance to the goal pose (the paper's registration loss)
    info_metrics=("coverage",),
    draw_plan=render.draw_plan,
    draw_futures=render.draw_futures,
    pose_coverage=pose_coverage,
    check_replay=check_replay,
    row_shapes={"keypoint": (9, 2), "goal_keypoint": (9, 2), "n_contacts": (1,), "vertex": (8, 2)},
    references=PAPER,
    foreign_features=FOREIGN_FEATURES,
    derived={"vertex": outline_vertices},
    to_lerobot=to_lerobot,
    from_lerobot=from_lerobot,
    fps=CONTROL_HZ,
)

__all__ = ["ENV_ID", "LAYOUT", "TASK", "PushTEnv", "SimulatorModel", "geometry", "render"]
