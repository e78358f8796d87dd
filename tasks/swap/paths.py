"""Free space around the cube and the sphere, and the agent's shortest paths through it (world coordinates)."""

from __future__ import annotations

import numpy as np

from gpc.tasks.planar.paths import all_pairs, rotate
from gpc.tasks.planar.scene import AGENT_RADIUS, WALL_RADIUS, WALLS, WORKSPACE
from gpc.tasks.swap.geometry import CUBE_SIDE, SPHERE_RADIUS

R = AGENT_RADIUS
HALF_DIAGONAL = CUBE_SIDE / np.sqrt(2)
LO = float(WALLS[0][1][0]) + WALL_RADIUS + R + 3.0  # the box the agent's centre keeps to, clear of the walls
HI = WORKSPACE - LO - 1.0
_RING = 12  # waypoints around each object


def clearance(points: np.ndarray, cube_pose: np.ndarray, sphere_xy: np.ndarray) -> np.ndarray:
    """Distance (px) from world points ``(..., 2)`` to the nearer object (negative inside)."""
    p = np.asarray(points, dtype=np.float64)
    q = np.abs(rotate(p - cube_pose[:2], -cube_pose[2])) - CUBE_SIDE / 2
    cube = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)
    sphere = np.linalg.norm(p - sphere_xy, axis=-1) - SPHERE_RADIUS
    return np.minimum(cube, sphere)


def segments_clear(a: np.ndarray, b: np.ndarray, cube_pose: np.ndarray, sphere_xy: np.ndarray, gap: float) -> np.ndarray:
    """Whether segments ``a -> b`` (``(M, 2)`` each) keep ``gap`` from both objects."""
    t = np.linspace(0.0, 1.0, 48)[:, None]
    pts = a[:, None, :] + t * (b - a)[:, None, :]
    return clearance(pts, cube_pose, sphere_xy).min(axis=-1) >= gap


def in_workspace(points: np.ndarray) -> np.ndarray:
    return np.all((points >= LO) & (points <= HI), axis=-1)


def away(point: np.ndarray, cube_pose: np.ndarray, sphere_xy: np.ndarray) -> np.ndarray:
    """The unit direction in which clearance grows fastest at ``point`` (towards the middle where it is flat)."""
    p, eps = np.asarray(point, dtype=np.float64), 1e-3
    grad = np.array([float(clearance(p + [eps, 0.0], cube_pose, sphere_xy) - clearance(p - [eps, 0.0], cube_pose, sphere_xy)),
                     float(clearance(p + [0.0, eps], cube_pose, sphere_xy) - clearance(p - [0.0, eps], cube_pose, sphere_xy))])
    norm = np.linalg.norm(grad)
    return grad / norm if norm > 1e-9 else (WORKSPACE / 2 - p) / (np.linalg.norm(WORKSPACE / 2 - p) + 1e-9)


def escape(point: np.ndarray, cube_pose: np.ndarray, sphere_xy: np.ndarray, target: float) -> np.ndarray:
    """Climb the clearance field from ``point`` until ``target`` px clear (a few steps; corners bend the field)."""
    p = np.asarray(point, dtype=np.float64)
    for _ in range(8):
        gap = target - float(clearance(p, cube_pose, sphere_xy))
        if gap <= 0.5:
            break
        p = np.clip(p + away(p, cube_pose, sphere_xy) * gap, LO, HI)
    return p


def shortest_path(start: np.ndarray, goal: np.ndarray, cube_pose: np.ndarray, sphere_xy: np.ndarray, margin: float,
                  turn: float = 0.0) -> np.ndarray | None:
    """The shortest polyline from ``start`` to ``goal`` keeping ``R + margin / 2`` from both objects, or None.

    A visibility graph over rings of waypoints around the objects (turned by ``turn`` rad), walls ruling some out;
    a start too close to an object first backs away from it.
    """
    gap = R + margin / 2
    first = [np.asarray(start, dtype=np.float64)]
    if clearance(first[0], cube_pose, sphere_xy) < gap:
        first.append(escape(first[0], cube_pose, sphere_xy, R + margin))
    angles = turn + np.arange(_RING) * 2 * np.pi / _RING
    ring = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    nodes = np.vstack([first[-1][None], goal[None],
                       cube_pose[:2] + ring * (HALF_DIAGONAL + R + margin + 2.0),
                       sphere_xy + ring * (SPHERE_RADIUS + R + margin + 2.0)])
    usable = in_workspace(nodes) & (clearance(nodes, cube_pose, sphere_xy) >= gap)
    usable[:2] = True
    k = len(nodes)
    ii, jj = np.triu_indices(k, 1)
    vis = usable[ii] & usable[jj]
    vis[vis] = segments_clear(nodes[ii[vis]], nodes[jj[vis]], cube_pose, sphere_xy, gap)
    dist, nxt = all_pairs(nodes, ii, jj, vis)
    if not np.isfinite(dist[0, 1]):
        return None
    hops, u = [], 0
    while u != 1:
        u = int(nxt[u, 1])
        hops.append(nodes[u])
    return np.array(first + hops)
