"""Reading every object's pose, and the agent's presence, from RGB frames: what a planner reads from a predicted frame.

SSIM rewards blur, so the figures that matter for a visual world model come from a readout: each object's pose
read from a frame by colour segmentation (``ColourReadout``: the centroid of the object's colour and the angle of
its drawn shape, modulo the shape's symmetry) or by the learned reward's pose predictor (``LearnedPoseReadout``),
against the pose read the same way from the recorded frame. ``ColourReadout.from_layout`` takes every object's
colours, angle offset and symmetry from the task's ``FrameLayout``; nothing here knows a task.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from gpc.datasets.layout import TaskLayout
from gpc.models.rewards.registration import registration_distance

Colour = tuple[int, int, int]


@dataclass(frozen=True)
class ObjectReadout:
    """One object as a readout reads it: its colours, whether and how its angle is read, its outline.

    With ``symmetry`` 1 the angle is its principal axis' (largest spread), oriented towards its skew (its long
    tail); with ``symmetry`` n > 1 the angle of its n-th angular moment over n, so defined modulo ``2 pi / n``
    (a square's 90 degrees). ``angle_offset`` is added either way.
    """

    name: str
    colours: tuple[Colour, ...]
    angle: bool = True  # whether its angle is read and compared
    angle_offset: float = 0.0
    symmetry: int = 1
    tolerance: float = 40.0  # RGB distance (0..255) within which a pixel is the object's
    vertices: tuple[tuple[float, float], ...] = ()  # its outline in its body frame; () or one point skips the vertex error
    centroid: tuple[float, float] = (0.0, 0.0)  # its area centroid in the body frame: the position colour reads

    @property
    def period(self) -> float:
        """The turn after which it looks the same (radians)."""
        return 2.0 * math.pi / self.symmetry

    def turn(self, pred: np.ndarray, true: np.ndarray) -> np.ndarray:
        """Signed angle from ``true`` to ``pred``, wrapped into ``[-period / 2, period / 2)``."""
        half = self.period / 2.0
        return (pred - true + half) % self.period - half


def pose_errors(obj: ObjectReadout, pred: np.ndarray, true: np.ndarray, vertices: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """``(..., 3)`` poses of one object -> position error, angle error (degrees, modulo its symmetry; where its angle
    is read) and, given its ``(V, 2)`` outline (V > 1), the mean distance between its vertices placed at both poses
    (ADD: position and angle in one length, what the registration reward compares); a missing prediction is NaN."""
    out = {"object_units": np.linalg.norm(pred[..., :2] - true[..., :2], axis=-1)}
    if obj.angle:
        turn = obj.turn(pred[..., 2], true[..., 2])
        out["object_deg"] = np.abs(turn) * (180.0 / np.pi)
        if vertices is not None and len(vertices) > 1:
            if obj.symmetry > 1:  # the nearest look-alike turn: a square turned by 90 degrees is the same square
                pred = np.concatenate([pred[..., :2], (true[..., 2] + turn)[..., None]], axis=-1)
            out["object_vertex_units"] = registration_distance(torch.from_numpy(pred), torch.from_numpy(true),
                                                               torch.from_numpy(vertices)).numpy()
    return out


@dataclass(frozen=True)
class ColourReadout:
    """Reads every object's pose and the agent's presence from RGB frames by colour.

    A pixel belongs to a part when it lies within a tolerance (RGB distance, 0..255: the object's own, ``tolerance``
    for the agent) of one of the part's colours. Positions are reported in ``extent`` units per frame width (the task's frame span).
    """

    objects: tuple[ObjectReadout, ...]
    agent_colours: tuple[Colour, ...]
    extent: float  # units per frame width
    tolerance: float = 40.0  # the agent's
    agent_min_share: float = 0.3  # agent visible: at least this share of its median area in the recorded frames
    moved_units: float = 5.0  # an object "moves" when its centroid shifts by more than this (extent units) ...
    moved_deg: float = 5.0  # ... or it turns by more than this (where its angle is read)

    @classmethod
    def from_layout(cls, layout: TaskLayout) -> ColourReadout:
        """The task's renderer colours, frame span, and each object's angle offset, symmetry and outline."""
        frame = layout.frame
        if frame is None or not frame.objects or not frame.agent_colours:
            raise ValueError(f"task {layout.name}: no colour readout (its frames name no object and agent colours)")
        objects = tuple(ObjectReadout(name=obj.name, colours=look.colours, angle=obj.angle is not None,
                                      angle_offset=look.angle_offset, symmetry=look.symmetry, tolerance=look.tolerance,
                                      vertices=obj.vertices,
                                      centroid=obj.centroid) for obj, look in zip(layout.objects, frame.objects))
        return cls(objects=objects, agent_colours=frame.agent_colours, extent=frame.span)

    def outline(self, i: int) -> np.ndarray:
        """Object ``i``'s outline about the pose this readout reports (its centroid), for the vertex error."""
        obj = self.objects[i]
        return np.asarray(obj.vertices, dtype=np.float64).reshape(-1, 2) - np.asarray(obj.centroid)

    def masks(self, frames: np.ndarray, colours: tuple[Colour, ...], tolerance: float | None = None) -> np.ndarray:
        """``(N, S, S, 3)`` uint8 -> ``(N, S, S)`` bool (``tolerance``: default the agent's)."""
        x = frames.astype(np.float32)
        dist = np.min([np.linalg.norm(x - np.asarray(c, np.float32), axis=-1) for c in colours], axis=0)
        return dist < (self.tolerance if tolerance is None else tolerance)

    def poses(self, frames: np.ndarray) -> np.ndarray:
        """``(N, S, S, 3)`` uint8 -> ``(N, O, 3)`` every object's (x, y, angle); NaN where an object is not found,
        and NaN angles for an object whose angle is not read."""
        s = frames.shape[1]
        coords = (np.arange(s, dtype=np.float64) + 0.5) * (self.extent / s)
        out = np.full((len(frames), len(self.objects), 3), np.nan)
        for j, obj in enumerate(self.objects):
            for i, m in enumerate(self.masks(frames, obj.colours, obj.tolerance)):
                ys, xs = np.nonzero(m)
                if len(xs) < 3:
                    continue
                p = np.stack([coords[xs], coords[ys]], axis=1)
                mean = p.mean(axis=0)
                out[i, j, :2] = mean
                if obj.angle:
                    out[i, j, 2] = _shape_angle(p - mean, obj.symmetry) + obj.angle_offset
        return out

    def agent_area(self, frames: np.ndarray) -> np.ndarray:
        """``(N, S, S, 3)`` uint8 -> ``(N,)`` agent pixels."""
        return self.masks(frames, self.agent_colours).sum(axis=(1, 2))

    def describe(self) -> dict[str, Any]:
        return {"pose": "colour", **asdict(self)}


