"""The planar scene every pushing task starts from: Diffusion Policy's walls, rates and PD-controlled disc agent.

A task subclasses ``AgentScene``, adds its objects after the walls and the agent (pymunk steps bodies in the order
they were added, so the order is part of a task's physics) and counts the contacts it cares about.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pymunk

WORKSPACE = 512.0
SIM_HZ = 100
CONTROL_HZ = 10
SUBSTEPS = SIM_HZ // CONTROL_HZ
DT = 1.0 / SIM_HZ
K_P, K_V = 100.0, 20.0
AGENT_RADIUS = 15.0
WALLS = (((5, 506), (5, 5)), ((5, 5), (506, 5)), ((506, 5), (506, 506)), ((5, 506), (506, 506)))
WALL_RADIUS = 2.0
# pymunk keeps a contact (and its warm-start impulse) this many ticks after the shapes part (its default).
CONTACT_PERSISTENCE = 3


class AgentScene:
    """A pymunk space without gravity or velocity memory (damping 0: a body stops the tick nothing pushes it),
    the four walls and a kinematic disc that tracks a target position under PD control."""

    def __init__(self) -> None:
        self.space = pymunk.Space()
        self.space.gravity = (0.0, 0.0)
        self.space.damping = 0.0
        for a, b in WALLS:
            self.space.add(pymunk.Segment(self.space.static_body, a, b, WALL_RADIUS))
        self.agent = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        self.agent.position = (256.0, 400.0)
        self.agent_shape = pymunk.Circle(self.agent, AGENT_RADIUS)
        self.space.add(self.agent, self.agent_shape)

    def drive(self, action: np.ndarray, trace: list[tuple[float, float]] | None = None) -> None:
        """Track target ``action`` (px) for one control period: ``SUBSTEPS`` ticks of PD control; ``trace`` (if given)
        receives the agent's position after each tick (a pen inks the path between them)."""
        tx, ty = float(action[0]), float(action[1])
        agent, space = self.agent, self.space
        for _ in range(SUBSTEPS):
            p, v = agent.position, agent.velocity
            ax = K_P * (tx - p.x) + K_V * (0.0 - v.x)
            ay = K_P * (ty - p.y) + K_V * (0.0 - v.y)
            agent.velocity = (v.x + ax * DT, v.y + ay * DT)
            space.step(DT)
            if trace is not None:
                trace.append((agent.position.x, agent.position.y))

    def lapse_contacts(self, bodies: Sequence[pymunk.Body] = ()) -> None:
        """Let pymunk's cached contacts expire: the agent (and ``bodies``, apart) parked far outside for empty ticks.

        pymunk cannot save its contacts' warm-start impulses, so a scene about to be restored for a lookahead first
        forgets them; every lookahead from one snapshot is then the same, whatever the scene did before. The caller
        restores every body it parked.
        """
        self.agent.position, self.agent.velocity = (-500.0, -500.0), (0.0, 0.0)
        for i, body in enumerate(bodies):
            body.position, body.velocity, body.angular_velocity = (-2000.0 - 1000.0 * i, -2000.0), (0.0, 0.0), 0.0
        for _ in range(CONTACT_PERSISTENCE + 1):
            self.space.step(DT)


def contact_ticks(points: int) -> int:
    """Contact points summed over a control period's ticks, as contacts per tick (rounded up)."""
    return int(np.ceil(points / SUBSTEPS))


OBS_TYPES = ("state", "keypoints", "pixels")  # what a planar task's Gymnasium environment can observe


@dataclass(frozen=True)
class ObsConfig:
    """What a planar environment observes: ``obs_type`` is one of ``OBS_TYPES`` or a '+'-joined combination."""

    obs_type: str = "state"
    render_size: int = 96

    def __post_init__(self) -> None:
        parts = self.obs_type.split("+")
        bad = [p for p in parts if p not in OBS_TYPES]
        if bad or len(set(parts)) != len(parts):
            raise ValueError(f"obs_type {self.obs_type!r}: use one of {', '.join(OBS_TYPES)} or a '+'-joined combination")
        if self.render_size < 8:
            raise ValueError(f"render_size {self.render_size}: must be at least 8")

    @property
    def obs_parts(self) -> tuple[str, ...]:
        return tuple(self.obs_type.split("+"))


def observation_space(parts: Sequence[str], render_size: int, sizes: dict[str, int]) -> Any:
    """An environment's Gymnasium observation space: ``pixels`` an RGB frame, every other part a vector of ``sizes[part]``
    numbers; one part alone is its own space, several a ``Dict``."""
    from gymnasium import spaces

    def space(part: str) -> spaces.Space:
        if part == "pixels":
            return spaces.Box(0, 255, shape=(render_size, render_size, 3), dtype=np.uint8)
        return spaces.Box(-np.inf, np.inf, shape=(sizes[part],), dtype=np.float64)

    subspaces = {p: space(p) for p in parts}
    return next(iter(subspaces.values())) if len(subspaces) == 1 else spaces.Dict(subspaces)


def episode_seed(env: Any, seed: int | None) -> int:
    """The seed an episode is drawn from: the one given, else one from the Gymnasium env's own stream (``np_random``)."""
    return int(env.np_random.integers(0, 2**31 - 1)) if seed is None else seed
