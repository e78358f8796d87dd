"""How far a state world model's rollouts drift from recorded futures, per horizon step.

Each held-out window gives a history of H recorded states and the next T recorded actions;
the model rolls them out open-loop and every predicted state is compared with the recorded
one. Beside it stands the trivial "nothing moves" baseline that copies the last history
state forward. Errors: object position, object height (3-D tasks), object angle (deg, wrapped), agent
position and the registration distance (mean vertex distance between predicted and recorded pose, what
the planner's reward reads), where the task's layout says they sit; lengths in state units, shown in the
layout's unit (px, or Block Stacking's metres as mm). The metric keys keep their ``_px`` names.

Given the task's planning reward, each step also reports that reward's error on the predicted future so far, and the last
step the rank correlation across windows of the reward's predicted and recorded *change* over the horizon: what
ranking chunks needs, and the only figure for a task whose state is no pose (Triangle Drawing's ink), which
"nothing moves" cannot score (its change is 0 everywhere).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from gpc.datasets.errors import DataError
from gpc.datasets.layout import TaskLayout
from gpc.datasets.sequence import HeldOutOf, WindowSpec, held_out_by, recorded_held_out, window_indices, window_starts
from gpc.datasets.windows import load_stores
from gpc.models.rewards.registration import layout_registration
from gpc.models.stats import spearman
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.state import ACTION_KEY, STATE_KEY, wrap_angle

SPLITS = ("val", "all")
# Metric -> its column ({unit}: the layout's length unit; a metric without it is no length).
METRICS = {"object_px": "object {unit}", "object_height": "object height {unit}", "object_deg": "object deg",
           "agent_px": "agent {unit}", "registration_px": "vertices {unit}", "reward": "reward"}


def per_step_reward(reward: Any, states: torch.Tensor) -> torch.Tensor:
    """``(N, T, D)`` future states -> ``(N, T)``: at step t the task's reward (built with ``aggregate="final"``) on
    the future up to t, as the planner scores a future. A reward that reads each state alone (registration) gives
    its value on state t; one that reads the whole future (the drawing's ink, grown along the pen's path from the
    first step's) gives what the planner would see of a chunk that long."""
    return torch.stack([reward(states[:, : i + 1]) for i in range(states.shape[1])], dim=1)


def state_errors(pred: torch.Tensor, true: torch.Tensor, layout: TaskLayout) -> dict[str, torch.Tensor]:
    """``(N, T, D)`` each -> metric name -> ``(N, T)`` errors (an object metric: the mean over the task's objects)."""
    out = {"object_px": torch.stack([(pred[..., list(o.pose[:2])] - true[..., list(o.pose[:2])]).norm(dim=-1)
                                     for o in layout.objects]).mean(dim=0)} if layout.objects else {}
    heights = [o.height for o in layout.objects if o.height is not None]
    if heights:
        out["object_height"] = torch.stack([(pred[..., z] - true[..., z]).abs() for z in heights]).mean(dim=0)
    turning = [o.angle for o in layout.objects if o.angle is not None]
    if turning:
        out["object_deg"] = torch.stack([wrap_angle(pred[..., a] - true[..., a]).abs() for a in turning]).mean(dim=0) * (180.0 / math.pi)
    if layout.state.agent_xy:
        ag = list(layout.state.agent_xy)
        out["agent_px"] = (pred[..., ag] - true[..., ag]).norm(dim=-1)
    if layout.objects:  # a task without objects (a drawing) has no outline to register
        out["registration_px"] = layout_registration(pred, true, layout)
    return out


def held_out_windows(module: WorldModelModule, datasets: Sequence[str | os.PathLike], keys: Sequence[str], split: str = "val",
                     episodes: int | None = None, horizon: int | None = None, stride: int = 1,
                     max_windows: int | None = None, held_out_of: HeldOutOf | None = None) -> tuple[Any, np.ndarray, np.ndarray, int]:
    """The evaluation windows: (arrays, chosen episodes, ``(N, n_obs + T)`` step indices, T).

    ``split="val"``: the validation episodes of the split the model was trained with (its
    recorded seed and ratio over the same list of stores); ``"all"``: every episode (for a
    store the model never saw). ``held_out_of``: instead, the episodes another run held out, so two
    models meet on the same unseen episodes (``held_out_by``). ``episodes``: only the first N of them. Windows start every
    ``stride`` steps (histories padded at episode starts, unless a store says its episodes begin mid-motion; futures
    never); ``max_windows``:
    only that many, evenly spread.
    """
    if split not in SPLITS:
        raise ValueError(f"split {split!r}: use one of {', '.join(SPLITS)}")
    if stride < 1:
        raise ValueError(f"stride {stride}: must be at least 1")
    if held_out_of is not None and split != "val":
        raise ValueError("--split all and --held-out-of exclude each other")
    h, t = module.n_obs_steps, horizon or module.config.horizon
    arrays = load_stores([str(p) for p in datasets], tuple(keys))
    if held_out_of is not None:
        chosen = held_out_by(held_out_of.record, module.data_record, arrays.sources, arrays.counts, held_out_of.name)
    elif split == "val":
        chosen = recorded_held_out(module.data_record, arrays.sources, arrays.counts)
        if len(chosen) == 0:
            raise DataError("the model was trained without held-out episodes; pass --split all with a separate store")
    else:
        chosen = np.arange(arrays.n_episodes)
    if episodes is not None:
        chosen = chosen[:episodes]
    rows = window_starts(arrays.episode_ends, chosen, WindowSpec(h + t, h - 1, 0), mid_motion=arrays.mid_motion)[::stride]
    if max_windows is not None and len(rows) > max_windows:
        rows = rows[np.linspace(0, len(rows) - 1, max_windows).round().astype(int)]
    idx = np.stack([window_indices(r, h + t) for r in rows])
    return arrays, chosen, idx, t


@torch.no_grad()
def evaluate_rollouts(
    module: WorldModelModule, datasets: Sequence[str | os.PathLike], split: str = "val", episodes: int | None = None,
    horizon: int | None = None, layout: TaskLayout | None = None, batch_size: int = 4096, stride: int = 1,
    held_out_of: HeldOutOf | None = None, reward: Any = None,
) -> dict[str, Any]:
    """Per-step mean errors of the state model and of the "nothing moves" baseline on held-out
    windows (see ``held_out_windows`` for ``split``, ``episodes``, ``stride``, ``held_out_of``); ``layout``: the
    task's, for where the object and the agent sit and the object's outline; ``reward``: the task's planning
    reward (``aggregate="final"``, needing no per-episode goal), judged too."""
    if layout is None:
        raise ValueError("evaluate_rollouts needs the task's layout (gpc.tasks.get_task(name).layout)")
    arrays, chosen, idx, t = held_out_windows(module, datasets, (STATE_KEY, ACTION_KEY), split, episodes, horizon, stride,
                                              held_out_of=held_out_of)
    h = module.n_obs_steps
    states = torch.from_numpy(arrays.data[STATE_KEY][idx]).float()
    actions = torch.from_numpy(arrays.data[ACTION_KEY][idx[:, h - 1 : h - 1 + t]]).float()
    sums: dict[str, dict[str, torch.Tensor]] = {"model": {}, "baseline": {}}
    changes: list[tuple[torch.Tensor, torch.Tensor]] = []  # (predicted, recorded) reward change over the horizon
    for lo in range(0, len(idx), batch_size):
        hist, acts, true = states[lo : lo + batch_size, :h], actions[lo : lo + batch_size], states[lo : lo + batch_size, h:]
        pred = module.rollout(hist, acts).cpu()
        still = hist[:, -1:].expand_as(true)
        if reward is not None:
            now, true_r = per_step_reward(reward, hist[:, -1:])[:, 0], per_step_reward(reward, true)
        for name, guess in (("model", pred), ("baseline", still)):
            errors = state_errors(guess, true, layout)
            if reward is not None:
                guess_r = per_step_reward(reward, guess)
                errors["reward"] = (guess_r - true_r).abs()
                if name == "model":
                    changes.append((guess_r[:, -1] - now, true_r[:, -1] - now))
            for metric, err in errors.items():
                sums[name][metric] = sums[name].get(metric, 0.0) + err.double().sum(dim=0)
    n = len(idx)
    ranking = None
    if changes:
        predicted, recorded = (torch.cat(c).double().numpy() for c in zip(*changes, strict=True))
        rho = spearman(predicted, recorded)
        ranking = {"spearman": None if np.isnan(rho) else rho, "predicted_std": float(predicted.std()),
                   "recorded_std": float(recorded.std())}
    means = {name: {m: (v / n).tolist() for m, v in d.items()} for name, d in sums.items()}
    steps = [{"step": i + 1, **{name: {m: means[name][m][i] for m in means[name]} for name in means}} for i in range(t)]
    return {
        "split": held_out_of.label if held_out_of else split, "datasets": [str(p) for p in datasets],
        "episodes": int(len(chosen)), "windows": int(n),
        "history": h, "horizon": t, "config": module.config.to_dict(), "steps": steps,
        "unit": layout.unit, "unit_scale": layout.unit_scale,
        "mean_over_steps": {name: {m: float(np.mean(v)) for m, v in means[name].items()} for name in means},
        "reward_change": ranking,
    }


def episodes_phrase(report: dict[str, Any]) -> str:
    """"12 val episodes", or "12 episodes held out by B.ckpt"."""
    split = report["split"]
    return f"{report['episodes']} {split} episodes" if split in SPLITS else f"{report['episodes']} episodes {split}"


def markdown_table(report: dict[str, Any], title: str = "World model rollouts") -> str:
    """One row per horizon step: each metric as ``model / baseline`` (baseline: nothing moves)."""
    metrics = [m for m in METRICS if m in report["steps"][0]["model"]]
    unit, scale = report.get("unit", "px"), report.get("unit_scale", 1.0)  # (reports before units: px)
    scales = {m: scale if "{unit}" in METRICS[m] else 1.0 for m in metrics}
    digits = {m: 3 if m == "reward" else 2 for m in metrics}  # a reward in [0, 1] (or so) needs a third digit
    lines = [
        f"## {title}", "",
        f"{report['windows']} windows from {episodes_phrase(report)}; history {report['history']}, "
        f"horizon {report['horizon']}. Each cell: model / nothing-moves baseline (mean error).", "",
        "| step | " + " | ".join(METRICS[m].format(unit=unit) for m in metrics) + " |",
        "|---|" + "---|" * len(metrics),
    ]
    for row in report["steps"] + [{"step": "mean", **report["mean_over_steps"]}]:
        cells = [f"{row['model'][m] * scales[m]:.{digits[m]}f} / {row['baseline'][m] * scales[m]:.{digits[m]}f}" for m in metrics]
        lines.append(f"| {row['step']} | " + " | ".join(cells) + " |")
    change = report.get("reward_change")
    if change and change["spearman"] is not None:
        lines += ["", f"The reward's change over the {report['horizon']} steps, predicted against recorded, across windows: "
                  f"Spearman {change['spearman']:.3f}; spread (std) {change['predicted_std']:.4f} predicted, "
                  f"{change['recorded_std']:.4f} recorded."]
    return "\n".join(lines) + "\n"
