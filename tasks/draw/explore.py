"""Exploration for world-model data: scribbles, partial edges and retracing, so the ink summary takes values across
the reward's range (a world model must learn what a stroke does to it anywhere, not only along an expert's path).

An episode is a chain of moves drawn from the seed, each a few to a few dozen steps: ``trace`` runs the target along
the outline (from the pen's nearest point, either way, a random length, at a random speed, offset sideways by up to
``max_offset``: partial edges, corners cut at speed, and retracing when it goes back over ink), ``scribble`` wanders
smoothly anywhere on the canvas (ink off the outline), ``hold`` keeps the target still. ``mode`` weights them:
``scribbles`` mostly wander, ``partial`` and ``retrace`` mostly trace (``retrace`` longer and with more reversals),
and ``mixed`` draws one of the three per episode.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gpc.tasks.draw.env import MAX_EPISODE_STEPS
from gpc.tasks.draw.geometry import edge_lengths
from gpc.tasks.draw.sim import DrawSim
from gpc.tasks.planar.scene import WORKSPACE

MODES = ("scribbles", "partial", "retrace", "mixed")
WEIGHTS = {"scribbles": (0.25, 0.65, 0.10), "partial": (0.65, 0.20, 0.15), "retrace": (0.85, 0.05, 0.10)}  # trace, scribble, hold
LO, HI = 30.0, WORKSPACE - 30.0


@dataclass(frozen=True)
class ExploreConfig:
    """What kind of exploration to run; ranges are drawn per move."""

    mode: str = "mixed"
    trace_length: tuple[float, float] = (40.0, 500.0)  # px of outline a trace covers
    trace_speed: tuple[float, float] = (6.0, 35.0)  # px per step of the target along the outline
    max_offset: float = 14.0  # px: a trace's sideways offset is drawn up to this (0 with probability on_line)
    on_line: float = 0.5  # the chance that a trace runs on the outline itself
    scribble_steps: tuple[int, int] = (5, 30)
    scribble_speed: tuple[float, float] = (5.0, 25.0)  # px per step
    scribble_turn: float = 0.5  # std (rad) of the scribble's heading change per step
    hold_steps: tuple[int, int] = (1, 6)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode {self.mode!r}: use one of {', '.join(MODES)}")
        for name in ("trace_length", "trace_speed", "scribble_speed", "scribble_steps", "hold_steps"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"{name} {getattr(self, name)}: need 0 < low <= high")
        if self.max_offset < 0 or not 0.0 <= self.on_line <= 1.0 or self.scribble_turn < 0:
            raise ValueError("need max_offset >= 0, on_line in [0, 1] and scribble_turn >= 0")


def outline_point(vertices: np.ndarray, u: float) -> tuple[np.ndarray, np.ndarray]:
    """The point at arc length ``u`` (mod the perimeter) along the outline from vertex 0, and the edge's unit direction."""
    lengths = edge_lengths(vertices)
    u = float(u) % float(lengths.sum())
    edge = min(int(np.searchsorted(np.cumsum(lengths), u, side="right")), 2)
    a, b = vertices[edge], vertices[(edge + 1) % 3]
    along = (b - a) / lengths[edge]
    return a + along * (u - (np.cumsum(lengths)[edge] - lengths[edge])), along


def nearest_arc(vertices: np.ndarray, xy: np.ndarray) -> float:
    """Arc length of the outline point nearest ``xy``."""
    lengths, best, arc = edge_lengths(vertices), np.inf, 0.0
    for i in range(3):
        a, b = vertices[i], vertices[(i + 1) % 3]
        t = float(np.clip(np.dot(xy - a, b - a) / lengths[i] ** 2, 0.0, 1.0))
        d = float(np.linalg.norm(a + t * (b - a) - xy))
        if d < best:
            best, arc = d, float(lengths[:i].sum() + t * lengths[i])
    return arc


class ExplorePolicy:
    """A privileged random controller: a chain of trace, scribble and hold moves (``ExploreConfig``)."""

    def __init__(self, config: ExploreConfig = ExploreConfig()) -> None:
        self.config = config
        self._rng = np.random.default_rng(0)
        self.episode_mode = config.mode
        self._left = 0

    def reset(self, seed: int) -> None:
        self._rng = np.random.default_rng(seed)
        modes = MODES[:3]
        self.episode_mode = modes[int(self._rng.integers(3))] if self.config.mode == "mixed" else self.config.mode
        self._left, self._kind = 0, "hold"

    def _next_move(self, sim: DrawSim) -> None:
        c, rng = self.config, self._rng
        self._kind = str(rng.choice(("trace", "scribble", "hold"), p=WEIGHTS[self.episode_mode]))
        pen = sim.pen()
        if self._kind == "trace":
            speed = rng.uniform(*c.trace_speed)
            self._arc, self._speed = nearest_arc(sim.vertices, pen), speed * (1 if rng.random() < 0.5 else -1)
            self._offset = 0.0 if rng.random() < c.on_line else rng.uniform(-c.max_offset, c.max_offset)
            self._left = max(1, int(rng.uniform(*c.trace_length) / speed))
        elif self._kind == "scribble":
            self._carrot, self._heading = pen.copy(), rng.uniform(-np.pi, np.pi)
            self._speed = rng.uniform(*c.scribble_speed)
            self._left = int(rng.integers(c.scribble_steps[0], c.scribble_steps[1] + 1))
        else:
            self._hold = pen.copy()
            self._left = int(rng.integers(c.hold_steps[0], c.hold_steps[1] + 1))

    def act(self, sim: DrawSim, goal: np.ndarray | None = None) -> np.ndarray:
        if self._left <= 0:
            self._next_move(sim)
        self._left -= 1
        if self._kind == "trace":
            self._arc += self._speed
            point, along = outline_point(sim.vertices, self._arc)
            return np.clip(point + self._offset * np.array([-along[1], along[0]]), 0.0, WORKSPACE)
        if self._kind == "scribble":
            self._heading += float(self._rng.normal(0.0, self.config.scribble_turn))
            step = self._speed * np.array([np.cos(self._heading), np.sin(self._heading)])
            nxt = self._carrot + step
            if not (LO <= nxt[0] <= HI and LO <= nxt[1] <= HI):  # bounce off the margins: turn back inwards
                self._heading += np.pi
                nxt = np.clip(self._carrot - step, LO, HI)
            self._carrot = nxt
            return self._carrot.copy()
        return self._hold.copy()


def evaluate_explore(seeds: Sequence[int], config: ExploreConfig = ExploreConfig(), max_steps: int = MAX_EPISODE_STEPS) -> dict:
    """The episodes' scores (max F1) and final ink off the outline (share of the band), with their modes."""
    from gpc.tasks.draw.record import RecordConfig, record_episode

    policy = ExplorePolicy(config)
    scores, off, modes = [], [], []
    for seed in seeds:
        data, stats = record_episode(policy, int(seed), RecordConfig(max_steps=max_steps, stop_on_success=False, images=False))
        scores.append(stats.score)
        off.append(float(data["state"][-1, -1]))
        modes.append(policy.episode_mode)
    s = np.array(scores)
    return {"episodes": len(s), "mean_score": float(s.mean()), "score_quantiles": {q: float(np.quantile(s, q / 100))
            for q in (0, 10, 25, 50, 75, 90, 100)}, "score_histogram": np.histogram(s, bins=10, range=(0.0, 1.0))[0].tolist(),
            "success_rate": float((s > 0.9).mean()), "mean_final_off_outline": float(np.mean(off)),
            "modes": {m: modes.count(m) for m in MODES[:3]}}
