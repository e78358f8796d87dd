"""The drawing scene: Push-T's PD-controlled agent (``gpc.tasks.planar.scene``) as a pen that is always down, and
the ink it leaves on a 128 x 128 grid of 4 px cells (``geometry``).

Nothing is pushed: the agent's body only carries the pen, and the walls are out of its way. After each physics tick
the segment the pen moved along is inked (round-capped, ``PEN_RADIUS`` wide), so a control step's stroke follows
the PD path's curve, not a chord. Bookkeeping is incremental (cells newly inked are counted per band bin or off the
band), so a step costs one small stamp, not a pass over the canvas.
"""

from __future__ import annotations

import numpy as np

from gpc.tasks.draw import geometry
from gpc.tasks.draw.geometry import GRID, N_BINS, N_SUMMARY, Band
from gpc.tasks.planar.scene import AgentScene

STATE_DIM = 2 + 6 + N_SUMMARY  # pen x, y; the triangle's vertices; the ink summary
INK_DIM = GRID * GRID
SIM_DIM = 4 + 6 + INK_DIM  # pen x, y, vx, vy; vertices; the ink grid (0/1, row-major)


class DrawSim(AgentScene):
    """A pen under PD control, a target triangle and the ink drawn so far."""

    def __init__(self, vertices: np.ndarray | None = None) -> None:
        super().__init__()
        self.ink = np.zeros((GRID, GRID), dtype=bool)
        self._band_of: np.ndarray | None = None  # the vertices ``band`` was computed for (recomputed when they change)
        self.set_triangle(np.array([[156.0, 156.0], [356.0, 156.0], [256.0, 356.0]]) if vertices is None else vertices)

    def set_triangle(self, vertices: np.ndarray) -> None:
        """Make ``vertices`` ``(3, 2)`` the target (its band recomputed; the ink recounted against it)."""
        vertices = np.asarray(vertices, dtype=np.float64).reshape(3, 2)
        if self._band_of is None or not np.array_equal(vertices, self._band_of):
            self.band, self._band_of = Band.of(vertices), vertices.copy()
        self.vertices = vertices.copy()
        self._recount()

    def _recount(self) -> None:
        bins = self.band.bins[self.ink]
        self.bin_ink = np.bincount(bins[bins >= 0], minlength=3 * N_BINS).astype(np.int64)
        self.off_ink = int((bins < 0).sum())

    # ------------------------------------------------------------------ state
    def pen(self) -> np.ndarray:
        p = self.agent.position
        return np.array([p.x, p.y])

    def summary(self) -> np.ndarray:
        """``(N_SUMMARY,)``: each bin's inked cells, then the cells inked off the band, as shares of the band's cells."""
        return np.concatenate([self.bin_ink, [self.off_ink]]) / self.band.size

    def f1(self) -> float:
        return float(geometry.f1_from_counts(self.bin_ink.sum(), self.off_ink, self.band.size))

    def state(self) -> np.ndarray:
        """``[pen x, y, vertex 0 x, y, vertex 1 x, y, vertex 2 x, y, ink summary (25)]``."""
        return np.concatenate([self.pen(), self.vertices.ravel(), self.summary()])

    def vector(self) -> np.ndarray:
        """``(SIM_DIM,)`` float64: pen position and velocity, the triangle, the ink grid: all ``restore`` needs."""
        a, v = self.agent.position, self.agent.velocity
        return np.concatenate([[a.x, a.y, v.x, v.y], self.vertices.ravel(), self.ink.ravel().astype(np.float64)])

    def restore(self, vector: np.ndarray) -> None:
        """Return the pen, the triangle and the ink to ``vector`` exactly."""
        vector = np.asarray(vector, dtype=np.float64)
        if vector.shape != (SIM_DIM,):
            raise ValueError(f"a drawing scene's vector has {SIM_DIM} entries, got shape {vector.shape}")
        self.agent.position, self.agent.velocity = (float(vector[0]), float(vector[1])), (float(vector[2]), float(vector[3]))
        self.ink = vector[10:].reshape(GRID, GRID) > 0.5
        self.set_triangle(vector[4:10])

    def place_pen(self, xy: np.ndarray) -> None:
        """Put the pen down at rest on ``xy`` (inking its disc there); no tick is stepped."""
        self.agent.position, self.agent.velocity = (float(xy[0]), float(xy[1])), (0.0, 0.0)
        self._ink_path(np.asarray(xy, dtype=np.float64)[None])

    # ------------------------------------------------------------------ dynamics
    def _ink_path(self, path: np.ndarray) -> None:
        rows, cols, near = geometry.stamp(path)
        new = near & ~self.ink[rows, cols]
        if new.any():
            self.ink[rows, cols] |= new
            bins = self.band.bins[rows, cols][new]
            self.bin_ink += np.bincount(bins[bins >= 0], minlength=3 * N_BINS)
            self.off_ink += int((bins < 0).sum())

    def step(self, action: np.ndarray) -> np.ndarray:
        """Track target ``action`` (px) for one control period, inking the pen's path tick by tick; the path
        ``(SUBSTEPS + 1, 2)`` (where the pen was, then after each tick)."""
        trace = [(self.agent.position.x, self.agent.position.y)]
        self.drive(action, trace)
        path = np.asarray(trace)
        self._ink_path(path)
        return path
