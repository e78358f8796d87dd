"""The stacking exploration collector: pushes, lifts, drops and knocks over, for world-model data.

A seeded sequence of behaviours, each a short list of waypoints planned from the scene when it starts: ``push``
(down beside a cube, the jaws closed or open, and through it), ``drop`` (grasp a cube, lift it, carry it anywhere,
let go from a height), ``stack`` (set the red cube on the blue one off centre, where it may topple or stay) and
``sweep`` (through the stack or a cube at mid height, knocking it over). The gripper moves toward the current
waypoint by a drawn speed and goes on when it is reached or after a timeout, so what follows depends on what
happened: the data covers contacts, grasps, falls and stacks from many starts. ``evaluate_explore`` measures how
much of it touches something.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gpc.tasks.stack import geometry
from gpc.tasks.stack.expert import step_toward
from gpc.tasks.stack.render import quat_matrix
from gpc.tasks.stack.scene import ACTION_HIGH, ACTION_LOW, CUBE_SIDE, MAX_OPENING, StackSim

BEHAVIOURS = ("push", "drop", "stack", "sweep")
Waypoint = tuple[np.ndarray, float]  # (grasp-centre target, opening)


@dataclass(frozen=True)
class ExploreConfig:
    """The behaviours' shares, speed range and how long a waypoint may take."""

    weights: tuple[float, ...] = (0.35, 0.3, 0.2, 0.15)  # push, drop, stack, sweep
    max_step: tuple[float, float] = (0.02, 0.045)
    timeout: int = 12  # steps toward one waypoint before moving on

    def __post_init__(self) -> None:
        if len(self.weights) != len(BEHAVIOURS) or min(self.weights) < 0 or sum(self.weights) <= 0:
            raise ValueError(f"weights {self.weights}: need {len(BEHAVIOURS)} non-negative shares, not all 0")


