"""Block Stacking geometry on 18-d states: the red cube's target above the blue one, the reward and success.

The target is the point one cube side straight above the blue cube's centre: where the red cube's centre sits when
it rests on the blue one, centred (whichever faces touch, a resting cube is a cube side tall). Only positions count:
the cubes are symmetric and the goal says "on top, centred". reward = clip(1 - distance / ``REWARD_DISTANCE``, 0, 1),
so 1 cm off scores 0.9 and two cubes side by side on the table about 0.
"""

from __future__ import annotations

import numpy as np

from gpc.tasks.stack.scene import CUBE_SIDE, FINGER, FINGER_Z

GRIPPER, OPENING, RED, BLUE = slice(0, 3), 3, slice(4, 7), slice(11, 14)  # entries of an 18-d state
RED_QUAT, BLUE_QUAT = slice(7, 11), slice(14, 18)
REWARD_DISTANCE = 0.1  # metres at which the reward reaches 0
ON_TARGET = 0.01  # the red cube within this of its target (reward >= 0.9) counts as stacked
OPEN = CUBE_SIDE + 0.01  # a gripper this open has let go
CLEAR = 0.01  # and its fingertips this far above the red cube's top (or the hand ``ASIDE`` away from it) is clear
ASIDE = 0.08
SETTLED_SPEED = 0.02  # m/s: a cube slower than this rests
SUCCESS_STEPS = 10  # steps in a row stacked, released and clear that make a success


def target(state: np.ndarray) -> np.ndarray:
    """The red cube's target position ``(..., 3)``: one cube side above the blue cube's centre."""
    state = np.asarray(state, dtype=np.float64)
    return state[..., BLUE] + np.array([0.0, 0.0, CUBE_SIDE])


def distance(state: np.ndarray) -> np.ndarray:
    """The red cube's distance to its target (m) ``(...)``."""
    state = np.asarray(state, dtype=np.float64)
    return np.linalg.norm(state[..., RED] - target(state), axis=-1)


def reward(state: np.ndarray) -> np.ndarray:
    """One minus the normalised distance, in [0, 1] ``(...)``."""
    return np.clip(1.0 - distance(state) / REWARD_DISTANCE, 0.0, 1.0)


def released(state: np.ndarray) -> np.ndarray:
    """The gripper open and clear of the red cube: fingertips above its top, or the hand aside of it ``(...)`` bool."""
    state = np.asarray(state, dtype=np.float64)
    tips = state[..., 2] + FINGER_Z - FINGER[2]
    above = tips > state[..., RED][..., 2] + CUBE_SIDE / 2 + CLEAR
    aside = np.linalg.norm(state[..., 0:2] - state[..., RED][..., 0:2], axis=-1) > ASIDE
    return (state[..., OPENING] > OPEN) & (above | aside)


def stacked(state: np.ndarray) -> np.ndarray:
    """The red cube on its target ``(...)`` bool."""
    return distance(state) < ON_TARGET
