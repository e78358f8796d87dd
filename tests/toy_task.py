"""A second task, defined only through ``gpc.tasks.base.Task``: a point that must reach a goal.

The agent is a point in a 100 x 100 box; an action is a target position it moves towards by
at most ``SPEED`` per step. The object the reward places is the agent itself, so the
registration reward is the negative distance to the goal. It exists to show that collection,
training and every planner run on a task that ``gpc.models`` has never heard of.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np
import torch

from gpc.datasets.layout import ActionBox, FrameLayout, ObjectLayout, StateLayout, TaskLayout
from gpc.tasks.base import EpisodeStats, Task

SIZE, SPEED, GOAL, SUCCESS = 100.0, 3.0, (70.0, 30.0), 3.0
LAYOUT = TaskLayout(
    name="reach",
    state=StateLayout(dim=2, agent_xy=(0, 1), action_targets=(0, 1)),
    action=ActionBox(dim=2, low=0.0, high=SIZE),
    objects=(ObjectLayout(name="point", pose=(0, 1), vertices=((0.0, 0.0),), goal=GOAL, size=10.0),),
    frame=FrameLayout(extent=(0.0, SIZE), marker_size=4.0, agent_colours=((30, 60, 220),)),
)


def move(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """One step towards the target, at most SPEED long, inside the box."""
    step = np.asarray(target, np.float64) - position
    length = float(np.linalg.norm(step))
    if length > SPEED:
        step *= SPEED / length
    return np.clip(position + step, 0.0, SIZE)


def reward_of(position: np.ndarray) -> float:
    return float(max(0.0, 1.0 - np.linalg.norm(position - np.asarray(GOAL)) / 50.0))


class ReachEnv:
    """Gymnasium-style: ``reset(seed=...)`` draws the start, ``step(target)`` moves and scores."""

    def __init__(self, goal: str = "fixed") -> None:
        self.position = np.zeros(2)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        # Starts in the far corner's quarter, at least 13 steps from the goal.
        self.position = np.random.default_rng(seed).uniform((5.0, 55.0), (40.0, 95.0))
        return self.position.copy(), {"distance": self.distance}

    @property
    def distance(self) -> float:
        return float(np.linalg.norm(self.position - np.asarray(GOAL)))

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self.position = move(self.position, action)
        return self.position.copy(), reward_of(self.position), self.distance < SUCCESS, False, {"distance": self.distance}

    def frame(self, size: int) -> np.ndarray:
        return render_state(self.position, size=size)


def render_state(state: np.ndarray, goal: np.ndarray | None = None, size: int = 32) -> np.ndarray:
    canvas = np.full((size, size, 3), 255, np.uint8)
    scale = size / SIZE
    gx, gy = (np.asarray(GOAL if goal is None else goal) * scale).astype(int)
    cv2.circle(canvas, (int(gx), int(gy)), max(1, int(SUCCESS * scale)), (120, 220, 120), -1)
    x, y = (np.asarray(state[:2]) * scale).astype(int)
    cv2.circle(canvas, (int(x), int(y)), max(1, int(4.0 * scale)), (30, 60, 220), -1)
    return canvas


def observe(env: ReachEnv, images: bool = False, sim: bool = False) -> dict[str, np.ndarray]:
    obs = {"state": env.position.astype(np.float32)}
    if images:
        obs["img"] = env.frame(32)
    if sim:
        obs["sim"] = env.position.astype(np.float64)
    return obs


def record(kind: str, seed: int, goal: str, images: bool, max_steps: int) -> tuple[dict[str, np.ndarray], EpisodeStats]:
    """The expert heads for the goal with a little noise and stops there; the explorer wanders to random targets
    (five arguments, as a task written before `gpc collect --dart`: it is refused there)."""
    env, rng = ReachEnv(goal), np.random.default_rng(seed + 7)
    env.reset(seed=seed)
    rows: dict[str, list[np.ndarray]] = {}
    best, success = 0.0, False
    for _ in range(max_steps):
        aim = np.asarray(GOAL) + rng.normal(0.0, 2.0, 2) if kind == "expert" else rng.uniform(0.0, SIZE, 2)
        action = np.clip(aim, 0.0, SIZE)
        for key, value in {**observe(env, images), "action": action}.items():
            rows.setdefault(key, []).append(value)
        _, reward, done, _, _ = env.step(action)
        best, success = max(best, reward), success or done
        if done and kind == "expert":
            break
    data = {k: np.stack(v).astype(np.uint8 if k == "img" else np.float32) for k, v in rows.items()}
    return data, EpisodeStats(seed, len(data["action"]), best, success, 0.0)


class ReachSimulator:
    """The true dynamics as a world model (``gt-sim``): exact replay from the ``sim`` observation."""

    obs_key, n_obs_steps = "sim", 1

    def rollout(self, history: torch.Tensor | np.ndarray, actions: torch.Tensor | np.ndarray) -> torch.Tensor:
        history = np.asarray(torch.as_tensor(history).detach().cpu(), np.float64)
        actions = np.asarray(torch.as_tensor(actions).detach().cpu(), np.float64)
        if history.ndim == 2:
            history = np.broadcast_to(history, (actions.shape[0],) + history.shape)
        out = np.empty(actions.shape, np.float64)
        for k in range(actions.shape[0]):
            position = history[k, -1]
            for t, action in enumerate(actions[k]):
                position = out[k, t] = move(position, action)
        return torch.as_tensor(out, dtype=torch.float32)


def episode_scores(arrays: Mapping[str, np.ndarray], episode_ends: np.ndarray) -> np.ndarray:
    states = arrays["state"]
    starts = np.concatenate([[0], episode_ends[:-1]]).astype(int)
    return np.array([max(reward_of(s) for s in states[a:b]) for a, b in zip(starts, episode_ends.astype(int))])


def record_keys(images: bool, goal: str) -> list[str]:
    return sorted(["action", "state"] + (["img"] if images else []))


def collector_params(kind: str, max_steps: int) -> dict[str, Any]:
    return {"kind": kind, "max_steps": max_steps}


def env_params(goal: str, max_steps: int) -> dict[str, Any]:
    return {"id": "toy/Reach-v0", "goal": goal, "max_steps": max_steps}


REACH = Task(
    layout=LAYOUT,
    description="move the blue dot onto the green disc",
    goal_modes=("fixed",),
    make_env=ReachEnv,
    observe=observe,  # type: ignore[arg-type]
    record_keys=record_keys,
    record=record,
    collector_params=collector_params,
    env_params=env_params,
    simulator=ReachSimulator,
    sim_key="sim",
    render_state=render_state,
    episode_scores=episode_scores,
    max_episode_steps=60,
)