def _shape_angle(d: np.ndarray, symmetry: int) -> float:
    """The angle of a shape's ``(P, 2)`` points about their mean: oriented principal axis, or n-th moment over n."""
    if symmetry == 1:
        _, vecs = np.linalg.eigh(d.T @ d)
        axis = vecs[:, -1]
        if np.sum((d @ axis) ** 3) < 0:
            axis = -axis
        return math.atan2(axis[1], axis[0])
    moment = np.sum((d[:, 0] + 1j * d[:, 1]) ** symmetry)
    return float(np.angle(moment)) / symmetry


class LearnedPoseReadout:
    """Every object's pose read by a learned pose predictor (``gpc train reward``), the agent by colour.

    The learned image reward reads poses this way, so these are the pose errors a planner scoring with it
    actually faces; colour segmentation mistakes a blurred T for a turned one. An object's angle is compared
    where the predictor reads one.
    """

    def __init__(self, colour: ColourReadout, predictor: torch.nn.Module, source: str, batch_size: int = 256) -> None:
        self.colour, self.predictor, self.source, self.batch_size = colour, predictor.eval(), source, batch_size
        self.sizes = tuple(int(n) for n in getattr(predictor, "sizes", (3,) * len(colour.objects)))
        if len(self.sizes) != len(colour.objects):
            raise ValueError(f"{source}: the pose predictor reads {len(self.sizes)} objects, the task has {len(colour.objects)}")
        self.objects = tuple(ObjectReadout(**{**asdict(o), "angle": n == 3}) for o, n in zip(colour.objects, self.sizes))
        self.moved_units, self.moved_deg, self.agent_min_share = colour.moved_units, colour.moved_deg, colour.agent_min_share
        self.agent_area = colour.agent_area

    def outline(self, i: int) -> np.ndarray:
        """The predictor reads the recorded (state) pose, about the body origin: the outline as it is."""
        return np.asarray(self.objects[i].vertices, dtype=np.float64).reshape(-1, 2)

    @torch.no_grad()
    def poses(self, frames: np.ndarray) -> np.ndarray:
        """``(N, S, S, 3)`` uint8 -> ``(N, O, 3)`` in the predictor's (state) units; NaN angles where it reads none."""
        x = torch.from_numpy(np.ascontiguousarray(frames)).movedim(-1, 1).float() / 255.0
        parts = [self.predictor(x[i : i + self.batch_size]) for i in range(0, len(x), self.batch_size)]
        flat = torch.cat(parts).double().numpy() if parts else np.zeros((0, sum(self.sizes)))
        out = np.full((len(flat), len(self.sizes), 3), np.nan)
        start = 0
        for j, n in enumerate(self.sizes):
            out[:, j, :n] = flat[:, start : start + n]
            start += n
        return out

    def describe(self) -> dict[str, Any]:
        return {"pose": "learned", "checkpoint": self.source, **asdict(self.colour)}
