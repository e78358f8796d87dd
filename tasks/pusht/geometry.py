"""Push-T geometry: the T's shape, its keypoints, goal coverage and registration error.

Every Push-T constant that reward, rendering and observation code need lives here, so the
simulator, the renderer and a learned model all agree on one definition of the block.
A *pose* is ``(x, y, theta)`` of the block's body origin (not its centre of gravity), as
Diffusion Policy records it.
"""

from __future__ import annotations

import numpy as np

from gpc.tasks.planar.scene import WORKSPACE

GOAL_POSE = np.array([256.0, 256.0, np.pi / 4])
SUCCESS_COVERAGE = 0.95

# The T as two boxes in block coordinates (Diffusion Policy's add_tee with scale 30, length 4).
TEE_BOXES = np.array(
    [
        [(-60.0, 30.0), (60.0, 30.0), (60.0, 0.0), (-60.0, 0.0)],
        [(-15.0, 30.0), (-15.0, 120.0), (15.0, 120.0), (15.0, 30.0)],
    ]
)
TEE_AREA = 120.0 * 30.0 + 30.0 * 90.0
# Its area centroid in block coordinates (each box weighted by its area): where a colour segmentation finds it.
TEE_CENTROID = sum(box.mean(axis=0) * np.ptp(box[:, 0]) * np.ptp(box[:, 1]) for box in TEE_BOXES) / TEE_AREA

# Diffusion Policy's 9 block keypoints in block coordinates. Its keypoint manager draws them
# once by farthest-point sampling on a rendered mask (plus a random shift); these values are
# recovered from the recorded `keypoint` field of its human Push-T data (median over all steps).
BLOCK_KEYPOINTS = np.array(
    [
        [9.26978659, 90.04097383],
        [-60.98347199, -1.18673028],
        [60.91275549, -1.39336337],
        [-0.27050363, 25.54362506],
        [-14.06492732, 122.81585395],
        [39.00273833, 32.85740443],
        [-39.96641428, 32.7296555],
        [-16.824344, 62.8631792],
        [23.54146135, -1.70028786],
    ]
)


# gym-pusht's ``environment_state`` (what LeRobot's Push-T keypoint policies read): the T's 8 outline
# vertices, bar then stem, in the order pymunk returns each box's vertices (as gym-pusht reads them).
OUTLINE_VERTICES = np.array(
    [(-60.0, 0.0), (60.0, 0.0), (60.0, 30.0), (-60.0, 30.0), (-15.0, 30.0), (15.0, 30.0), (15.0, 120.0), (-15.0, 120.0)]
)


