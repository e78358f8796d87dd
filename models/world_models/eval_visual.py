"""How a visual world model's predicted frames compare with recorded ones, per predicted step.

Each held-out window gives the model its context frames and the next T recorded actions; it
predicts ``T / frameskip`` frames open-loop (frozen noise unless told otherwise), each
compared with the recorded frame at that step. Beside it stands the "nothing moves"
baseline that copies the last context frame. Image figures: SSIM (torchmetrics) and PSNR.

SSIM rewards blur, so the figures that matter to a planner come from a readout: the
object's pose read from a frame by colour segmentation (``ColourReadout``: centroid and the
orientation of its principal axis, oriented by its skew; for Push-T's T block) or by the
learned reward's pose predictor (``LearnedPoseReadout``), against the pose read the same way
from the recorded frame, on windows where the object moves, and whether the agent is still
visible (by colour). ``ColourReadout.from_layout`` takes the colours from the task's layout.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any, cast

import numpy as np
import torch
from torchmetrics.functional.image import structural_similarity_index_measure

from gpc.datasets.layout import TaskLayout
from gpc.datasets.sequence import HeldOutOf
from gpc.models.rewards.registration import registration_distance
from gpc.models.world_models.config import IMAGE_KEY, VisualWorldModelConfig
from gpc.models.world_models.eval_state import episodes_phrase, held_out_windows
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.visual import ACTION_KEY, VisualDynamics

Colour = tuple[int, int, int]


@dataclass(frozen=True)
class ColourReadout:
    """Reads an object's pose and an agent's presence from RGB frames by colour.

    A pixel belongs to a part when it lies within ``tolerance`` (RGB distance, 0..255) of one
    of the part's colours. The object's angle is that of its principal axis (largest
    spread), oriented towards its skew (its long tail), plus ``angle_offset``. Positions are
    reported in ``extent`` units per frame width (the task's frame span); ``from_layout`` fills
    colours, offset, extent and outline from the task.
    """

    object_colours: tuple[Colour, ...]
    agent_colours: tuple[Colour, ...]
    extent: float  # units per frame width
    tolerance: float = 40.0
    angle_offset: float = 0.0  # radians added to the oriented principal axis' angle
    agent_min_share: float = 0.3  # agent visible: at least this share of its median area in the recorded frames
    moved_units: float = 5.0  # the object "moves" when its centroid shifts by more than this (extent units) ...
    moved_deg: float = 5.0  # ... or it turns by more than this
    vertices: tuple[tuple[float, float], ...] = ()  # the object's outline in its body frame; () skips the vertex error
    centroid: tuple[float, float] = (0.0, 0.0)  # its area centroid in the body frame: the position colour reads

    @classmethod
    def from_layout(cls, layout: TaskLayout) -> ColourReadout:
        """The task's renderer colours, frame span, axis offset and object outline."""
        frame = layout.frame
        if frame is None or not frame.object_colours or not frame.agent_colours or not layout.objects or not layout.primary.has_angle:
            raise ValueError(f"task {layout.name}: no colour readout (its frames name no object and agent colours, "
                             "or its object has no angle)")
        return cls(object_colours=frame.object_colours, agent_colours=frame.agent_colours, extent=frame.span,
                   angle_offset=frame.angle_offset, vertices=layout.primary.vertices, centroid=layout.primary.centroid)

    @property
    def pose_vertices(self) -> np.ndarray:
        """The outline about the pose this readout reports (the centroid), for the vertex error."""
        return np.asarray(self.vertices, dtype=np.float64).reshape(-1, 2) - np.asarray(self.centroid)

    def masks(self, frames: np.ndarray, colours: tuple[Colour, ...]) -> np.ndarray:
        """``(N, S, S, 3)`` uint8 -> ``(N, S, S)`` bool."""
        x = frames.astype(np.float32)
        dist = np.min([np.linalg.norm(x - np.asarray(c, np.float32), axis=-1) for c in colours], axis=0)
        return dist < self.tolerance

    def object_pose(self, frames: np.ndarray) -> np.ndarray:
        """``(N, S, S, 3)`` uint8 -> ``(N, 3)`` (x, y, angle); NaN where the object is not found."""
        mask = self.masks(frames, self.object_colours)
        s = frames.shape[1]
        coords = (np.arange(s, dtype=np.float64) + 0.5) * (self.extent / s)
        out = np.full((len(frames), 3), np.nan)
        for i, m in enumerate(mask):
            ys, xs = np.nonzero(m)
            if len(xs) < 3:
                continue
            p = np.stack([coords[xs], coords[ys]], axis=1)
            mean = p.mean(axis=0)
            d = p - mean
            _, vecs = np.linalg.eigh(d.T @ d)
            axis = vecs[:, -1]
            if np.sum((d @ axis) ** 3) < 0:
                axis = -axis
            out[i] = (*mean, math.atan2(axis[1], axis[0]) + self.angle_offset)
        return out

    def agent_area(self, frames: np.ndarray) -> np.ndarray:
        """``(N, S, S, 3)`` uint8 -> ``(N,)`` agent pixels."""
        return self.masks(frames, self.agent_colours).sum(axis=(1, 2))

    def describe(self) -> dict[str, Any]:
        return {"pose": "colour", **asdict(self)}


class LearnedPoseReadout:
    """The object pose read by a learned pose predictor (``gpc train reward``), the agent by colour.

    The learned image reward reads poses this way, so these are the pose errors a planner
    scoring with it actually faces; colour segmentation mistakes a blurred T for a turned one.
    """

    def __init__(self, colour: ColourReadout, predictor: torch.nn.Module, source: str, batch_size: int = 256) -> None:
        self.colour, self.predictor, self.source, self.batch_size = colour, predictor.eval(), source, batch_size
        # The predictor reads the recorded (state) pose, about the body origin: the outline as it is.
        self.pose_vertices = np.asarray(colour.vertices, dtype=np.float64).reshape(-1, 2)
        self.moved_units, self.moved_deg, self.agent_min_share = colour.moved_units, colour.moved_deg, colour.agent_min_share
        self.agent_area = colour.agent_area

    @torch.no_grad()
    def object_pose(self, frames: np.ndarray) -> np.ndarray:
        """``(N, S, S, 3)`` uint8 -> ``(N, 3)`` (x, y, angle) in the predictor's (state) units."""
        x = torch.from_numpy(np.ascontiguousarray(frames)).movedim(-1, 1).float() / 255.0
        parts = [self.predictor(x[i : i + self.batch_size]) for i in range(0, len(x), self.batch_size)]
        return torch.cat(parts).double().numpy() if parts else np.zeros((0, 3))

    def describe(self) -> dict[str, Any]:
        return {"pose": "learned", "checkpoint": self.source, **asdict(self.colour)}


def _uint8(frames: torch.Tensor) -> np.ndarray:
    """``(..., 3, S, S)`` in [0, 1] -> ``(..., S, S, 3)`` uint8."""
    return (frames.clamp(0, 1) * 255).round().to(torch.uint8).movedim(-3, -1).cpu().numpy()


def _image_scores(pred: torch.Tensor, true: torch.Tensor) -> dict[str, torch.Tensor]:
    """``(N, T, 3, S, S)`` each -> ``{ssim, psnr}``: ``(N, T)``."""
    n, t = pred.shape[:2]
    a, b = pred.flatten(0, 1).double(), true.flatten(0, 1).double()
    # A tuple only with return_full_image=True.
    ssim = cast(torch.Tensor, structural_similarity_index_measure(a, b, data_range=1.0, reduction="none"))
    mse = (a - b).pow(2).flatten(1).mean(dim=1).clamp_min(1e-10)
    return {"ssim": ssim.reshape(n, t), "psnr": (-10.0 * torch.log10(mse)).reshape(n, t)}


def _pose_errors(pred: np.ndarray, true: np.ndarray, vertices: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """``(..., 3)`` poses -> position error, angle error (degrees) and, given the object's ``(V, 2)`` outline, the
    mean distance between its vertices placed at both poses (ADD: position and angle in one length, what the
    registration reward compares); a missing prediction counts as NaN."""
    out = {"object_units": np.linalg.norm(pred[..., :2] - true[..., :2], axis=-1),
           "object_deg": np.abs((pred[..., 2] - true[..., 2] + np.pi) % (2 * np.pi) - np.pi) * (180.0 / np.pi)}
    if vertices is not None and len(vertices):
        out["object_vertex_units"] = registration_distance(torch.from_numpy(pred), torch.from_numpy(true),
                                                           torch.from_numpy(vertices)).numpy()
    return out


@torch.no_grad()
def evaluate_visual_rollouts(
    module: WorldModelModule, datasets: Sequence[str | os.PathLike], split: str = "val", episodes: int | None = None,
    horizon: int | None = None, readout: ColourReadout | LearnedPoseReadout | None = None, stride: int = 8, max_windows: int | None = 512,
    batch_size: int = 32, noise: str = "frozen", grid_windows: int = 6, seed: int = 0, held_out_of: HeldOutOf | None = None,
) -> tuple[dict[str, Any], np.ndarray]:
    """Per-step SSIM / PSNR (and, with ``readout``, object pose errors and agent visibility) of the
    model and of the nothing-moves baseline; returns (report, PNG grid as ``(H, W, 3)`` uint8 RGB).

    Windows as ``held_out_windows`` picks them (every ``stride`` steps, at most ``max_windows``; ``held_out_of``).
    """
    dyn, config = module.dynamics, module.config
    assert isinstance(dyn, VisualDynamics) and isinstance(config, VisualWorldModelConfig)  # a visual world model
    c = config.dynamics
    arrays, chosen, idx, t = held_out_windows(module, datasets, (IMAGE_KEY, ACTION_KEY), split, episodes, horizon,
                                              stride, max_windows, held_out_of)
    n0, f = module.n_obs_steps, c.frameskip
    steps = t // f
    future = n0 - 1 + f * np.arange(1, steps + 1)  # window positions of the predicted frames
    generator = torch.Generator().manual_seed(seed)
    scores: dict[str, dict[str, list[torch.Tensor]]] = {"model": {}, "baseline": {}}
    frames_u8: dict[str, list[np.ndarray]] = {"model": [], "true": [], "last": []}
    for lo in range(0, len(idx), batch_size):
        rows = idx[lo : lo + batch_size]
        images = torch.from_numpy(arrays.data[IMAGE_KEY][rows[:, : n0]])
        actions = torch.from_numpy(arrays.data[ACTION_KEY][rows[:, n0 - 1 : n0 - 1 + t]]).float()
        recorded = dyn.frames(torch.from_numpy(arrays.data[IMAGE_KEY][rows[:, future]]))
        history = dyn.frames(images)
        pred = module.rollout(history, actions, noise=noise, generator=generator).cpu()
        still = history[:, -1:].expand_as(recorded)
        for name, guess in (("model", pred), ("baseline", still)):
            for metric, value in _image_scores(guess, recorded).items():
                scores[name].setdefault(metric, []).append(value)
        frames_u8["model"].append(_uint8(pred))
        frames_u8["true"].append(_uint8(recorded))
        frames_u8["last"].append(_uint8(history[:, -1]))
    merged = {name: {m: torch.cat(v).mean(dim=0).tolist() for m, v in d.items()} for name, d in scores.items()}
    model, true, last = (np.concatenate(frames_u8[k]) for k in ("model", "true", "last"))
    report: dict[str, Any] = {
        "split": held_out_of.label if held_out_of else split, "datasets": [str(p) for p in datasets],
        "episodes": int(len(chosen)), "windows": int(len(idx)),
        "history": n0, "horizon": t, "frameskip": f, "resolution": c.resolution, "noise": noise,
        "sampler": asdict(dyn.config.sampler),
        "config": replace(config, dynamics=dyn.config).to_dict(),  # the chain actually sampled (--sampler-steps)
        "steps": [{"step": i + 1, "actions": int((i + 1) * f), **{name: {m: merged[name][m][i] for m in merged[name]}
                                                                    for name in merged}} for i in range(steps)],
    }
    if readout is not None:
        report["readout"] = _readout_figures(readout, model, true, last)
        report["readout_config"] = readout.describe()
    return report, frame_grid(last[:grid_windows], true[:grid_windows], model[:grid_windows])


def _readout_figures(readout: ColourReadout | LearnedPoseReadout, model: np.ndarray, true: np.ndarray, last: np.ndarray) -> dict[str, Any]:
    """Object pose errors at every step (all windows) and at the final step on windows where the object moves;
    the share of predicted frames where the agent is visible."""
    n, t = model.shape[:2]
    pose = {k: readout.object_pose(v.reshape((-1,) + v.shape[2:])).reshape(n, t, 3) for k, v in (("model", model), ("true", true))}
    pose["baseline"] = np.repeat(readout.object_pose(last)[:, None], t, axis=1)
    vertices = readout.pose_vertices
    moved = _pose_errors(pose["baseline"][:, -1], pose["true"][:, -1])
    moving = (moved["object_units"] > readout.moved_units) | (moved["object_deg"] > readout.moved_deg)
    out: dict[str, Any] = {"moving_windows": int(moving.sum()), "per_step": {}, "final_moving": {}}
    for name in ("model", "baseline"):
        errors = _pose_errors(pose[name], pose["true"], vertices)
        lost = np.isnan(errors["object_units"])
        out["per_step"][name] = {**{k: np.nanmean(v, axis=0).tolist() for k, v in errors.items()},
                                 "object_lost": lost.mean(axis=0).tolist()}
        if moving.any():
            final = {k: v[moving, -1] for k, v in errors.items()}
            out["final_moving"][name] = {**{k: float(np.nanmean(v)) for k, v in final.items()},
                                         **{f"{k}_median": float(np.nanmedian(v)) for k, v in final.items()},
                                         "object_deg_over_90": float(np.mean(final["object_deg"] > 90.0)),
                                         "object_lost": float(lost[moving, -1].mean())}
    true_area = readout.agent_area(true.reshape((-1,) + true.shape[2:]))
    threshold = max(1.0, readout.agent_min_share * float(np.median(true_area)))
    area = readout.agent_area(model.reshape((-1,) + model.shape[2:])).reshape(n, t)
    out["agent_visible"] = {"model": float((area >= threshold).mean()), "true": float((true_area >= threshold).mean()),
                            "per_step": (area >= threshold).mean(axis=0).tolist(), "min_pixels": threshold}
    if moving.any():
        m, b = out["final_moving"]["model"], out["final_moving"]["baseline"]
        out["final_moving"]["ratio"] = {k: m[k] / b[k] if b[k] > 0 else float("nan")
                                        for k in ("object_units", "object_deg", "object_vertex_units") if k in m}
    return out


def frame_grid(last: np.ndarray, true: np.ndarray, pred: np.ndarray, scale: int = 3, gap: int = 2) -> np.ndarray:
    """Per window two rows: [last context | recorded futures] over [last context | predicted futures].

    ``last``: ``(N, S, S, 3)``, ``true`` / ``pred``: ``(N, T, S, S, 3)`` uint8 -> RGB ``(rows, cols, 3)`` uint8.
    """
    if len(last) == 0:
        return np.full((1, 1, 3), 255, np.uint8)
    n, t, s = true.shape[0], true.shape[1], true.shape[2]
    cell = s * scale + gap
    grid = np.full((2 * n * cell + gap * n, (t + 1) * cell, 3), 255, np.uint8)
    for i in range(n):
        for r, seq in enumerate((true[i], pred[i])):
            y = i * (2 * cell + gap) + r * cell
            for j, img in enumerate([last[i], *seq]):
                big = np.kron(img, np.ones((scale, scale, 1), np.uint8))
                grid[y : y + s * scale, j * cell : j * cell + s * scale] = big
    return grid


def visual_markdown_table(report: dict[str, Any], title: str = "Visual world model rollouts") -> str:
    """One row per predicted frame: SSIM and PSNR (and object pose errors, agent visibility) as model / baseline."""
    ro = report.get("readout")
    vertex = bool(ro and "object_vertex_units" in ro["per_step"]["model"])
    head = ["step (actions)", "SSIM", "PSNR dB"] + (["object units", "object deg"] + (["object vertices"] if vertex else [])
                                                    + ["agent visible"] if ro else [])
    lines = [
        f"## {title}", "",
        f"{report['windows']} windows from {episodes_phrase(report)}; {report['resolution']} px, "
        f"frameskip {report['frameskip']}, {report['noise']} noise, {report['sampler']['steps']} Euler steps. "
        "Each cell: model / nothing-moves baseline "
        "(SSIM, PSNR: higher is better; pose errors: lower)."
        + (f" Object pose read by {'colour' if report['readout_config']['pose'] == 'colour' else 'the learned pose predictor'}."
           if ro else ""), "",
        "| " + " | ".join(head) + " |", "|" + "---|" * len(head),
    ]
    for i, row in enumerate(report["steps"]):
        cells = [f"{row['step']} ({row['actions']})", f"{row['model']['ssim']:.3f} / {row['baseline']['ssim']:.3f}",
                 f"{row['model']['psnr']:.1f} / {row['baseline']['psnr']:.1f}"]
        if ro:
            m, b = ro["per_step"]["model"], ro["per_step"]["baseline"]
            keys = ("object_units", "object_deg") + (("object_vertex_units",) if vertex else ())
            cells += [f"{m[k][i]:.1f} / {b[k][i]:.1f}" for k in keys]
            cells.append(f"{ro['agent_visible']['per_step'][i]:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    if ro and ro["final_moving"]:
        fm = ro["final_moving"]
        lines += ["", f"Final frame, {ro['moving_windows']} windows where the object moves: position error "
                  f"{fm['model']['object_units']:.1f} vs {fm['baseline']['object_units']:.1f} (ratio "
                  f"{fm['ratio']['object_units']:.2f}), angle error {fm['model']['object_deg']:.1f} vs "
                  f"{fm['baseline']['object_deg']:.1f} deg (ratio {fm['ratio']['object_deg']:.2f}; medians "
                  f"{fm['model']['object_deg_median']:.1f} vs {fm['baseline']['object_deg_median']:.1f}, off by more than "
                  f"90 deg in {fm['model']['object_deg_over_90']:.0%} vs {fm['baseline']['object_deg_over_90']:.0%}); "
                  + (f"vertex error (position and angle in one length) {fm['model']['object_vertex_units']:.1f} vs "
                     f"{fm['baseline']['object_vertex_units']:.1f} (ratio {fm['ratio']['object_vertex_units']:.2f}; medians "
                     f"{fm['model']['object_vertex_units_median']:.1f} vs {fm['baseline']['object_vertex_units_median']:.1f}); "
                     if vertex else "")
                  + "agent visible in "
                  f"{ro['agent_visible']['model']:.0%} of predicted frames ({ro['agent_visible']['true']:.0%} of recorded ones)."]
    return "\n".join(lines) + "\n"
