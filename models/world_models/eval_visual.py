"""How a visual world model's predicted frames compare with recorded ones, per predicted step.

Each held-out window gives the model its context frames and the next T recorded actions; it
predicts ``T / frameskip`` frames open-loop (frozen noise unless told otherwise), each
compared with the recorded frame at that step. Beside it stands the "nothing moves"
baseline that copies the last context frame. Image figures: SSIM (torchmetrics) and PSNR.

SSIM rewards blur, so the figures that matter to a planner come from a readout
(``gpc.models.world_models.readout``): every object's pose read from a frame by colour or by the
learned reward's pose predictor, against the pose read the same way from the recorded frame, on
the windows where that object moves, and whether the agent is still visible (by colour). A region with extent but
no pose (a drawing's ink) is compared pixel by pixel (``gpc.models.world_models.regions``).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import asdict, replace
from typing import Any, cast

import numpy as np
import torch
from torchmetrics.functional.image import structural_similarity_index_measure

from gpc.datasets.sequence import HeldOutOf
from gpc.models.world_models.config import IMAGE_KEY, VisualWorldModelConfig
from gpc.models.world_models.eval_state import episodes_phrase, held_out_windows
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.readout import ColourReadout, LearnedPoseReadout, pose_errors
from gpc.models.world_models.regions import RegionReadout, regions_markdown
from gpc.models.world_models.state import STATE_KEY
from gpc.models.world_models.state_readout import StateReadout, state_readout_markdown
from gpc.models.world_models.visual import ACTION_KEY, VisualDynamics

__all__ = ["ColourReadout", "LearnedPoseReadout", "evaluate_visual_rollouts", "frame_grid", "readout_figures", "visual_markdown_table"]

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


@torch.no_grad()
def evaluate_visual_rollouts(
    module: WorldModelModule, datasets: Sequence[str | os.PathLike], split: str = "val", episodes: int | None = None,
    horizon: int | None = None, readout: ColourReadout | LearnedPoseReadout | None = None, stride: int = 8, max_windows: int | None = 512,
    batch_size: int = 32, noise: str = "frozen", grid_windows: int = 6, seed: int = 0, held_out_of: HeldOutOf | None = None,
    regions: RegionReadout | None = None, state_readout: StateReadout | None = None,
) -> tuple[dict[str, Any], np.ndarray]:
    """Per-step SSIM / PSNR (and, with ``readout``, object pose errors and agent visibility; with ``regions``, each
    region's wrong pixels; with ``state_readout``, the errors of the states a learned reader reads) of the model and
    of the nothing-moves baseline; returns (report, PNG grid as ``(H, W, 3)`` uint8 RGB).

    Windows as ``held_out_windows`` picks them (every ``stride`` steps, at most ``max_windows``; ``held_out_of``).
    """
    dyn, config = module.dynamics, module.config
    assert isinstance(dyn, VisualDynamics) and isinstance(config, VisualWorldModelConfig)  # a visual world model
    c = config.dynamics
    keys = (IMAGE_KEY, ACTION_KEY) + ((STATE_KEY,) if state_readout is not None else ())
    arrays, chosen, idx, t = held_out_windows(module, datasets, keys, split, episodes, horizon, stride, max_windows, held_out_of)
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
        report["readout"] = readout_figures(readout, model, true, last)
        report["readout_config"] = readout.describe()
    if regions is not None:
        report["regions"] = regions.figures(model, true, last)
        report["regions_config"] = regions.describe()
    if state_readout is not None:
        states = arrays.data[STATE_KEY][idx[:, future]].astype(np.float64)  # the recorded states behind ``true``
        report["state_readout"] = state_readout.figures(model, true, last, states)
        report["state_readout_config"] = state_readout.describe()
    return report, frame_grid(last[:grid_windows], true[:grid_windows], model[:grid_windows])


def readout_figures(readout: ColourReadout | LearnedPoseReadout, model: np.ndarray, true: np.ndarray, last: np.ndarray) -> dict[str, Any]:
    """Every object's pose errors (``objects``, by name; the first object's also at the top, as for one object);
    the share of predicted frames where the agent is visible."""
    n, t = model.shape[:2]
    count = len(readout.objects)
    pose = {k: readout.poses(v.reshape((-1,) + v.shape[2:])).reshape(n, t, count, 3) for k, v in (("model", model), ("true", true))}
    pose["baseline"] = np.repeat(readout.poses(last)[:, None], t, axis=1)
    objects = {obj.name: _object_figures(readout, i, {k: v[:, :, i] for k, v in pose.items()})
               for i, obj in enumerate(readout.objects)}
    out: dict[str, Any] = dict(objects[readout.objects[0].name])
    true_area = readout.agent_area(true.reshape((-1,) + true.shape[2:]))
    threshold = max(1.0, readout.agent_min_share * float(np.median(true_area)))
    area = readout.agent_area(model.reshape((-1,) + model.shape[2:])).reshape(n, t)
    out["agent_visible"] = {"model": float((area >= threshold).mean()), "true": float((true_area >= threshold).mean()),
                            "per_step": (area >= threshold).mean(axis=0).tolist(), "min_pixels": threshold}
    out["objects"] = objects
    return out


def _object_figures(readout: ColourReadout | LearnedPoseReadout, i: int, pose: dict[str, np.ndarray]) -> dict[str, Any]:
    """One object's pose errors at every step (all windows) and at the final step on the windows where it moves
    (between the last context frame and the recorded final one); ``pose``: ``(N, T, 3)`` per source."""
    obj, vertices = readout.objects[i], readout.outline(i)
    moved = pose_errors(obj, pose["baseline"][:, -1], pose["true"][:, -1])
    moving = moved["object_units"] > readout.moved_units
    if "object_deg" in moved:
        moving |= moved["object_deg"] > readout.moved_deg
    out: dict[str, Any] = {"moving_windows": int(moving.sum()), "per_step": {}, "final_moving": {}}
    for name in ("model", "baseline"):
        errors = pose_errors(obj, pose[name], pose["true"], vertices)
        lost = np.isnan(errors["object_units"])
        out["per_step"][name] = {**{k: np.nanmean(v, axis=0).tolist() for k, v in errors.items()},
                                 "object_lost": lost.mean(axis=0).tolist()}
        if moving.any():
            final = {k: v[moving, -1] for k, v in errors.items()}
            out["final_moving"][name] = {**{k: float(np.nanmean(v)) for k, v in final.items()},
                                         **{f"{k}_median": float(np.nanmedian(v)) for k, v in final.items()},
                                         **({"object_deg_over_90": float(np.mean(final["object_deg"] > 90.0))}
                                            if "object_deg" in final and obj.symmetry == 1 else {}),
                                         "object_lost": float(lost[moving, -1].mean())}
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
    """One row per predicted frame: SSIM and PSNR (and the first object's pose errors, agent visibility) as model /
    baseline; then each object's errors on the final frame of the windows where it moves; then each region's, then
    the state reader's."""
    table, steps = _readout_table(report, title), [row["actions"] for row in report["steps"]]
    if "regions" in report:
        table += "\n".join(regions_markdown(report["regions"], steps)) + "\n"
    if "state_readout" in report:
        table += "\n".join(state_readout_markdown(report["state_readout"], report["state_readout_config"], steps)) + "\n"
    return table


def _readout_table(report: dict[str, Any], title: str) -> str:
    """The image figures and the objects' readout (``visual_markdown_table`` without regions)."""
    ro = report.get("readout")
    keys = [k for k in ("object_units", "object_deg", "object_vertex_units") if ro and k in ro["per_step"]["model"]]
    objects = (ro.get("objects") or {"object": ro}) if ro else {}
    several = len(objects) > 1
    first = next(iter(objects)) if several else "object"  # the per-step columns are the first object's
    names = {"object_units": f"{first} units", "object_deg": f"{first} deg", "object_vertex_units": f"{first} vertices"}
    head = ["step (actions)", "SSIM", "PSNR dB"] + ([names[k] for k in keys] + ["agent visible"] if ro else [])
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
            cells += [f"{m[k][i]:.1f} / {b[k][i]:.1f}" for k in keys]
            cells.append(f"{ro['agent_visible']['per_step'][i]:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    if not ro:
        return "\n".join(lines) + "\n"
    agent = (f"agent visible in {ro['agent_visible']['model']:.0%} of predicted frames "
             f"({ro['agent_visible']['true']:.0%} of recorded ones).")
    if not several:  # one sentence, as it always read for one object
        if ro["final_moving"]:
            lines += ["", f"Final frame, {ro['moving_windows']} windows where the object moves: "
                      + _final_errors(ro["final_moving"]) + agent]
        return "\n".join(lines) + "\n"
    lines.append("")  # one line per object, then the agent
    for name, fig in objects.items():
        lines.append(f"Final frame, {fig['moving_windows']} windows where the {name} moves: "
                     + _final_errors(fig["final_moving"]).rstrip("; ") + "." if fig["final_moving"] else
                     f"The {name} moves in none of the windows (by more than the readout's threshold).")
    lines.append(agent[0].upper() + agent[1:])
    return "\n".join(lines) + "\n"


def _final_errors(fm: dict[str, Any]) -> str:
    """One object's final-frame errors on its moving windows, model vs baseline, with their ratios."""
    m, b, r = fm["model"], fm["baseline"], fm["ratio"]
    text = f"position error {m['object_units']:.1f} vs {b['object_units']:.1f} (ratio {r['object_units']:.2f})"
    if "object_deg" in m:
        text += (f", angle error {m['object_deg']:.1f} vs {b['object_deg']:.1f} deg (ratio {r['object_deg']:.2f}; medians "
                 f"{m['object_deg_median']:.1f} vs {b['object_deg_median']:.1f}"
                 + (f", off by more than 90 deg in {m['object_deg_over_90']:.0%} vs {b['object_deg_over_90']:.0%}"
                    if "object_deg_over_90" in m else "") + ")")
    text += "; "
    if "object_vertex_units" in m:
        text += (f"vertex error (position and angle in one length) {m['object_vertex_units']:.1f} vs "
                 f"{b['object_vertex_units']:.1f} (ratio {r['object_vertex_units']:.2f}; medians "
                 f"{m['object_vertex_units_median']:.1f} vs {b['object_vertex_units_median']:.1f}); ")
    return text
