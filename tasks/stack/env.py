"""Gymnasium environment for Block Stacking: ``gymnasium.make("gpc/Stack-v0", obs_type="state")``.

``obs_type`` is ``state`` (18: ``scene.StackSim.state``), ``pixels`` (96x96 RGB uint8 from the fixed camera, drawn by
``render``) or ``state+pixels`` (a dict). An action is ``[x, y, z, opening]`` (m): the gripper's target, each entry
clipped to its range (``scene.ACTION_LOW``, ``ACTION_HIGH``). ``reset(options={"reset_to_state": state})`` lands
exactly on an 18-d state, everything at rest. A step that leaves the simulation untrustworthy (NaN, interpenetration)
truncates the episode (``info["unstable"]`` says why); its score so far stands.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from gpc.tasks.planar.scene import episode_seed, observation_space
from gpc.tasks.stack import geometry
from gpc.tasks.stack.render import draw_state
from gpc.tasks.stack.scene import ACTION_HIGH, ACTION_LOW, CUBE_SIDE, MAX_OPENING, STATE_DIM, StackSim

MAX_EPISODE_STEPS = 300
START_RANGE = 0.12  # cube centres start in [-0.12, 0.12]^2 on the table
MIN_APART = 0.10  # and at least this far apart: room for the fingers between them, and a reward near 0
MAX_YAW = np.radians(25.0)  # a start yaw the closing jaws square up (near 45 degrees they pinch two edges)
OBS_PARTS = ("state", "pixels")


@dataclass(frozen=True)
class StackConfig:
    """What a stacking environment observes: ``state``, ``pixels`` or ``state+pixels``."""

    obs_type: str = "state"
    render_size: int = 96

    def __post_init__(self) -> None:
        parts = self.obs_type.split("+")
        if any(p not in OBS_PARTS for p in parts) or len(set(parts)) != len(parts):
            raise ValueError(f"obs_type {self.obs_type!r}: use state, pixels or state+pixels")
        if self.render_size < 8:
            raise ValueError(f"render_size {self.render_size}: must be at least 8")

    @property
    def obs_parts(self) -> tuple[str, ...]:
        return tuple(self.obs_type.split("+"))


def yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def initial_scene(seed: int) -> np.ndarray:
    """The 18-d start state drawn for ``seed``: both cubes flat on the table, centres in [-0.12, 0.12]^2 at least
    ``MIN_APART`` apart, yaws uniform in [-25, 25] degrees; the gripper open, anywhere in [-0.15, 0.15]^2 at a height
    of 10 to 18 cm. Draws are redrawn until they fit, from one ``RandomState(seed)``."""
    rs = np.random.RandomState(seed=seed)
    while True:
        red, blue = rs.uniform(-START_RANGE, START_RANGE, 2), rs.uniform(-START_RANGE, START_RANGE, 2)
        if np.linalg.norm(red - blue) >= MIN_APART:
            break
    yaws = rs.uniform(-MAX_YAW, MAX_YAW, 2)
    gripper = np.concatenate([rs.uniform(-0.15, 0.15, 2), rs.uniform(0.10, 0.18, 1), [MAX_OPENING]])
    cubes = [np.concatenate([xy, [CUBE_SIDE / 2], yaw_quat(yaw)]) for xy, yaw in zip((red, blue), yaws)]
    return np.concatenate([gripper, *cubes])


def check_action(action: np.ndarray) -> np.ndarray:
    action = np.asarray(action, dtype=np.float64)
    if action.shape != (4,) or not np.all(np.isfinite(action)):
        raise ValueError(f"action must be 4 finite numbers (gripper target x, y, z and opening, in m), got {action!r}")
    return action


class StackEnv(gym.Env):
    """Put the red cube on the blue one with a floating parallel-jaw gripper."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, obs_type: str = "state", render_size: int = 96, render_mode: str | None = "rgb_array") -> None:
        self.config = StackConfig(obs_type=obs_type, render_size=render_size)
        self.render_mode = render_mode
        self.sim = StackSim()
        self.settled = 0  # steps in a row stacked, released and at rest
        self.action_space = spaces.Box(ACTION_LOW, ACTION_HIGH, dtype=np.float64)
        self.observation_space = observation_space(self.config.obs_parts, self.config.render_size, {"state": STATE_DIM})

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = options or {}
        seed = self.seed_value = episode_seed(self, seed)
        self.sim.set_state(np.asarray(options.get("reset_to_state", initial_scene(seed)), dtype=np.float64))
        self.settled = 0
        return self._obs(), self._info(np.zeros(3, dtype=int))

    def step(self, action: np.ndarray):
        contacts = self.sim.step(check_action(action))
        unstable = self.sim.unstable()
        state = self.sim.state()
        resting = bool(np.all(self.sim.cube_speeds() < geometry.SETTLED_SPEED))
        done_right = bool(geometry.stacked(state)) and bool(geometry.released(state)) and resting
        self.settled = self.settled + 1 if done_right and unstable is None else 0
        info = self._info(contacts, unstable)
        reward = 0.0 if unstable else float(geometry.reward(state))
        return self._obs(), reward, bool(info["is_success"]), unstable is not None, info

    def render(self) -> np.ndarray:
        return self.frame(self.config.render_size)

    def frame(self, size: int) -> np.ndarray:
        """The scene drawn at ``size`` px (videos use a larger size than observations)."""
        return draw_state(self.sim.state(), size)

    # ------------------------------------------------------------------ helpers
    def _obs(self):
        out = {p: self.render() if p == "pixels" else self.sim.state() for p in self.config.obs_parts}
        return out[self.config.obs_parts[0]] if len(out) == 1 else out

    def _info(self, contacts: np.ndarray, unstable: str | None = None) -> dict[str, Any]:
        """``n_contacts``: how many of the pairs gripper-red, gripper-blue, red-blue touched during the step;
        ``contacts``: the physics steps each touched."""
        state = self.sim.state()
        out = {"distance": float(geometry.distance(state)), "is_success": self.settled >= geometry.SUCCESS_STEPS,
               "n_contacts": int(np.count_nonzero(contacts)), "contacts": contacts, "state": state}
        if unstable:
            out["unstable"] = unstable
        return out
