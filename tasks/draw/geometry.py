"""Triangle Drawing geometry: the seed's triangle, the ink grid, the outline band, its bins, and the F1 reward.

Ink lives on a coarse grid of ``CELL`` = 4 px cells (128 x 128 over the 512 px canvas): a cell is inked once its
centre has come within ``PEN_RADIUS`` of the pen's path. The target is the triangle's outline widened by the pen's
width: the cells whose centre lies within ``PEN_RADIUS`` of the outline (the *band*), so a pen that runs exactly
along the outline inks exactly the band. The reward is the F1 (Dice) score of inked cells against the band,
``2 |ink & band| / (|ink| + |band|)``: ink off the outline lowers it as missing ink does. F1 rather than IoU because a
PD-tracked pen a pixel or two off the line loses IoU twice as fast (F1 = 2 IoU / (1 + IoU)), and success (F1 > 0.9)
should mean a recognisable, tidy triangle, not a pixel-exact one.

The band is split into ``N_BINS`` bins along each edge (a band cell belongs to its nearest edge and to the bin its
projection falls in, corners to the end bins), so the state can say which parts are drawn; the state keeps each
bin's inked cells and the ink off the band as shares of the band's cells, which makes the F1 an exact function of
the state (``f1_from_summary``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpc.tasks.planar.scene import WORKSPACE

CELL = 4.0  # px per ink cell
GRID = int(WORKSPACE / CELL)  # 128 cells a side
PEN_RADIUS = 10.0  # px: the ink's half-width (a 20 px stroke)
N_BINS = 8  # bins along each edge
N_SUMMARY = 3 * N_BINS + 1  # the bins' ink shares, then the ink off the band
SUCCESS_F1 = 0.90
CENTRES = (np.arange(GRID) + 0.5) * CELL  # cell centres along x (columns) and y (rows)
# The seed's triangle: circumradius, centre and corner spread.
RADIUS_RANGE = (120.0, 175.0)
CENTRE_RANGE = (200.0, 312.0)
ANGLE_JITTER = 0.35  # rad: each corner's angle about the centre moves this far off the equilateral one
MIN_EDGE, MIN_ANGLE, MARGIN = 150.0, np.deg2rad(35.0), 40.0  # redraw triangles with a shorter edge, a sharper corner, or
# a corner nearer the canvas edge than this


def draw_triangle(rs: np.random.RandomState) -> np.ndarray:
    """Vertices ``(3, 2)`` drawn from ``rs`` (in order of increasing angle about the centre), redrawn until they fit."""
    while True:
        centre = rs.uniform(*CENTRE_RANGE, 2)
        radius = rs.uniform(*RADIUS_RANGE)
        angles = rs.uniform(-np.pi, np.pi) + np.arange(3) * 2 * np.pi / 3 + rs.uniform(-ANGLE_JITTER, ANGLE_JITTER, 3)
        vertices = centre + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)
        if (vertices.min() >= MARGIN and vertices.max() <= WORKSPACE - MARGIN and edge_lengths(vertices).min() >= MIN_EDGE
                and corner_angles(vertices).min() >= MIN_ANGLE):
            return vertices


def edge_lengths(vertices: np.ndarray) -> np.ndarray:
    """Edge ``i`` runs from vertex ``i`` to vertex ``i + 1`` (mod 3)."""
    return np.linalg.norm(np.roll(vertices, -1, axis=0) - vertices, axis=1)


def corner_angles(vertices: np.ndarray) -> np.ndarray:
    a, b = np.roll(vertices, 1, axis=0) - vertices, np.roll(vertices, -1, axis=0) - vertices
    cos = (a * b).sum(axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.arccos(np.clip(cos, -1.0, 1.0))


def segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from points ``p`` ``(..., 2)`` to the segment ``a -> b``, and the projection's place ``t`` in [0, 1]."""
    ab, ap = b - a, p - a
    t = np.clip((ap * ab).sum(axis=-1) / max(float((ab * ab).sum()), 1e-12), 0.0, 1.0)
    return np.linalg.norm(ap - t[..., None] * ab, axis=-1), t


