"""Cube & Sphere Swapping geometry: the two objects' shapes, the keypoints, coverage of the targets and the reward.

The cube is a square block with a pose ``(x, y, angle)`` of its centre (its body origin is its centre of gravity);
the sphere is a disc with a position ``(x, y)``. The goal is the swap: the cube's target is the sphere's start and
the sphere's target the cube's start, both positions. The cube's orientation does not count: the task is to swap
places, a disc agent controls an object's position far more precisely than a square's yaw, and the sphere has no
orientation, so the cube's target region is its own footprint (oriented as the cube is now) centred on its target.
Coverage is the share of an object's area inside its target region, in closed form (no polygon clipping).
"""

from __future__ import annotations

import numpy as np

from gpc.tasks.planar.paths import rotate

CUBE_SIDE = 60.0
SPHERE_RADIUS = 34.0  # a little under the cube's half-diagonal (42.4 px): about the cube's area (3632 against 3600 px^2)
SUCCESS_COVERAGE = 0.90  # both objects must cover their targets by more than this
REWARD_SCALE = 0.95  # reward = clip(mean coverage / 0.95, 0, 1)
# Keypoints in the cube's frame: its 4 corners (counter-clockwise from (-s/2, -s/2)) then its centre.
CUBE_KEYPOINTS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0], [0.0, 0.0]]) * (CUBE_SIDE / 2)
N_KEYPOINTS = 6  # the cube's 5, then the sphere's centre


def cube_keypoints(pose: np.ndarray) -> np.ndarray:
    """The cube's 4 corners and centre ``(..., 5, 2)`` for poses ``(..., 3)``."""
    pose = np.asarray(pose, dtype=np.float64)
    return pose[..., None, :2] + rotate(CUBE_KEYPOINTS, pose[..., 2, None])


def keypoints(state: np.ndarray) -> np.ndarray:
    """``(..., 6, 2)`` from 7-d states: the cube's 4 corners (counter-clockwise in its frame) and centre, the sphere's centre."""
    state = np.asarray(state, dtype=np.float64)
    return np.concatenate([cube_keypoints(state[..., 2:5]), state[..., None, 5:7]], axis=-2)


def cube_coverage(pose: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Share of the cube's area inside its footprint centred at ``target`` ``(..., 2)``, for poses ``(..., 3)``.

    Two equal squares of the same orientation overlap in ``(1 - |dx'|/s)+ (1 - |dy'|/s)+`` of their area, ``dx', dy'``
    the offset in the cube's frame.
    """
    pose, target = np.asarray(pose, dtype=np.float64), np.asarray(target, dtype=np.float64)
    offset = rotate(target - pose[..., :2], -pose[..., 2])
    share = np.clip(1.0 - np.abs(offset) / CUBE_SIDE, 0.0, 1.0)
    return share[..., 0] * share[..., 1]


def sphere_coverage(xy: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Share of the sphere's area inside the disc of its radius centred at ``target``: the lens of two equal discs."""
    d = np.linalg.norm(np.asarray(xy, dtype=np.float64) - np.asarray(target, dtype=np.float64), axis=-1)
    r = SPHERE_RADIUS
    h = np.clip(d / (2 * r), 0.0, 1.0)
    lens = 2 * r * r * np.arccos(h) - 0.5 * d * np.sqrt(np.clip(4 * r * r - d * d, 0.0, None))
    return np.where(d < 2 * r, lens / (np.pi * r * r), 0.0)


def coverages(state: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """``(..., 2)``: the cube's and the sphere's coverage, for 7-d states and 4-d goals ``[cube target, sphere target]``."""
    state, goal = np.asarray(state, dtype=np.float64), np.asarray(goal, dtype=np.float64)
    return np.stack([cube_coverage(state[..., 2:5], goal[..., 0:2]), sphere_coverage(state[..., 5:7], goal[..., 2:4])], axis=-1)


def reward_from_coverages(cov: np.ndarray) -> np.ndarray:
    """``clip(mean coverage / 0.95, 0, 1)`` over the last axis (the two objects)."""
    return np.clip(np.asarray(cov, dtype=np.float64).mean(axis=-1) / REWARD_SCALE, 0.0, 1.0)


def is_success(cov: np.ndarray) -> np.ndarray:
    """Both objects cover their targets by more than ``SUCCESS_COVERAGE``."""
    return np.all(np.asarray(cov) > SUCCESS_COVERAGE, axis=-1)
