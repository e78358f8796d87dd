"""Gymnasium environment for Cube & Sphere Swapping: ``gymnasium.make("gpc/Swap-v0", obs_type="state")``.

``obs_type`` is ``state``, ``keypoints`` or ``pixels`` (96x96 RGB uint8), or a ``+``-joined combination (a dict),
as Push-T's. The targets differ per seed, so the vector observations carry them: ``state`` is the 7-d state then the
4-d goal (11); ``keypoints`` the 6 keypoints (``geometry.keypoints``), the agent, then the goal (18). The pixels draw
the targets as outlines. ``reset(options={"reset_to_state": state})`` lands exactly on a 7-d state, its targets the
seed's (or ``options["goal"]``).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from gpc.tasks.planar.scene import AGENT_RADIUS, WORKSPACE, ObsConfig, episode_seed, observation_space
from gpc.tasks.swap import geometry
from gpc.tasks.swap.render import draw_state
from gpc.tasks.swap.sim import SwapSim

MAX_EPISODE_STEPS = 400
START_LOW, START_HIGH = 100.0, 412.0  # objects' start centres: room for the agent between each and the walls
MIN_APART = 140.0  # objects' start centres at least this far apart (px): room for the agent between them
AGENT_CLEARANCE = 5.0  # the agent starts at least this far (px) from both objects


SwapConfig = ObsConfig  # what a swap environment observes (the goal is the seed's)


def initial_scene(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The start state (7) and the goal (4: cube target, sphere target) drawn for ``seed``.

    Both objects' centres lie in [100, 412]^2 (each can be pushed from every side), at least ``MIN_APART`` apart;
    the cube's angle is uniform; the agent starts anywhere inside the walls clear of both. Draws are redrawn until
    they fit, from one ``RandomState(seed)``.
    """
    rs = np.random.RandomState(seed=seed)
    while True:
        cube, sphere = rs.uniform(START_LOW, START_HIGH, 2), rs.uniform(START_LOW, START_HIGH, 2)
        if np.linalg.norm(cube - sphere) >= MIN_APART:
            break
    angle = rs.uniform(-np.pi, np.pi)
    half_diagonal = geometry.CUBE_SIDE / np.sqrt(2)
    while True:
        agent = rs.uniform(40.0, WORKSPACE - 40.0, 2)
        if (np.linalg.norm(agent - cube) >= half_diagonal + AGENT_RADIUS + AGENT_CLEARANCE
                and np.linalg.norm(agent - sphere) >= geometry.SPHERE_RADIUS + AGENT_RADIUS + AGENT_CLEARANCE):
            break
    state = np.array([agent[0], agent[1], cube[0], cube[1], angle, sphere[0], sphere[1]])
    return state, np.concatenate([sphere, cube])


def vector_obs(state: np.ndarray, goal: np.ndarray, kind: str) -> np.ndarray:
    """``state`` (11) or ``keypoints`` (18) observation from 7-d states ``(..., 7)`` and goals ``(..., 4)``."""
    state = np.asarray(state, dtype=np.float64)
    goal = np.broadcast_to(np.asarray(goal, dtype=np.float64), state.shape[:-1] + (4,))
    if kind == "state":
        return np.concatenate([state, goal], axis=-1)
    kps = geometry.keypoints(state).reshape(state.shape[:-1] + (2 * geometry.N_KEYPOINTS,))
    return np.concatenate([kps, state[..., :2], goal], axis=-1)


class SwapEnv(gym.Env):
    """Swap a cube and a sphere with a disc that tracks a target position."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, obs_type: str = "state", render_size: int = 96, render_mode: str | None = "rgb_array") -> None:
        self.config = SwapConfig(obs_type=obs_type, render_size=render_size)
        self.render_mode = render_mode
        self.sim = SwapSim()
        self.goal = initial_scene(0)[1]
        self.action_space = spaces.Box(0.0, WORKSPACE, shape=(2,), dtype=np.float64)
        self.observation_space = observation_space(self.config.obs_parts, self.config.render_size, {"state": 11, "keypoints": 18})

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = options or {}
        seed = self.seed_value = episode_seed(self, seed)
        start, goal = initial_scene(seed)
        self.goal = np.asarray(options.get("goal", goal), dtype=np.float64).copy()
        if self.goal.shape != (4,):
            raise ValueError(f"goal must be 4 numbers (cube target x, y, sphere target x, y), got {self.goal!r}")
        self.sim = SwapSim()  # a fresh scene: no contacts cached from an earlier episode
        self.sim.set_state(np.asarray(options.get("reset_to_state", start), dtype=np.float64))
        return self._obs(), self._info(np.zeros(3, dtype=int))

    def step(self, action: np.ndarray):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (2,) or not np.all(np.isfinite(action)):
            raise ValueError(f"action must be 2 finite numbers (target x, y in px), got {action!r}")
        contacts = self.sim.step(action)
        info = self._info(contacts)
        reward = float(geometry.reward_from_coverages(info["coverages"]))
        return self._obs(), reward, bool(info["is_success"]), False, info

    def render(self) -> np.ndarray:
        return self.frame(self.config.render_size)

    def frame(self, size: int) -> np.ndarray:
        """The scene drawn at ``size`` px (videos use a larger size than observations)."""
        return draw_state(self.sim.state(), self.goal, size)

    # ------------------------------------------------------------------ helpers
    def _obs(self):
        state = self.sim.state()
        out = {p: self.render() if p == "pixels" else vector_obs(state, self.goal, p) for p in self.config.obs_parts}
        return out[self.config.obs_parts[0]] if len(out) == 1 else out

    def _info(self, contacts: np.ndarray) -> dict[str, Any]:
        """``n_contacts``: contacts per tick of the step, agent-object and object-object together (object-wall ones
        not counted); ``contacts``: the three counts apart (agent-cube, agent-sphere, cube-sphere)."""
        state = self.sim.state()
        cov = geometry.coverages(state, self.goal)
        return {
            "coverage": float(cov.mean()),
            "coverages": cov,
            "is_success": bool(geometry.is_success(cov)),
            "n_contacts": int(contacts.sum()),
            "contacts": contacts,
            "state": state,
            "goal": self.goal.copy(),
        }
