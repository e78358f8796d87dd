"""Measuring the image reward's predictor against the reward computed from the recorded state.

``evaluate_reward_predictor`` reads held-out
frames (the validation episodes of the training split, or every episode of a store the
predictor never saw, e.g. the human demonstrations) and compares the predicted registration
loss with the one computed from the recorded state; for a state reader (a task scored by its own
state reward) ``evaluate_state_reader`` compares that reward on the read and the recorded states.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from gpc.datasets.errors import DataError
from gpc.datasets.sequence import recorded_held_out
from gpc.datasets.store import EpisodeStore
from gpc.models.rewards.augment import resize
from gpc.models.rewards.learned import IMAGE_KEY, STATE_KEY, RewardPredictorModule
from gpc.models.rewards.registration import pose_errors
from gpc.models.stats import spearman

GOAL_KEY = "goal"  # a store's per-step goal, where the task draws one per episode

SPLITS = ("val", "all")
BINS_PX = (0.0, 10.0, 30.0, 100.0, float("inf"))  # true registration loss bins of the report


def _episodes(datasets: Sequence[str | os.PathLike], split: str, record: dict[str, Any]) -> list[tuple[EpisodeStore, int]]:
    """(store, episode) pairs of the split, numbered across the stores in order as training numbered them."""
    stores = [EpisodeStore.open(p) for p in datasets]
    pairs = [(s, i) for s in stores for i in range(s.n_episodes)]
    if split == "all":
        return pairs
    chosen = recorded_held_out(record, [str(p) for p in datasets], [s.n_episodes for s in stores])
    if len(chosen) == 0:
        raise DataError("the predictor was trained without held-out episodes; pass --split all with a separate store")
    return [pairs[i] for i in chosen]


def _summary(errors: dict[str, np.ndarray]) -> dict[str, Any]:
    true, pred, err = errors["registration_true_px"], errors["registration_pred_px"], errors["registration_abs_err_px"]
    rho = spearman(true, pred)
    out: dict[str, Any] = {
        "frames": int(len(true)),
        "registration_mae_px": float(err.mean()), "registration_median_err_px": float(np.median(err)),
        "registration_p90_err_px": float(np.percentile(err, 90)),
        "constant_baseline_mae_px": float(np.abs(true - np.median(true)).mean()),
        "spearman": rho, "true_registration_mean_px": float(true.mean()),
        "vertex_px": float(errors["vertex_px"].mean()), "position_px": float(errors["position_px"].mean()),
        "angle_deg": float(errors["angle_deg"].mean()), "angle_median_deg": float(np.median(errors["angle_deg"])),
    }
    bins = []
    for lo, hi in zip(BINS_PX[:-1], BINS_PX[1:]):
        inside = (true >= lo) & (true < hi)
        if inside.any():
            bins.append({"true_px": [lo, hi], "frames": int(inside.sum()), "registration_mae_px": float(err[inside].mean()),
                         "vertex_px": float(errors["vertex_px"][inside].mean())})
    out["by_true_registration"] = bins
    return out


@torch.no_grad()
def evaluate_reward_predictor(
    module: RewardPredictorModule, datasets: Sequence[str | os.PathLike], split: str = "val", episodes: int | None = None,
    stride: int = 1, goal: Sequence[float] | None = None, frame_size: int | None = None, batch_size: int = 256,
) -> dict[str, Any]:
    """Predicted vs true registration loss (px) and pose errors on held-out frames.

    ``split="val"``: the validation episodes of the split the predictor was trained with (its
    recorded seed and ratio over the same list of stores); ``"all"``: every episode (for a
    store it never saw). ``episodes``: only the first N of them; ``stride``: every k-th frame.
    ``goal``: the pose the registration loss is measured against (default: the predictor's).
    ``frame_size``: first downscale the frames to this size (as a world model would produce them).
    """
    if split not in SPLITS:
        raise ValueError(f"split {split!r}: use one of {', '.join(SPLITS)}")
    if stride < 1:
        raise ValueError(f"stride {stride}: must be at least 1")
    c = module.config
    c.check_task()
    chosen = _episodes(datasets, split, module.data_record)[:episodes]
    if not chosen:
        raise DataError(f"{', '.join(map(str, datasets))}: no episodes to evaluate")
    verts = [torch.tensor(v, device=module.device) for v in c.object_vertices]
    fixed = c.goal if goal is None else tuple(goal)  # None: each frame's goal as its store recorded it (a goal per episode)
    goal_t = None if fixed is None else torch.tensor(fixed, dtype=torch.float32, device=module.device)
    parts: dict[str, list[np.ndarray]] = {}
    size = [0]
    for x, states, goals in _batches(chosen, stride, batch_size, frame_size, goal_t is None, module.device, size):
        against = goal_t if goals is None else goals
        for name, value in pose_errors(module.predictor(x), states[:, list(c.pose_dims)], verts, against, c.sizes).items():
            parts.setdefault(name, []).append(value.double().cpu().numpy())
    errors = {k: np.concatenate(v) for k, v in parts.items()}
    return {"split": split, "datasets": [str(p) for p in datasets], "episodes": len(chosen), "stride": stride,
            "goal": "per episode" if goal_t is None else goal_t.tolist(),
            "frame_size": size[0], "input_size": c.input_size,
            "config": c.to_dict(), **_summary(errors)}


def _batches(chosen: list[tuple[EpisodeStore, int]], stride: int, batch_size: int, frame_size: int | None, goals: bool,
             device: Any, size: list[int]) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]]:
    """Every ``stride``-th frame of the chosen episodes in batches: frames ``(B, 3, S, S)`` in [0, 1] (downscaled to
    ``frame_size``), recorded states ``(B, D)`` and, with ``goals``, recorded goals ``(B, G)``; ``size[0]``: the size read."""
    for store, i in chosen:
        sl = store.episode_slice(i)
        frames = store.read(IMAGE_KEY, sl.start, sl.stop)[::stride]
        states = store.read(STATE_KEY, sl.start, sl.stop)[::stride]
        if frames.ndim != 4 or frames.shape[-1] != 3:
            raise DataError(f"{store.path}: data/{IMAGE_KEY} rows are {frames.shape[1:]}, expected RGB frames (H, W, 3)")
        frames = np.clip(np.rint(frames), 0, 255).astype(np.uint8)
        size[0] = frame_size or int(frames.shape[1])
        recorded = store.read(GOAL_KEY, sl.start, sl.stop)[::stride] if goals else None
        for lo in range(0, len(frames), batch_size):
            x = torch.from_numpy(frames[lo : lo + batch_size]).to(device).permute(0, 3, 1, 2).float() / 255.0
            x = x if frame_size is None else resize(x, frame_size)
            true = torch.from_numpy(np.asarray(states[lo : lo + batch_size], np.float32)).to(device)
            yield x, true, (None if recorded is None else
                            torch.from_numpy(np.asarray(recorded[lo : lo + batch_size], np.float32)).to(device))


@torch.no_grad()
def evaluate_state_reader(
    module: RewardPredictorModule, datasets: Sequence[str | os.PathLike], reward: nn.Module, split: str = "val",
    episodes: int | None = None, stride: int = 1, frame_size: int | None = None, batch_size: int = 256,
) -> dict[str, Any]:
    """A state reader's reward against the truth on held-out frames: ``reward`` (the task's state reward, ``(K, T, D)``
    states -> ``(K,)``) on the state read from each frame vs on the recorded state, and the read state's error."""
    if split not in SPLITS:
        raise ValueError(f"split {split!r}: use one of {', '.join(SPLITS)}")
    chosen = _episodes(datasets, split, module.data_record)[:episodes]
    if not chosen:
        raise DataError(f"{', '.join(map(str, datasets))}: no episodes to evaluate")
    parts: dict[str, list[np.ndarray]] = {"pred": [], "true": [], "state_err": []}
    size = [0]
    for x, states, _ in _batches(chosen, stride, batch_size, frame_size, False, module.device, size):
        read = module.predictor(x)
        parts["pred"].append(reward(read[:, None]).double().cpu().numpy())
        parts["true"].append(reward(states[:, None]).double().cpu().numpy())
        parts["state_err"].append((read - module.predictor.label(states, read)).abs().double().cpu().numpy())
    pred, true, err = (np.concatenate(parts[k]) for k in ("pred", "true", "state_err"))
    rho = spearman(true, pred)
    return {"split": split, "datasets": [str(p) for p in datasets], "episodes": len(chosen), "stride": stride,
            "frame_size": size[0], "input_size": module.config.input_size, "config": module.config.to_dict(),
            "frames": int(len(true)), "reward_mae": float(np.abs(pred - true).mean()),
            "reward_p90_err": float(np.percentile(np.abs(pred - true), 90)),
            "constant_baseline_mae": float(np.abs(true - np.median(true)).mean()), "spearman": rho,
            "true_reward_mean": float(true.mean()), "state_abs_err": err.mean(axis=0).tolist()}


