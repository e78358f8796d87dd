"""The drawing's reward on predicted states, differentiable (torch): the ink's F1, read from where the pen goes.

A state's summary holds each outline bin's inked share of the band and the share inked off it, so
``F1 = 2 R / (R + off + 1)`` with ``R`` the bins' sum (``geometry.f1_from_summary``, exact on true states). Scoring a
predicted future by its predicted summary ranks the policy's proposals no better than chance (validation seeds, in
docs/tasks.md): a state model forecasts the pen's path well and the few hundredths of ink a chunk adds poorly. The
ink is a function of the path (the scene inks every cell within ``PEN_RADIUS`` of it), so the reward takes only the
first predicted step's summary and draws the rest from the predicted pen: each bin gains the part of its empty share
that the path covers (points spread over the bin, each covered by a sigmoid of its distance to the path), and each
stretch of path adds ink off the outline as wide as the pen strays from it. Against the true summaries of recorded
windows (16 steps), the estimate's F1 is within 0.006 of the truth and its changes correlate 0.998 with the true ones.
The task names it ``gpc.tasks.draw.reward:from_layout``, which ``gpc.models.rewards.state`` imports on first use
(tasks never import models).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from gpc.tasks.draw.geometry import N_BINS, N_SUMMARY, PEN_RADIUS

SUMMARY_START = 8  # pen (2) and vertices (6) come first
ALONG = 4  # points per bin along its edge
ACROSS = (-2.0 / 3.0, 0.0, 2.0 / 3.0)  # their offsets across the band, in pen radii
SOFTNESS = 0.75  # px: the sigmoid's scale at the pen's edge (a gradient for GPC-OPT where a hard edge has none)


def f1(recall: torch.Tensor, off: torch.Tensor) -> torch.Tensor:
    return 2.0 * recall / (recall + off + 1.0)


def segment_distance(points: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distances ``(..., Q, S)`` from points ``(..., Q, 1, 2)`` to segments ``a -> b`` ``(..., 1, S, 2)``."""
    ab, ap = b - a, points - a
    t = ((ap * ab).sum(-1) / (ab * ab).sum(-1).clamp(min=1e-9)).clamp(0.0, 1.0)
    gap = ap - t[..., None] * ab
    return (gap * gap).sum(-1).clamp(min=1e-9).sqrt()


def rotations(states: torch.Tensor) -> torch.Tensor:
    """``(N, D)`` -> ``(N, 3, D)``: the three labellings of one picture (each corner first; the seed's first corner
    is where the pen started, which a frame does not show). The reward is the same on each: every bin keeps its edge,
    the edges their order (``draw_triangle`` lists the corners by increasing angle)."""
    end = SUMMARY_START + 3 * N_BINS
    corners, bins = states[:, 2:SUMMARY_START].reshape(-1, 3, 2), states[:, SUMMARY_START:end].reshape(-1, 3, N_BINS)
    return torch.stack([torch.cat([states[:, :2], corners.roll(-r, 1).flatten(1), bins.roll(-r, 1).flatten(1), states[:, end:]], 1)
                        for r in range(3)], dim=1)