class ExplorePolicy:
    """``act(sim) -> [x, y, z, opening]``; ``reset(seed)`` starts the seed's sequence of behaviours."""

    def __init__(self, config: ExploreConfig = ExploreConfig()) -> None:
        self.config = config
        self.reset(0)

    def reset(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.plan: list[Waypoint] = []
        self.command: np.ndarray | None = None
        self.timer, self.max_step, self.behaviour = 0, 0.03, BEHAVIOURS[0]

    def act(self, sim: StackSim) -> np.ndarray:
        s = sim.state()
        hand = s[geometry.GRIPPER]
        if self.command is None:
            self.command = hand.copy()
        if self.plan and (np.linalg.norm(hand - self.plan[0][0]) < 0.006 or self.timer >= self.config.timeout):
            self.plan.pop(0)
            self.timer = 0
        if not self.plan:
            self._new_behaviour(s)
        self.timer += 1
        target, opening = self.plan[0]
        self.command = step_toward(self.command, target, self.max_step)
        return np.clip(np.concatenate([self.command, [opening]]), ACTION_LOW, ACTION_HIGH)

    def _new_behaviour(self, s: np.ndarray) -> None:
        c, rng = self.config, self.rng
        weights = np.asarray(c.weights) / sum(c.weights)
        self.behaviour = BEHAVIOURS[int(rng.choice(len(BEHAVIOURS), p=weights))]
        self.max_step = rng.uniform(*c.max_step)
        cube = s[geometry.RED] if rng.random() < 0.5 else s[geometry.BLUE]
        self.plan = getattr(self, f"_{self.behaviour}")(s, cube.copy())
        self.timer = 0

    def _above(self, xy: np.ndarray, opening: float) -> Waypoint:
        return np.array([xy[0], xy[1], self.rng.uniform(0.07, 0.11)]), opening

    def _push(self, s: np.ndarray, cube: np.ndarray) -> list[Waypoint]:
        rng = self.rng
        angle = rng.uniform(-np.pi, np.pi)
        direction = np.array([np.cos(angle), np.sin(angle)])
        start = cube[:2] - direction * rng.uniform(0.045, 0.06)
        end = cube[:2] + direction * rng.uniform(0.02, 0.1)
        opening = rng.choice([0.0, MAX_OPENING * rng.uniform(0.3, 1.0)])
        z = rng.uniform(0.015, 0.035)
        return [self._above(start, opening), (np.array([*start, z]), opening), (np.array([*end, z]), opening),
                self._above(end, opening)]

    def _grasp(self, cube: np.ndarray) -> list[Waypoint]:
        wide = self.rng.uniform(0.065, MAX_OPENING)
        return [self._above(cube[:2], wide), (cube + self.rng.normal(0.0, 0.003, 3), wide), (cube, 0.0), (cube, 0.0)]

    def _drop(self, s: np.ndarray, cube: np.ndarray) -> list[Waypoint]:
        rng = self.rng
        high = np.array([*rng.uniform(-0.13, 0.13, 2), rng.uniform(0.06, 0.16)])
        return [*self._grasp(cube), (np.array([cube[0], cube[1], high[2]]), 0.0), (high, 0.0), (high, MAX_OPENING),
                (high + [0.0, 0.0, 0.03], MAX_OPENING)]

    def _stack(self, s: np.ndarray, cube: np.ndarray) -> list[Waypoint]:
        rng, red, blue = self.rng, s[geometry.RED], s[geometry.BLUE]
        over = blue + np.array([*rng.normal(0.0, 0.012, 2), CUBE_SIDE + rng.uniform(0.0, 0.02)])
        return [*self._grasp(red), (np.array([red[0], red[1], 0.12]), 0.0), (np.array([over[0], over[1], 0.12]), 0.0),
                (over, 0.0), (over, MAX_OPENING), (over + [0.0, 0.0, 0.06], MAX_OPENING)]

    def _sweep(self, s: np.ndarray, cube: np.ndarray) -> list[Waypoint]:
        rng = self.rng
        angle = rng.uniform(-np.pi, np.pi)
        direction = np.array([np.cos(angle), np.sin(angle)])
        z = rng.uniform(0.03, 0.07)
        start, end = cube[:2] - direction * 0.08, cube[:2] + direction * rng.uniform(0.03, 0.1)
        opening = rng.uniform(0.0, MAX_OPENING)
        return [self._above(start, opening), (np.array([*start, z]), opening), (np.array([*end, z]), opening),
                self._above(end, opening)]


def evaluate_explore(seeds: Sequence[int], config: ExploreConfig = ExploreConfig(), max_steps: int = 300) -> dict:
    """The share of steps with gripper-cube or cube-cube contact, each pair's share, the share of steps stacked and
    of episodes in which a cube was knocked over (its up axis more than 30 degrees off vertical) at some step."""
    from gpc.tasks.stack.env import StackEnv

    touching, pairs, tipped, stacked = [], [], [], []
    for seed in seeds:
        env, policy = StackEnv(), ExplorePolicy(config)
        env.reset(seed=int(seed))
        policy.reset(int(seed))
        tilt = False
        for _ in range(max_steps):
            info = env.step(policy.act(env.sim))[4]
            touching.append(info["n_contacts"] > 0)
            pairs.append(info["contacts"] > 0)
            s = info["state"]
            stacked.append(bool(geometry.stacked(s)))
            tilt = tilt or _tipped(s)
            if info.get("unstable"):
                break
        tipped.append(tilt)
    share = np.mean(pairs, axis=0)
    return {"steps": len(touching), "contact_fraction": float(np.mean(touching)), "gripper_red": float(share[0]),
            "gripper_blue": float(share[1]), "red_blue": float(share[2]), "stacked_steps": float(np.mean(stacked)),
            "knocked_over": float(np.mean(tipped))}


def _tipped(s: np.ndarray) -> bool:
    """A cube whose starting up axis leans more than 30 degrees off vertical (knocked over, or turned in the jaws)."""
    return any(abs(quat_matrix(q)[2, 2]) < np.cos(np.radians(30)) for q in (s[geometry.RED_QUAT], s[geometry.BLUE_QUAT]))
