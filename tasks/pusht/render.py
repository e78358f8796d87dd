"""OpenCV renderer reproducing Diffusion Policy's pygame frames (no pygame needed).

Drawn at the 512 px workspace resolution with the original's colours, outline widths and
draw order, then resized like the original, so recorded frames and ours differ by well
under one grey level on average.
"""

from __future__ import annotations

import cv2
import numpy as np

from gpc.tasks.planar.draw import blank, draw_agent, draw_plan, draw_walls, fat_polyline, finish, ipts
from gpc.tasks.pusht.geometry import GOAL_POSE, TEE_BOXES, WORKSPACE, tee_vertices, to_world

__all__ = ["draw_futures", "draw_plan", "draw_scene", "draw_state"]

# RGB colours of the original (pygame named colours; fills are 1.2x lighter, capped at 255); the agent's and the
# walls' are every planar task's (gpc.tasks.planar.draw).
GOAL = (144, 238, 144)  # LightGreen
BLOCK_EDGE = (119, 136, 153)  # LightSlateGray
BLOCK_FILL = (143, 163, 184)


def draw_scene(
    agent_xy: np.ndarray,
    block_pose: np.ndarray,
    goal_pose: np.ndarray = GOAL_POSE,
    size: int = 96,
) -> np.ndarray:
    """RGB ``(size, size, 3)`` uint8 frame of one scene."""
    canvas = blank()
    for box in TEE_BOXES:
        cv2.fillPoly(canvas, [ipts(to_world(box, goal_pose))], GOAL)
    draw_walls(canvas)
    draw_agent(canvas, agent_xy)
    for box in TEE_BOXES:
        world = to_world(box, block_pose)
        cv2.fillPoly(canvas, [ipts(world)], BLOCK_FILL)
        fat_polyline(canvas, world, 2.0, BLOCK_EDGE)
    return finish(canvas, size)


def draw_state(state: np.ndarray, goal_pose: np.ndarray = GOAL_POSE, size: int = 96) -> np.ndarray:
    """Frame for a 5-d state vector ``[agent xy, block xy, block angle]``."""
    state = np.asarray(state, dtype=np.float64)
    return draw_scene(state[:2], state[2:5], goal_pose, size)


def draw_futures(frame: np.ndarray, futures: np.ndarray, scores: np.ndarray, chosen: int, top: int = 5) -> np.ndarray:
    """Overlay K predicted futures ``(K, T, 5)`` (states) on an RGB frame, in place.

    Each candidate's predicted agent path is a thin line coloured by its score (blue: worst,
    red: best); the predicted final block outline of the ``top`` best is drawn, the chosen
    one thick and green. This is the picture behind "why did it pick that?".
    """
    scale = frame.shape[0] / WORKSPACE
    scores = np.asarray(scores, dtype=np.float64)
    lo, hi = float(scores.min()), float(scores.max())
    rank = (scores - lo) / (hi - lo) if hi > lo else np.ones_like(scores)
    order = np.argsort(scores)  # worst first, so the best are drawn on top
    for k in order:
        colour = (int(255 * rank[k]), 60, int(255 * (1 - rank[k])))
        pts = np.round(futures[k, :, :2] * scale).astype(np.int32)
        cv2.polylines(frame, [pts], False, colour, thickness=1, lineType=cv2.LINE_AA)
    for k in list(order[::-1][:top]) + [chosen]:
        width, colour = (2, (0, 160, 0)) if k == chosen else (1, (90, 90, 90))
        for box in tee_vertices(futures[k, -1, 2:5]):
            cv2.polylines(frame, [np.round(box * scale).astype(np.int32)], True, colour, thickness=width, lineType=cv2.LINE_AA)
    cv2.putText(frame, f"K={len(scores)} best {hi:.1f}", (4, frame.shape[0] - 6), cv2.FONT_HERSHEY_SIMPLEX,
                frame.shape[0] / 900, (0, 0, 0), 1, cv2.LINE_AA)
    return frame