class InkReward(nn.Module):
    """``(K, T, D)`` predicted states -> ``(K,)`` scores: the last step's F1 (``aggregate="final"``) or the
    discounted sum of every step's (``"discounted"``); the goal is unused (the triangle is in the state)."""

    along: torch.Tensor
    across: torch.Tensor
    # Even the final score reads every step (the first's summary, then the pen's path): an image reward must read a
    # state from every predicted frame, not the last alone (``gpc.models.rewards.state``).
    reads_path = True

    def __init__(self, aggregate: str = "final", discount: float = 0.99) -> None:
        super().__init__()
        self.aggregate, self.discount = aggregate, discount
        along = (torch.arange(N_BINS, dtype=torch.float32)[:, None] + (torch.arange(ALONG) + 0.5)[None] / ALONG) / N_BINS
        self.register_buffer("along", along.reshape(1, 1, N_BINS, ALONG, 1, 1), persistent=False)
        self.register_buffer("across", torch.tensor(ACROSS).reshape(1, 1, 1, 1, -1, 1) * PEN_RADIUS, persistent=False)

    def per_step(self, futures: torch.Tensor) -> torch.Tensor:
        """``(K, T, D)`` -> ``(K, T)``: step 0's F1 from its summary, each later step's from the path since."""
        if futures.dim() != 3 or futures.shape[-1] < SUMMARY_START + N_SUMMARY:
            raise ValueError(f"states: expected (K, T, D >= {SUMMARY_START + N_SUMMARY}), got {tuple(futures.shape)}")
        k, t, _ = futures.shape
        start = futures[:, 0, SUMMARY_START:SUMMARY_START + N_SUMMARY].clamp(min=0.0)
        bins, off = start[:, :-1], start[:, -1]
        first = f1(bins.sum(-1), off)[:, None]
        if t == 1:
            return first
        pen = futures[..., 0:2]
        a = futures[:, 0, 2:SUMMARY_START].reshape(k, 3, 2)  # edge i runs from vertex i to vertex i + 1
        edge = a.roll(-1, dims=1) - a
        length = edge.norm(dim=-1).clamp(min=1e-6)  # (K, 3)
        total = length.sum(-1, keepdim=True)
        normal = torch.stack([-edge[..., 1], edge[..., 0]], dim=-1) / length[..., None]
        points = (a[:, :, None, None, None] + self.along * edge[:, :, None, None, None]
                  + self.across * normal[:, :, None, None, None])  # (K, 3, N_BINS, ALONG, len(ACROSS), 2)
        dist = segment_distance(points.reshape(k, -1, 1, 2), pen[:, None, :-1], pen[:, None, 1:])  # (K, Q, T - 1)
        nearest = torch.cummin(dist, dim=-1).values  # each point's distance to the path so far
        # the pen's own disc at step 0 is inked already (the summary counts it): only the rest of the path is new
        here = torch.sigmoid((PEN_RADIUS - (points.reshape(k, -1, 2) - pen[:, :1]).norm(dim=-1)) / SOFTNESS)  # (K, Q)
        new = torch.sigmoid((PEN_RADIUS - nearest) / SOFTNESS) * (1.0 - here)[..., None]
        new, here = new.reshape(k, 3 * N_BINS, -1, t - 1).mean(dim=2), here.reshape(k, 3 * N_BINS, -1).mean(dim=2)
        full = (length / (N_BINS * total)).repeat_interleave(N_BINS, dim=1)  # a bin's share of the band, inked whole
        # the rest of a bin's ink lies where the disc is not, anywhere: the path finds it empty in proportion
        empty = (full - bins).clamp(min=0.0) / (1.0 - here).clamp(min=0.1)
        drawn = bins[..., None] + empty[..., None] * new  # (K, 3 N_BINS, T - 1)
        # off the outline: a stroke whose centre is d from it leaves min(d, 2 r) of its width outside the band
        a_seg, b_seg = pen[:, :-1], pen[:, 1:]
        probes = torch.stack([a_seg, 0.5 * (a_seg + b_seg), b_seg], dim=2).reshape(k, -1, 1, 2)  # (K, 3 (T - 1), 1, 2)
        stray = segment_distance(probes, a[:, None], a.roll(-1, dims=1)[:, None]).min(dim=-1).values
        width = stray.reshape(k, t - 1, 3).clamp(0.0, 2.0 * PEN_RADIUS).mean(dim=-1)
        outside = off[:, None] + torch.cumsum((b_seg - a_seg).norm(dim=-1) * width, dim=1) / (total * 2.0 * PEN_RADIUS)
        later = f1(drawn.sum(dim=1), outside)  # (K, T - 1)
        return torch.cat([first, later], dim=1)

    def forward(self, futures: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
        rewards = self.per_step(futures)
        if self.aggregate == "final":
            return rewards[:, -1]
        weights = self.discount ** torch.arange(rewards.shape[1], dtype=rewards.dtype, device=rewards.device)
        return (rewards * weights).sum(dim=1)


def from_layout(layout: Any, config: Any) -> InkReward:
    """The factory ``register_state_reward`` takes: ``config`` is a ``gpc.models.rewards.registration.RewardConfig``."""
    return InkReward(config.aggregate, config.discount)
