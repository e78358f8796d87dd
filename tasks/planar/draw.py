"""OpenCV drawing of planar scenes as Diffusion Policy's pygame renderer draws them (no pygame needed).

Scenes are drawn at the 512 px workspace resolution, in the original's colours, outline widths and order, then
resized; a task draws its goal first, then ``draw_walls`` and ``draw_agent``, then its objects.
"""

from __future__ import annotations

import cv2
import numpy as np

from gpc.tasks.planar.scene import AGENT_RADIUS, WALL_RADIUS, WALLS, WORKSPACE

Colour = tuple[int, int, int]
# RGB colours of the original (pygame named colours; fills are 1.2x lighter, capped at 255).
AGENT_EDGE = (65, 105, 225)  # RoyalBlue
AGENT_FILL = (78, 126, 255)
WALL = (211, 211, 211)  # LightGray
SIZE = int(WORKSPACE)


def ipts(points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (rounded) of workspace points."""
    return np.round(points).astype(np.int32)


def blank() -> np.ndarray:
    """A white workspace-sized RGB canvas."""
    return np.full((SIZE, SIZE, 3), 255, dtype=np.uint8)


def fat_segment(canvas: np.ndarray, a: np.ndarray, b: np.ndarray, radius: float, color: Colour) -> None:
    """A round-capped segment, as pymunk's debug draw makes it."""
    pa, pb = ipts(a), ipts(b)
    cv2.line(canvas, tuple(pa.tolist()), tuple(pb.tolist()), color, thickness=int(round(2 * radius)))
    for p in (pa, pb):
        cv2.circle(canvas, tuple(p.tolist()), int(round(radius)), color, thickness=-1)


def fat_polyline(canvas: np.ndarray, pts: np.ndarray, radius: float, color: Colour) -> None:
    """A closed outline of round-capped segments."""
    for a, b in zip(pts, np.roll(pts, -1, axis=0)):
        fat_segment(canvas, a, b, radius, color)


def draw_walls(canvas: np.ndarray) -> None:
    for a, b in WALLS:
        fat_segment(canvas, np.asarray(a, float), np.asarray(b, float), WALL_RADIUS, WALL)


def draw_agent(canvas: np.ndarray, agent_xy: np.ndarray) -> None:
    center = tuple(ipts(np.asarray(agent_xy, float)).tolist())
    cv2.circle(canvas, center, int(round(AGENT_RADIUS)), AGENT_EDGE, thickness=-1)
    cv2.circle(canvas, center, int(round(AGENT_RADIUS - 4)), AGENT_FILL, thickness=-1)


def finish(canvas: np.ndarray, size: int) -> np.ndarray:
    """The workspace canvas as a ``(size, size, 3)`` frame (resized as the original resizes)."""
    if size == SIZE:
        return canvas
    return cv2.resize(canvas, (size, size))


def draw_plan(frame: np.ndarray, chunk: np.ndarray, executed: int) -> np.ndarray:
    """Overlay a planned action chunk ``(T, 2)`` (px targets) on an RGB frame, in place.

    The part about to be executed is drawn in red, the rest of the plan in orange.
    """
    scale = frame.shape[0] / WORKSPACE
    pts = np.round(np.asarray(chunk, dtype=np.float64) * scale).astype(np.int32)
    radius = max(1, frame.shape[0] // 128)
    for i, p in enumerate(pts):
        color = (220, 30, 30) if i < executed else (255, 165, 0)
        cv2.circle(frame, tuple(p.tolist()), radius, color, thickness=-1)
        if i:
            cv2.line(frame, tuple(pts[i - 1].tolist()), tuple(p.tolist()), color, thickness=max(1, radius // 2))
    return frame
