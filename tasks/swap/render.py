"""OpenCV renderer of the swap scene, in Push-T's style (``gpc.tasks.planar.draw``: white ground, walls, agent).

The targets are outlines in their objects' colours (the cube's oriented as the cube is now, since its orientation
does not count); the cube is filled red with a darker edge, the sphere green; draw order as Push-T's: targets,
walls, agent, objects.
"""

from __future__ import annotations

import cv2
import numpy as np

from gpc.tasks.planar.draw import blank, draw_agent, draw_walls, fat_polyline, finish, ipts
from gpc.tasks.swap.geometry import CUBE_KEYPOINTS, SPHERE_RADIUS, cube_keypoints

CUBE_EDGE = (205, 92, 92)  # IndianRed (RGB); fills 1.2x lighter, as Push-T's
CUBE_FILL = (246, 110, 110)
SPHERE_EDGE = (60, 179, 113)  # MediumSeaGreen
SPHERE_FILL = (72, 214, 135)
TARGET_WIDTH = 8  # px at 512: about 1.5 px in a 96 px frame
_N_CORNERS = len(CUBE_KEYPOINTS) - 1


def draw_state(state: np.ndarray, goal: np.ndarray | None, size: int = 96) -> np.ndarray:
    """RGB ``(size, size, 3)`` uint8 frame of a 7-d state with its 4-d goal (None: no targets drawn, e.g. a video of
    states alone)."""
    state = np.asarray(state, dtype=np.float64)
    canvas = blank()
    if goal is not None:
        goal = np.asarray(goal, dtype=np.float64)
        target_pose = np.array([goal[0], goal[1], state[4]])
        cv2.polylines(canvas, [ipts(cube_keypoints(target_pose)[:_N_CORNERS])], True, CUBE_EDGE, thickness=TARGET_WIDTH)
        cv2.circle(canvas, tuple(ipts(goal[2:4]).tolist()), int(round(SPHERE_RADIUS - TARGET_WIDTH / 2)), SPHERE_EDGE,
                   thickness=TARGET_WIDTH)
    draw_walls(canvas)
    draw_agent(canvas, state[:2])
    corners = cube_keypoints(state[2:5])[:_N_CORNERS]
    cv2.fillPoly(canvas, [ipts(corners)], CUBE_FILL)
    fat_polyline(canvas, corners, 2.0, CUBE_EDGE)
    centre = tuple(ipts(state[5:7]).tolist())
    cv2.circle(canvas, centre, int(round(SPHERE_RADIUS)), SPHERE_EDGE, thickness=-1)
    cv2.circle(canvas, centre, int(round(SPHERE_RADIUS - 2)), SPHERE_FILL, thickness=-1)
    return finish(canvas, size)