def to_world(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Map block-frame points ``(..., N, 2)`` to the world for poses ``(..., 3)``."""
    pose = np.asarray(pose, dtype=np.float64)
    c, s = np.cos(pose[..., 2])[..., None], np.sin(pose[..., 2])[..., None]
    x, y = points[..., 0], points[..., 1]
    return np.stack(
        [pose[..., 0, None] + c * x - s * y, pose[..., 1, None] + s * x + c * y], axis=-1
    )


def block_keypoints(pose: np.ndarray) -> np.ndarray:
    """Diffusion Policy's 9 keypoints ``(..., 9, 2)`` for block poses ``(..., 3)``."""
    return to_world(BLOCK_KEYPOINTS, pose)


def outline_vertices(pose: np.ndarray) -> np.ndarray:
    """gym-pusht's 8 outline vertices ``(..., 8, 2)`` for block poses ``(..., 3)``."""
    return to_world(OUTLINE_VERTICES, pose)


def pose_from_outline(vertices: np.ndarray) -> np.ndarray:
    """Block poses ``(..., 3)`` from outline vertices ``(..., 8, 2)`` (least-squares rigid fit; angle in (-pi, pi])."""
    q = np.asarray(vertices, dtype=np.float64)
    p = OUTLINE_VERTICES - OUTLINE_VERTICES.mean(axis=0)
    centre = q.mean(axis=-2)
    qc = q - centre[..., None, :]
    cross = (p[:, 0] * qc[..., 1] - p[:, 1] * qc[..., 0]).sum(axis=-1)
    dot = (p[:, 0] * qc[..., 0] + p[:, 1] * qc[..., 1]).sum(axis=-1)
    theta = np.arctan2(cross, dot)
    c, s = np.cos(theta), np.sin(theta)
    mx, my = OUTLINE_VERTICES.mean(axis=0)
    return np.stack([centre[..., 0] - (c * mx - s * my), centre[..., 1] - (s * mx + c * my), theta], axis=-1)


def tee_vertices(pose: np.ndarray) -> np.ndarray:
    """World vertices ``(..., 2, 4, 2)`` of the T's two boxes."""
    pose = np.asarray(pose, dtype=np.float64)
    return to_world(TEE_BOXES.reshape(8, 2), pose).reshape(pose.shape[:-1] + (2, 4, 2))


def _clip(subject: list[tuple[float, float]], clip: np.ndarray) -> list[tuple[float, float]]:
    """Sutherland-Hodgman: the part of polygon ``subject`` inside convex polygon ``clip``."""
    n = len(clip)
    # Orientation of the clip polygon decides which side of each edge is "inside".
    area2 = sum(clip[i][0] * clip[(i + 1) % n][1] - clip[(i + 1) % n][0] * clip[i][1] for i in range(n))
    sign = 1.0 if area2 > 0 else -1.0
    out = subject
    for i in range(n):
        if not out:
            break
        ax, ay = clip[i]
        bx, by = clip[(i + 1) % n]
        ex, ey = bx - ax, by - ay
        pts, out = out, []
        prev = pts[-1]
        dprev = sign * (ex * (prev[1] - ay) - ey * (prev[0] - ax))
        for cur in pts:
            dcur = sign * (ex * (cur[1] - ay) - ey * (cur[0] - ax))
            if dcur >= 0:
                if dprev < 0:
                    t = dprev / (dprev - dcur)
                    out.append((prev[0] + t * (cur[0] - prev[0]), prev[1] + t * (cur[1] - prev[1])))
                out.append(cur)
            elif dprev >= 0:
                t = dprev / (dprev - dcur)
                out.append((prev[0] + t * (cur[0] - prev[0]), prev[1] + t * (cur[1] - prev[1])))
            prev, dprev = cur, dcur
    return out


def _area(poly: list[tuple[float, float]]) -> float:
    n = len(poly)
    return 0.5 * abs(
        sum(poly[i][0] * poly[(i + 1) % n][1] - poly[(i + 1) % n][0] * poly[i][1] for i in range(n))
    )


def coverage(block_pose: np.ndarray, goal_pose: np.ndarray = GOAL_POSE) -> float:
    """Fraction of the goal T covered by the block T (Diffusion Policy's reward basis).

    The T's two boxes share only an edge, so the intersection of two Ts is the sum of the four
    convex box-box intersections: exact, and several times cheaper than shapely.
    """
    block = tee_vertices(block_pose)
    goal = tee_vertices(goal_pose)
    inter = 0.0
    for g in goal:
        for b in block:
            poly = _clip([tuple(p) for p in b.tolist()], g.tolist())
            if len(poly) >= 3:
                inter += _area(poly)
    return inter / TEE_AREA


def reward_from_coverage(cov: float) -> float:
    """Diffusion Policy's reward: coverage scaled so that success coverage scores 1."""
    return float(np.clip(cov / SUCCESS_COVERAGE, 0.0, 1.0))


def registration_error(pose: np.ndarray, goal_pose: np.ndarray = GOAL_POSE) -> np.ndarray:
    """Mean distance (px) between the T's 8 vertices at ``pose`` and at ``goal_pose``."""
    a = tee_vertices(pose).reshape(np.shape(pose)[:-1] + (8, 2))
    b = tee_vertices(goal_pose).reshape(np.shape(goal_pose)[:-1] + (8, 2))
    return np.linalg.norm(a - b, axis=-1).mean(axis=-1)


def pose_cells(states: np.ndarray, bins: tuple[int, int, int] = (16, 16, 12)) -> set[int]:
    """Occupied cells of a (block x, block y, block angle) grid over [0, 512)^2 x [0, 2pi)."""
    states = np.asarray(states, dtype=np.float64)
    x = np.clip((states[:, 2] / WORKSPACE * bins[0]).astype(int), 0, bins[0] - 1)
    y = np.clip((states[:, 3] / WORKSPACE * bins[1]).astype(int), 0, bins[1] - 1)
    a = np.clip((states[:, 4] % (2 * np.pi) / (2 * np.pi) * bins[2]).astype(int), 0, bins[2] - 1)
    return set(((x * bins[1] + y) * bins[2] + a).tolist())
