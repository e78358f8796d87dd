"""gpc's own renderer of the stacking scene: shaded boxes through the fixed camera, with NumPy and OpenCV.

MuJoCo's renderer needs an OpenGL library from the system (EGL or OSMesa), which a pip install does not bring, so
frames are drawn from the 18-d state alone (the same function draws predicted states): the cubes from their poses,
the gripper's palm and fingers from its position and opening, projected through the model's camera (``scene``'s
position, axes and vertical field of view). Faces are lit as MuJoCo lights them (its headlight along the view and
the directional light from above, Lambert), back faces culled, boxes painted far to near. The table fills the view,
so it is the ground colour. ``tests/test_stack.py`` compares the frames with MuJoCo's own where OpenGL exists.
"""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np

from gpc.tasks.stack import geometry
from gpc.tasks.stack.scene import (
    BLUE,
    CAMERA_FOVY,
    CAMERA_POS,
    CAMERA_TARGET,
    CUBE_SIDE,
    FINGER,
    FINGER_Z,
    GRIPPER_RGBA,
    PALM,
    PALM_Z,
    RED,
    TABLE_RGBA,
)

SUPERSAMPLE = 4  # drawn at 4x the frame size, then averaged down (MuJoCo multisamples likewise)
AMBIENT, HEADLIGHT, TOPLIGHT = 0.35, 0.55, 0.3  # the MJCF's light intensities
_FACES = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])  # corner indices
_NORMALS = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.float64)
_SIGNS = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=np.float64) * 2 - 1  # corner i: (x, y, z) signs


@cache
def camera() -> tuple[np.ndarray, np.ndarray]:
    """The camera's position and its world-to-camera rotation rows (right, up, forward)."""
    pos = np.asarray(CAMERA_POS, dtype=np.float64)
    forward = np.subtract(CAMERA_TARGET, pos)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return pos, np.stack([right, np.cross(right, forward), forward])


def quat_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` of a quaternion ``(w, x, y, z)`` (normalised here)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def boxes(state: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, ...]]]:
    """Every box of an 18-d state: (centre, rotation, half sizes, RGB in [0, 1])."""
    s = np.asarray(state, dtype=np.float64)
    hand, half_gap, eye = s[geometry.GRIPPER], max(float(s[geometry.OPENING]), 0.0) / 2, np.eye(3)
    cube = np.full(3, CUBE_SIDE / 2)
    grey = GRIPPER_RGBA
    return [
        (s[geometry.RED], quat_matrix(s[geometry.RED_QUAT]), cube, RED),
        (s[geometry.BLUE], quat_matrix(s[geometry.BLUE_QUAT]), cube, BLUE),
        (hand + [0.0, 0.0, PALM_Z], eye, np.array(PALM), grey),
        (hand + [-half_gap - FINGER[0], 0.0, FINGER_Z], eye, np.array(FINGER), grey),
        (hand + [half_gap + FINGER[0], 0.0, FINGER_Z], eye, np.array(FINGER), grey),
    ]


def _shade(rgb: tuple[float, ...], normal: np.ndarray, forward: np.ndarray) -> tuple[int, int, int]:
    light = AMBIENT + HEADLIGHT * max(0.0, -float(normal @ forward)) + TOPLIGHT * max(0.0, float(normal[2]))
    out = np.clip(np.asarray(rgb) * light, 0.0, 1.0) * 255
    return (int(round(out[0])), int(round(out[1])), int(round(out[2])))


def draw_state(state: np.ndarray, size: int = 96) -> np.ndarray:
    """RGB ``(size, size, 3)`` uint8 frame of an 18-d state as the fixed camera sees it."""
    n = size * SUPERSAMPLE
    pos, rot = camera()
    focal = (n / 2) / np.tan(np.radians(CAMERA_FOVY) / 2)
    canvas = np.empty((n, n, 3), dtype=np.uint8)
    canvas[:] = _shade(TABLE_RGBA, np.array([0.0, 0.0, 1.0]), rot[2])
    shift = 4  # fractional bits of the polygon corners
    items = sorted(boxes(state), key=lambda b: -float(rot[2] @ (b[0] - pos)))
    for centre, r, half, rgb in items:
        corners = centre + (_SIGNS * half) @ r.T  # (8, 3)
        cam = (corners - pos) @ rot.T
        if np.any(cam[:, 2] <= 1e-3):
            continue  # behind the camera: never in this scene's workspace
        px = np.stack([n / 2 + focal * cam[:, 0] / cam[:, 2], n / 2 - focal * cam[:, 1] / cam[:, 2]], axis=1) - 0.5  # pixel centres
        for face, local in zip(_FACES, _NORMALS):
            normal = r @ local
            if normal @ (pos - corners[face].mean(axis=0)) <= 0:
                continue  # faces away from the camera
            pts = np.round(px[face] * (1 << shift)).astype(np.int32)
            cv2.fillConvexPoly(canvas, pts, _shade(rgb, normal, rot[2]), lineType=cv2.LINE_8, shift=shift)
    return cv2.resize(canvas, (size, size), interpolation=cv2.INTER_AREA)
