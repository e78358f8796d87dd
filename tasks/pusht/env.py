"""Gymnasium environment for Push-T, faithful to Diffusion Policy's (and gym-pusht's).

``gymnasium.make("gpc/PushT-v0", obs_type="state")``; ``obs_type`` is ``state`` (5-d),
``keypoints`` (9 block keypoints then the agent, 20-d, Diffusion Policy's order),
``pixels`` (96x96 RGB uint8) or a ``+``-joined combination, which gives a dict.
With ``goal="random"`` (GPC's variant) each seed also draws a goal pose, appended to the
vector observations (the goal's pose for ``state``, its keypoints for ``keypoints``) and
drawn in the pixels, so a policy can see it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from gpc.tasks.planar.scene import ObsConfig, episode_seed
from gpc.tasks.pusht import geometry
from gpc.tasks.pusht.render import draw_scene
from gpc.tasks.pusht.sim import PushTSim

GOAL_MODES = ("fixed", "random")
MAX_EPISODE_STEPS = 300


@dataclass(frozen=True)
class PushTConfig(ObsConfig):
    """What an environment observes and where its goal lies."""

    goal: str = "fixed"

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.goal not in GOAL_MODES:
            raise ValueError(f"goal {self.goal!r}: use one of {', '.join(GOAL_MODES)}")


def initial_state(seed: int) -> np.ndarray:
    """Diffusion Policy's reset draw for ``seed`` (legacy ``RandomState``)."""
    rs = np.random.RandomState(seed=seed)
    return np.array(
        [rs.randint(50, 450), rs.randint(50, 450), rs.randint(100, 400), rs.randint(100, 400),
         rs.randn() * 2 * np.pi - np.pi],
        dtype=np.float64,
    )


def random_goal(seed: int) -> np.ndarray:
    """GPC's per-seed goal: a pose whose T stays inside the walls, independent of the start draw."""
    rng = np.random.default_rng([seed, 0x60A1])
    return np.array([rng.uniform(150, 362), rng.uniform(150, 362), rng.uniform(-np.pi, np.pi)])


def vector_obs(state: np.ndarray, kind: str, goal_pose: np.ndarray | None = None) -> np.ndarray:
    """``state`` or ``keypoints`` observation from 5-d states ``(..., 5)``; goal appended if given."""
    state = np.asarray(state, dtype=np.float64)
    if kind == "state":
        out = state
        extra = None if goal_pose is None else np.broadcast_to(goal_pose, state.shape[:-1] + (3,))
    else:
        kps = geometry.block_keypoints(state[..., 2:5]).reshape(state.shape[:-1] + (18,))
        out = np.concatenate([kps, state[..., :2]], axis=-1)
        extra = None
        if goal_pose is not None:
            g = geometry.block_keypoints(np.asarray(goal_pose, dtype=np.float64)).reshape(18)
            extra = np.broadcast_to(g, state.shape[:-1] + (18,))
    return out if extra is None else np.concatenate([out, extra], axis=-1)


class PushTEnv(gym.Env):
    """Push a T-shaped block onto a goal pose with a disc that tracks a target position."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, obs_type: str = "state", goal: str = "fixed", render_size: int = 96,
                 render_mode: str | None = "rgb_array") -> None:
        self.config = PushTConfig(obs_type=obs_type, goal=goal, render_size=render_size)
        self.render_mode = render_mode
        self.sim = PushTSim()
        self.goal_pose = geometry.GOAL_POSE.copy()
        self.action_space = spaces.Box(0.0, geometry.WORKSPACE, shape=(2,), dtype=np.float64)
        subspaces = {p: self._space(p) for p in self.config.obs_parts}
        self.observation_space = (
            next(iter(subspaces.values())) if len(subspaces) == 1 else spaces.Dict(subspaces)
        )

    def _space(self, part: str) -> spaces.Space:
        if part == "pixels":
            n = self.config.render_size
            return spaces.Box(0, 255, shape=(n, n, 3), dtype=np.uint8)
        dim = {"state": 5, "keypoints": 20}[part]
        if self.config.goal == "random":
            dim += {"state": 3, "keypoints": 18}[part]
        return spaces.Box(-np.inf, np.inf, shape=(dim,), dtype=np.float64)

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = options or {}
        seed = self.seed_value = episode_seed(self, seed)
        self.goal_pose = np.asarray(
            options.get("goal_pose", random_goal(seed) if self.config.goal == "random" else geometry.GOAL_POSE),
            dtype=np.float64,
        )
        self.sim = PushTSim()  # a fresh scene, as the original builds on every reset
        if "reset_to_state" in options:
            self.sim.set_state(np.asarray(options["reset_to_state"], dtype=np.float64), legacy=False)
        else:
            self.sim.set_state(initial_state(seed), legacy=True)
        cov = geometry.coverage(self.sim.block_pose(), self.goal_pose)
        return self._obs(), self._info(cov, 0)

    def step(self, action: np.ndarray):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (2,) or not np.all(np.isfinite(action)):
            raise ValueError(f"action must be 2 finite numbers (target x, y in px), got {action!r}")
        n_contacts = self.sim.step(action)
        cov = geometry.coverage(self.sim.block_pose(), self.goal_pose)
        reward = geometry.reward_from_coverage(cov)
        terminated = bool(cov > geometry.SUCCESS_COVERAGE)
        return self._obs(), reward, terminated, False, self._info(cov, n_contacts)

    def render(self) -> np.ndarray:
        return self.frame(self.config.render_size)

    def frame(self, size: int) -> np.ndarray:
        """The scene drawn at ``size`` px (videos use a larger size than observations)."""
        return draw_scene(self.sim.state()[:2], self.sim.block_pose(), self.goal_pose, size)

    # ------------------------------------------------------------------ helpers
    def _obs(self):
        state = self.sim.state()
        goal = self.goal_pose if self.config.goal == "random" else None
        out = {}
        for part in self.config.obs_parts:
            out[part] = self.render() if part == "pixels" else vector_obs(state, part, goal)
        return out[self.config.obs_parts[0]] if len(out) == 1 else out

    def _info(self, cov: float, n_contacts: int) -> dict[str, Any]:
        return {
            "coverage": cov,
            "is_success": cov > geometry.SUCCESS_COVERAGE,
            "n_contacts": n_contacts,
            "state": self.sim.state(),
            "block_pose": self.sim.block_pose(),
            "goal_pose": self.goal_pose.copy(),
        }
