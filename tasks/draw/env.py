"""Gymnasium environment for Triangle Drawing: ``gymnasium.make("gpc/Draw-v0", obs_type="state")``.

``obs_type`` is ``state`` or ``pixels`` (96x96 RGB uint8, the target faint, the ink dark, the pen a ring), or
``state+pixels`` (a dict). ``state`` is the 33-d vector of ``DrawSim.state``: the pen, the triangle's vertices and
the ink summary. The pen is PD-controlled (Push-T's agent: an action is a target position) and always down.

Why: a PD pen has the inertia the other tasks' agent has, so a policy and a world model meet the same control
problem, and a lagging pen has to be steered (a kinematic pen would make every chunk's stroke its action polyline).
Always down, because a pen-up entry would add an action dimension the other tasks lack and a mode a world model must
infer from the ink; the pen instead starts on the outline, at a vertex the seed draws, so it leaves no stray ink
before the first stroke and an expert can draw the whole outline in one stroke.

``reset(options={"reset_to_state": vector})`` lands exactly on a ``DrawSim.vector()`` (pen, velocity, triangle,
ink), or on ``[pen x, y, vertices (6)]`` with a fresh canvas (the pen's disc inked): the state's ink summary does not
say where ink lies, so a state alone cannot be restored.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from gpc.tasks.draw import geometry
from gpc.tasks.draw.render import draw_scene
from gpc.tasks.draw.sim import SIM_DIM, STATE_DIM, DrawSim
from gpc.tasks.planar.scene import WORKSPACE, ObsConfig, episode_seed, observation_space

MAX_EPISODE_STEPS = 300
OBS_PARTS = ("state", "pixels")


def initial_scene(seed: int) -> tuple[np.ndarray, int]:
    """The triangle ``(3, 2)`` and the vertex the pen starts on, drawn for ``seed`` from one ``RandomState(seed)``."""
    rs = np.random.RandomState(seed=seed)
    vertices = geometry.draw_triangle(rs)
    return vertices, int(rs.randint(3))


class DrawEnv(gym.Env):
    """Draw the seed's triangle with an always-down pen that tracks a target position."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, obs_type: str = "state", render_size: int = 96, render_mode: str | None = "rgb_array") -> None:
        self.config = ObsConfig(obs_type=obs_type, render_size=render_size)
        if any(p not in OBS_PARTS for p in self.config.obs_parts):
            raise ValueError(f"obs_type {obs_type!r}: a drawing observes state, pixels or state+pixels")
        self.render_mode = render_mode
        self.sim = DrawSim()
        self.start_vertex = 0
        self.action_space = spaces.Box(0.0, WORKSPACE, shape=(2,), dtype=np.float64)
        self.observation_space = observation_space(self.config.obs_parts, self.config.render_size, {"state": STATE_DIM})

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = options or {}
        seed = self.seed_value = episode_seed(self, seed)
        vertices, self.start_vertex = initial_scene(seed)
        self.sim = DrawSim(vertices)
        if "reset_to_state" in options:
            self._land(np.asarray(options["reset_to_state"], dtype=np.float64))
        else:
            self.sim.place_pen(vertices[self.start_vertex])
        return self._obs(), self._info()

    def _land(self, target: np.ndarray) -> None:
        if target.shape == (SIM_DIM,):
            self.sim.restore(target)
        elif target.shape == (8,):
            self.sim.set_triangle(target[2:8])
            self.sim.place_pen(target[:2])
        else:
            raise ValueError(f"reset_to_state: give a scene vector ({SIM_DIM}) or [pen x, y, vertices] (8), got shape {target.shape}")

    def step(self, action: np.ndarray):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (2,) or not np.all(np.isfinite(action)):
            raise ValueError(f"action must be 2 finite numbers (target x, y in px), got {action!r}")
        self.sim.step(np.clip(action, 0.0, WORKSPACE))
        info = self._info()
        return self._obs(), info["f1"], bool(info["is_success"]), False, info

    def render(self) -> np.ndarray:
        return self.frame(self.config.render_size)

    def frame(self, size: int) -> np.ndarray:
        """The canvas drawn at ``size`` px (videos use a larger size than observations)."""
        return draw_scene(self.sim.vertices, self.sim.ink, self.sim.pen(), size)

    # ------------------------------------------------------------------ helpers
    def _obs(self):
        out = {p: self.render() if p == "pixels" else self.sim.state() for p in self.config.obs_parts}
        return out[self.config.obs_parts[0]] if len(out) == 1 else out

    def _info(self) -> dict[str, Any]:
        """``n_contacts`` is 0 (nothing is touched: the recording loop's contact count has nothing to count)."""
        f1 = self.sim.f1()
        recall = float(self.sim.bin_ink.sum() / self.sim.band.size)
        return {"f1": f1, "coverage": recall, "off_outline": float(self.sim.off_ink / self.sim.band.size),
                "is_success": bool(geometry.is_success(f1)), "n_contacts": 0, "state": self.sim.state()}
