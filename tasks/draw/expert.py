"""Scripted drawing expert: trace the triangle in one stroke from the vertex the pen starts on, either way round.

The pen is Push-T's critically damped PD agent: steered by a target that moves along a straight edge from rest on
that edge, it stays on the edge's line exactly (lagging behind the target, never beside it). So the expert moves
its target along each edge with a bell-shaped, noisy speed (a hand's: slow off a corner, fastest mid-edge, a peak
drawn per edge) and turns onto the next edge once the pen is within its own radius of the corner (its ink already
covers the corner), without stopping there: demonstrations that rest at a corner teach a policy to rest there (a
first expert held each corner 4-8 steps until the pen had stopped, 18% of its steps idle, and its policy, at rest
at a corner, kept predicting more rest). A faint, slow tremor across the stroke (its amplitude drawn per episode) is
the only ink off the line. The direction, the speeds and the tremor are drawn from the seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gpc.tasks.draw.sim import DrawSim


@dataclass(frozen=True)
class ExpertConfig:
    """Ranges drawn per edge (peak speed) or per episode (direction, tremor)."""

    peak_speed: tuple[float, float] = (14.0, 28.0)  # px per step of the target at an edge's middle
    slow_share: float = 0.3  # speed at an edge's ends, as a share of its peak
    speed_noise: float = 0.15  # relative std of the per-step speed
    tremor: tuple[float, float] = (0.0, 1.2)  # px: amplitude of the slow sideways wobble of the target
    settle_px: float = 10.0  # the pen turns a corner once within this of the vertex (the pen's radius) ...
    settle_speed: float = math.inf  # ... and slower than this (px/s; a finite value makes it stop at corners)
    pause: tuple[int, int] = (0, 0)  # extra steps held at a corner (idle steps: none by default)
    clockwise_share: float = 0.5  # the chance of going round in the vertices' reverse order

    def __post_init__(self) -> None:
        lo, hi = self.peak_speed
        if not 0.0 < lo <= hi <= 60.0:
            raise ValueError(f"peak_speed {self.peak_speed}: need 0 < low <= high <= 60")
        if not 0.0 < self.slow_share <= 1.0 or self.speed_noise < 0 or self.settle_px <= 0 or self.settle_speed <= 0:
            raise ValueError("need 0 < slow_share <= 1, speed_noise >= 0, settle_px > 0 and settle_speed > 0")
        if not 0.0 <= self.tremor[0] <= self.tremor[1] or not 0 <= self.pause[0] <= self.pause[1]:
            raise ValueError(f"tremor {self.tremor} and pause {self.pause}: need 0 <= low <= high")
        if not 0.0 <= self.clockwise_share <= 1.0:
            raise ValueError(f"clockwise_share {self.clockwise_share}: must lie in [0, 1]")


def corners_from(vertices: np.ndarray, start: int, step: int) -> np.ndarray:
    """The closed tour ``(4, 2)`` of the triangle from vertex ``start`` in direction ``step`` (+1 or -1)."""
    return np.asarray(vertices)[[(start + step * i) % 3 for i in range(4)]]


def nearest_vertex(vertices: np.ndarray, xy: np.ndarray) -> int:
    return int(np.argmin(np.linalg.norm(np.asarray(vertices) - xy, axis=1)))


class DrawExpert:
    """A privileged controller: reads the true scene (pen and triangle), returns a target position."""

    def __init__(self, config: ExpertConfig = ExpertConfig()) -> None:
        self.config = config
        self._rng = np.random.default_rng(0)
        self._tour: np.ndarray | None = None

    def reset(self, seed: int) -> None:
        self._rng = np.random.default_rng(seed)
        self._tour = None

    def _plan(self, sim: DrawSim) -> None:
        c, rng = self.config, self._rng
        step = -1 if rng.random() < c.clockwise_share else 1
        self._tour = corners_from(sim.vertices, nearest_vertex(sim.vertices, sim.pen()), step)
        self._edge, self._s, self._hold = 0, 0.0, -1
        self._peak = rng.uniform(*c.peak_speed)
        self._tremor, self._phase, self._period = rng.uniform(*c.tremor), rng.uniform(0, 2 * np.pi), rng.uniform(6.0, 14.0)
        self._t = 0

    def act(self, sim: DrawSim, goal: np.ndarray | None = None) -> np.ndarray:
        if self._tour is None:
            self._plan(sim)
        assert self._tour is not None
        c, rng = self.config, self._rng
        self._t += 1
        if self._edge >= 3:  # done: rest on the start vertex
            return self._tour[3].copy()
        a, b = self._tour[self._edge], self._tour[self._edge + 1]
        length = float(np.linalg.norm(b - a))
        if self._s < length:
            bell = c.slow_share + (1.0 - c.slow_share) * np.sin(np.pi * min(self._s / length, 1.0))
            self._s = min(self._s + self._peak * bell * max(0.2, 1.0 + rng.normal(0.0, c.speed_noise)), length)
            along = (b - a) / length
            fade = np.sin(np.pi * self._s / length)  # no wobble at the corners
            wobble = self._tremor * fade * np.sin(self._phase + 2 * np.pi * self._t / self._period)
            return a + along * self._s + wobble * np.array([-along[1], along[0]])
        velocity = np.hypot(*sim.agent.velocity)
        if self._hold < 0 and np.linalg.norm(sim.pen() - b) < c.settle_px and velocity < c.settle_speed:
            self._hold = int(rng.integers(c.pause[0], c.pause[1] + 1))
        if self._hold == 0:  # turn the corner: the next edge, a new peak speed
            self._edge, self._s, self._hold = self._edge + 1, 0.0, -1
            self._peak = rng.uniform(*c.peak_speed)
            return self.act(sim, goal) if self._edge < 3 else b.copy()
        if self._hold > 0:
            self._hold -= 1
        return b.copy()