def state_reader_report(reports: Sequence[dict[str, Any]], title: str = "Image reward") -> str:
    """One row per evaluated data set: the reward read from frames against the reward of the recorded states."""
    lines = [f"## {title}", "",
             f"Frames {reports[0]['frame_size']} px, network input {reports[0]['input_size']} px. The task's state reward "
             f"({reports[0]['config']['state_reward']}) on the state read from each frame vs on the recorded state. "
             "Constant baseline: always predicting the median true reward.", "",
             "| data | split | episodes | frames | reward MAE | p90 | constant baseline MAE | Spearman | true reward mean | "
             "state entries' mean abs error |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in reports:
        lines.append(f"| {', '.join(Path(p).name for p in r['datasets'])} | {r['split']} | {r['episodes']} | {r['frames']} | "
                     f"{r['reward_mae']:.4f} | {r['reward_p90_err']:.4f} | {r['constant_baseline_mae']:.4f} | "
                     f"{r['spearman']:.3f} | {r['true_reward_mean']:.3f} | {np.mean(r['state_abs_err']):.3f} |")
    return "\n".join(lines) + "\n"


def markdown_report(reports: Sequence[dict[str, Any]], title: str = "Image reward") -> str:
    """One row per evaluated data set, then the error by true-registration bin of each."""
    lines = [
        f"## {title}", "",
        f"Frames {reports[0]['frame_size']} px, network input {reports[0]['input_size']} px. Registration loss "
        "(mean vertex distance to the goal, px): predicted vs computed from the recorded state. "
        "Constant baseline: always predicting the median true loss.", "",
        "| data | split | episodes | frames | reg. MAE px | median | p90 | constant baseline MAE | Spearman | "
        "vertex px | position px | angle deg (median) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in reports:
        lines.append(
            f"| {', '.join(Path(p).name for p in r['datasets'])} | {r['split']} | {r['episodes']} | {r['frames']} | "
            f"{r['registration_mae_px']:.2f} | {r['registration_median_err_px']:.2f} | {r['registration_p90_err_px']:.2f} | "
            f"{r['constant_baseline_mae_px']:.2f} | {r['spearman']:.3f} | {r['vertex_px']:.2f} | {r['position_px']:.2f} | "
            f"{r['angle_deg']:.2f} ({r['angle_median_deg']:.2f}) |"
        )
    lines += ["", "By true registration loss (reg. MAE px / vertex px, frames):", "",
              "| data | " + " | ".join(f"{lo:g}-{hi:g} px" for lo, hi in zip(BINS_PX[:-1], BINS_PX[1:])) + " |",
              "|---|" + "---|" * (len(BINS_PX) - 1)]
    for r in reports:
        cells = {tuple(b["true_px"]): f"{b['registration_mae_px']:.2f} / {b['vertex_px']:.2f} ({b['frames']})"
                 for b in r["by_true_registration"]}
        row = [cells.get((lo, hi), "-") for lo, hi in zip(BINS_PX[:-1], BINS_PX[1:])]
        lines.append(f"| {', '.join(Path(p).name for p in r['datasets'])} ({r['split']}) | " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"
