"""Measuring the image reward's pose predictor against the true registration loss.

``evaluate_reward_predictor`` reads held-out
frames (the validation episodes of the training split, or every episode of a store the
predictor never saw, e.g. the human demonstrations) and compares the predicted registration
loss with the one computed from the recorded state.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gpc.datasets.errors import DataError
from gpc.datasets.sequence import recorded_held_out
from gpc.datasets.store import EpisodeStore
from gpc.models.rewards.learned import IMAGE_KEY, STATE_KEY, RewardPredictorModule, resize
from gpc.models.rewards.registration import pose_errors

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
    ranks = [np.argsort(np.argsort(v)).astype(np.float64) for v in (true, pred)]
    spearman = float(np.corrcoef(ranks[0], ranks[1])[0, 1]) if len(true) > 1 and ranks[0].std() > 0 and ranks[1].std() > 0 else float("nan")
    out: dict[str, Any] = {
        "frames": int(len(true)),
        "registration_mae_px": float(err.mean()), "registration_median_err_px": float(np.median(err)),
        "registration_p90_err_px": float(np.percentile(err, 90)),
        "constant_baseline_mae_px": float(np.abs(true - np.median(true)).mean()),
        "spearman": spearman, "true_registration_mean_px": float(true.mean()),
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
    for store, i in chosen:
        sl = store.episode_slice(i)
        frames = store.read(IMAGE_KEY, sl.start, sl.stop)[::stride]
        states = store.read(STATE_KEY, sl.start, sl.stop)[::stride]
        if frames.ndim != 4 or frames.shape[-1] != 3:
            raise DataError(f"{store.path}: data/{IMAGE_KEY} rows are {frames.shape[1:]}, expected RGB frames (H, W, 3)")
        frames = np.clip(np.rint(frames), 0, 255).astype(np.uint8)
        goals = None if goal_t is not None else store.read(GOAL_KEY, sl.start, sl.stop)[::stride]
        for lo in range(0, len(frames), batch_size):
            x = torch.from_numpy(frames[lo : lo + batch_size]).to(module.device).permute(0, 3, 1, 2).float() / 255.0
            x = x if frame_size is None else resize(x, frame_size)
            true = torch.from_numpy(np.asarray(states[lo : lo + batch_size], np.float32)).to(module.device)[:, list(c.pose_dims)]
            against = goal_t if goals is None else torch.from_numpy(np.asarray(goals[lo : lo + batch_size], np.float32)).to(module.device)
            for name, value in pose_errors(module.predictor(x), true, verts, against, c.sizes).items():
                parts.setdefault(name, []).append(value.double().cpu().numpy())
    errors = {k: np.concatenate(v) for k, v in parts.items()}
    return {"split": split, "datasets": [str(p) for p in datasets], "episodes": len(chosen), "stride": stride,
            "goal": "per episode" if goal_t is None else goal_t.tolist(),
            "frame_size": frame_size or int(frames.shape[1]), "input_size": c.input_size,
            "config": c.to_dict(), **_summary(errors)}


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
