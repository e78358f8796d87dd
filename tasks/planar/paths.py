"""Moving the agent's target along planned paths: what every scripted controller of a planar task needs."""

from __future__ import annotations

import numpy as np


def rotate(v: np.ndarray, angle: float | np.ndarray) -> np.ndarray:
    """Vectors ``(..., 2)`` turned by ``angle`` (rad, counter-clockwise in pymunk's frame)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def follow(path: np.ndarray, s: float, speed: float, agent: np.ndarray, max_lead: float) -> tuple[float, np.ndarray]:
    """Advance arc length ``s`` along ``path`` by up to ``speed`` without running ``max_lead`` ahead of the disc."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    for step in (speed, 0.5 * speed, 0.0):
        s_new = min(s + step, cum[-1])
        i = int(np.clip(np.searchsorted(cum, s_new, side="right") - 1, 0, len(seg) - 1))
        point = path[i] + min((s_new - cum[i]) / max(seg[i], 1e-9), 1.0) * (path[i + 1] - path[i])
        if np.linalg.norm(point - agent) <= max_lead:
            break
    return s_new, point


def all_pairs(nodes: np.ndarray, ii: np.ndarray, jj: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shortest paths between every two of ``nodes`` ``(K, 2)`` over the straight edges ``(ii, jj)`` that are
    ``visible`` (Floyd-Warshall): distances ``(K, K)`` and each path's next node ``(K, K)``."""
    k = len(nodes)
    dist = np.full((k, k), np.inf)
    np.fill_diagonal(dist, 0.0)
    dist[ii[visible], jj[visible]] = dist[jj[visible], ii[visible]] = np.linalg.norm(nodes[ii] - nodes[jj], axis=1)[visible]
    nxt = np.tile(np.arange(k), (k, 1))
    for m in range(k):
        via = dist[:, m, None] + dist[None, m, :]
        better = via < dist
        dist, nxt = np.where(better, via, dist), np.where(better, nxt[:, m, None], nxt)
    return dist, nxt
