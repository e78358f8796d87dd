"""OpenCV renderer of the drawing canvas, in Push-T's style (``gpc.tasks.planar.draw``): white ground, the target
faint (the outline widened by the pen's width, in a pale blue), the ink dark, the pen a RoyalBlue ring (so the ink
under it stays visible). Draw order: target, ink, pen; the walls are not drawn (nothing meets them).

``draw_state`` draws a (predicted) state vector, which keeps no map of the ink: each bin of the outline is drawn
shaded by the share of it that is inked, and ink off the outline is not drawn.
"""

from __future__ import annotations

import cv2
import numpy as np

from gpc.tasks.draw.geometry import CELL, N_BINS, PEN_RADIUS, Band
from gpc.tasks.planar.draw import AGENT_EDGE, blank, fat_polyline, fat_segment, finish, ipts

TARGET = (222, 232, 248)  # faint: a 96 px frame shows where to draw without reading as ink
INK = (25, 25, 40)
PEN_RING = 3  # px at 512


def _target(canvas: np.ndarray, vertices: np.ndarray) -> None:
    fat_polyline(canvas, np.asarray(vertices, dtype=np.float64), PEN_RADIUS, TARGET)


def _pen(canvas: np.ndarray, pen: np.ndarray) -> None:
    cv2.circle(canvas, tuple(ipts(np.asarray(pen, float)).tolist()), int(PEN_RADIUS + PEN_RING), AGENT_EDGE, thickness=PEN_RING)


def draw_scene(vertices: np.ndarray, ink: np.ndarray, pen: np.ndarray, size: int = 96) -> np.ndarray:
    """RGB ``(size, size, 3)`` uint8 frame of the true canvas: the ink grid ``(128, 128)`` bool as 4 px squares."""
    canvas = blank()
    _target(canvas, vertices)
    scale = int(CELL)
    canvas[np.repeat(np.repeat(ink, scale, axis=0), scale, axis=1)] = INK
    _pen(canvas, pen)
    return finish(canvas, size)


def draw_state(state: np.ndarray, goal: np.ndarray | None = None, size: int = 96) -> np.ndarray:
    """RGB frame of a 33-d state (``goal`` unused: the triangle is in the state): each bin shaded by its inked share."""
    state = np.asarray(state, dtype=np.float64)
    vertices = state[2:8].reshape(3, 2)
    band = Band.of(vertices)
    shares = np.clip(state[8:8 + 3 * N_BINS] * band.size / np.maximum(band.bin_sizes, 1), 0.0, 1.0)
    canvas = blank()
    _target(canvas, vertices)
    for edge in range(3):
        a, b = vertices[edge], vertices[(edge + 1) % 3]
        for j in range(N_BINS):
            share = shares[edge * N_BINS + j]
            if share > 0.02:
                colour = tuple(int(round(t + share * (k - t))) for t, k in zip(TARGET, INK))
                fat_segment(canvas, a + (b - a) * j / N_BINS, a + (b - a) * (j + 1) / N_BINS, PEN_RADIUS, colour)  # type: ignore[arg-type]
    _pen(canvas, state[:2])
    return finish(canvas, size)