_CELLS = np.stack(np.meshgrid(CENTRES, CENTRES), axis=-1)  # (GRID, GRID, 2): each cell's centre (x, y), rows along y


def cell_points(rows: slice = slice(0, GRID), cols: slice = slice(0, GRID)) -> np.ndarray:
    """Centres ``(R, C, 2)`` (x, y) of a block of cells."""
    return _CELLS[rows, cols]


@dataclass(frozen=True)
class Band:
    """The target band of one triangle: ``bins`` ``(GRID, GRID)`` holds each band cell's bin (edge * N_BINS + bin
    along it, edges and bins in the vertices' order) and -1 off the band; ``size``: its cells."""

    bins: np.ndarray
    size: int
    bin_sizes: np.ndarray  # (3 * N_BINS,) cells per bin

    @classmethod
    def of(cls, vertices: np.ndarray) -> Band:
        points = cell_points()
        dist, place = zip(*(segment_distance(points, vertices[i], vertices[(i + 1) % 3]) for i in range(3)))
        d, t = np.stack(dist), np.stack(place)
        edge = d.argmin(axis=0)
        along = np.take_along_axis(t, edge[None], axis=0)[0]
        bins = np.where(d.min(axis=0) <= PEN_RADIUS, edge * N_BINS + np.minimum((along * N_BINS).astype(int), N_BINS - 1), -1)
        sizes = np.bincount(bins[bins >= 0], minlength=3 * N_BINS)
        return cls(bins=bins.astype(np.int16), size=int(sizes.sum()), bin_sizes=sizes)


def stamp(path: np.ndarray) -> tuple[slice, slice, np.ndarray]:
    """The cells a pen moving along ``path`` ``(P, 2)`` (straight between points) inks: a block of the grid and its
    ``(R, C)`` mask, every segment at once (one vectorised pass, however many ticks the path has)."""
    lo = np.clip(np.floor((path.min(axis=0) - PEN_RADIUS) / CELL).astype(int), 0, GRID)
    hi = np.clip(np.ceil((path.max(axis=0) + PEN_RADIUS) / CELL).astype(int) + 1, 0, GRID)
    rows, cols = slice(int(lo[1]), int(hi[1])), slice(int(lo[0]), int(hi[0]))
    points = _CELLS[rows, cols][:, :, None]  # (R, C, 1, 2)
    a, ab = path[:-1] if len(path) > 1 else path, np.diff(path, axis=0) if len(path) > 1 else np.zeros((1, 2))
    ap = points - a  # (R, C, S, 2)
    t = np.clip((ap * ab).sum(axis=-1) / np.maximum((ab * ab).sum(axis=-1), 1e-12), 0.0, 1.0)
    gap = ap - t[..., None] * ab
    return rows, cols, ((gap * gap).sum(axis=-1) <= PEN_RADIUS**2).any(axis=-1)


def f1_from_counts(on_band: int | np.ndarray, off_band: int | np.ndarray, band: int | np.ndarray) -> np.ndarray:
    """``2 |ink & band| / (|ink| + |band|)`` from cell counts."""
    on, off, size = (np.asarray(v, dtype=np.float64) for v in (on_band, off_band, band))
    return 2.0 * on / np.maximum(on + off + size, 1e-12)


def f1_from_summary(summary: np.ndarray) -> np.ndarray:
    """The F1 from ink summaries ``(..., N_SUMMARY)`` (bins' shares of the band, then the off-band share)."""
    summary = np.asarray(summary, dtype=np.float64)
    recall = summary[..., :-1].sum(axis=-1)
    return 2.0 * recall / np.maximum(recall + summary[..., -1] + 1.0, 1e-12)


def is_success(f1: np.ndarray | float) -> np.ndarray:
    return np.asarray(f1) > SUCCESS_F1
