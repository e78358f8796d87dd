"""The scripted stacking expert: privileged (it reads the true scene), seeded and stochastic.

A state machine over the true state: approach above the red cube, descend, close, lift, carry over the blue cube
(correcting for where the cube sits in the hand), lower until the red cube rests on the blue one, open, retreat. It
reacts to what happens: a cube lost on the way, or one left off its target after release, is grasped again. Each
seed draws the episode's heights, speed, jaw opening and small waypoint noise, so demonstrations vary as a human's
would while every one of them succeeds the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpc.tasks.stack import geometry
from gpc.tasks.stack.scene import CUBE_SIDE, StackSim

APPROACH, DESCEND, CLOSE, LIFT, CARRY, LOWER, RELEASE, RETREAT = range(8)


@dataclass(frozen=True)
class ExpertConfig:
    """Ranges each episode draws its style from (metres, steps)."""

    approach_height: tuple[float, float] = (0.07, 0.10)  # grasp-centre height when moving above a cube
    carry_height: tuple[float, float] = (0.10, 0.13)  # when carrying the red cube over the blue one
    max_step: tuple[float, float] = (0.025, 0.04)  # the largest move of the target per step
    open_width: tuple[float, float] = (0.07, 0.085)
    noise: float = 0.002  # waypoint noise (std, m) while moving freely
    close_steps: int = 3
    release_steps: int = 2
    aligned: float = 0.003  # horizontal error (m) that counts as above a cube

    def __post_init__(self) -> None:
        for name in ("approach_height", "carry_height", "max_step", "open_width"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"{name} {lo, hi}: need 0 < low <= high")


def step_toward(base: np.ndarray, target: np.ndarray, max_step: float) -> np.ndarray:
    """``base`` moved toward ``target`` by at most ``max_step`` (m)."""
    step = target - base
    return base + step * min(1.0, max_step / max(float(np.linalg.norm(step)), 1e-9))


class StackExpert:
    """``act(sim) -> [x, y, z, opening]`` targets; ``reset(seed)`` draws the episode's style."""

    def __init__(self, config: ExpertConfig = ExpertConfig()) -> None:
        self.config = config
        self.command: np.ndarray | None = None  # the last target sent (moves start from it, not from the lagging hand)
        self.reset(0)

    def reset(self, seed: int) -> None:
        c, self.rng = self.config, np.random.default_rng(seed)
        self.approach = self.rng.uniform(*c.approach_height)
        self.carry = self.rng.uniform(*c.carry_height)
        self.max_step = self.rng.uniform(*c.max_step)
        self.open = self.rng.uniform(*c.open_width)
        self.phase, self.timer, self.command = APPROACH, 0, None

    def _move(self, hand: np.ndarray, target: np.ndarray, noisy: bool) -> np.ndarray:
        out = step_toward(hand if self.command is None else self.command, target, self.max_step)
        if noisy:
            out = out + self.rng.normal(0.0, self.config.noise, 3)
        self.command = out
        return out

    def act(self, sim: StackSim, goal: np.ndarray | None = None) -> np.ndarray:
        s = sim.state()
        hand, red, blue = s[geometry.GRIPPER], s[geometry.RED], s[geometry.BLUE]
        c = self.config
        grasped = s[geometry.OPENING] < CUBE_SIDE + 0.004 and np.linalg.norm(red - hand) < 0.015
        if self.phase in (LIFT, CARRY, LOWER) and not grasped:
            self.phase = APPROACH  # dropped on the way: grasp again
        if self.phase == RETREAT and self.timer > 8 and not geometry.stacked(s) and sim.cube_speeds().max() < geometry.SETTLED_SPEED:
            self.phase = APPROACH  # released off target: grasp again
        self.timer += 1
        opening = self.open
        if self.phase == APPROACH:
            target = np.array([red[0], red[1], max(self.approach, red[2] + 0.05)])
            near = np.linalg.norm(hand[:2] - red[:2]) < c.aligned and abs(hand[2] - target[2]) < 0.01
            pos = self._move(hand, target, noisy=not near)
            if near:
                self.phase, self.timer = DESCEND, 0
        elif self.phase == DESCEND:
            target = red.copy()
            pos = self._move(hand, target, noisy=False)
            if abs(hand[2] - red[2]) < 0.003:
                self.phase, self.timer = CLOSE, 0
        elif self.phase == CLOSE:
            pos, opening = self._move(hand, red, noisy=False), 0.0
            if self.timer >= c.close_steps:
                self.phase, self.timer = LIFT, 0
        else:
            pos, opening = self._carry(hand, red, blue, s)
        return np.concatenate([pos, [opening]])

    def _carry(self, hand: np.ndarray, red: np.ndarray, blue: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, float]:
        """The phases after the grasp: lift, carry, lower, release, retreat."""
        c = self.config
        offset = hand - red  # where the cube sits in the hand
        over = blue[:2] + offset[:2]
        if self.phase == LIFT:
            pos = self._move(hand, np.array([hand[0], hand[1], self.carry]), noisy=False)
            if hand[2] > self.carry - 0.01:
                self.phase, self.timer = CARRY, 0
            return pos, 0.0
        if self.phase == CARRY:
            pos = self._move(hand, np.array([over[0], over[1], self.carry]), noisy=bool(np.linalg.norm(red[:2] - blue[:2]) > 0.03))
            if np.linalg.norm(red[:2] - blue[:2]) < c.aligned:
                self.phase, self.timer = LOWER, 0
            return pos, 0.0
        if self.phase == LOWER:
            place = blue[2] + CUBE_SIDE + offset[2] + 0.001
            pos = self._move(hand, np.array([over[0], over[1], place]), noisy=False)
            if red[2] - blue[2] < CUBE_SIDE + 0.003:
                self.phase, self.timer = RELEASE, 0
            return pos, 0.0
        if self.phase == RELEASE:
            pos = self._move(hand, hand if self.command is None else self.command, noisy=False)
            if self.timer >= c.release_steps:
                self.phase, self.timer = RETREAT, 0
            return pos, self.open
        return self._move(hand, np.array([hand[0], hand[1], red[2] + 0.08]), noisy=False), self.open
