"""One episode's result row, kept step by step alike by `gpc eval` (``evaluation.run_group``) and a served robot
(``gpc.serving.robot``), so the two score an episode the same way; no torch, for the robot's side."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from gpc.tasks.base import Task


def new_row(task: Task, seed: int) -> dict[str, Any]:
    """An episode's result before its first step (``add_step`` fills it; `gpc serve`'s robot keeps the same row)."""
    return {"seed": int(seed), "score": 0.0, "success": False, "steps": 0, **{f"{m}_max": 0.0 for m in task.info_metrics}}


def add_step(task: Task, row: dict[str, Any], reward: float, terminated: bool, truncated: bool,
             info: Mapping[str, Any]) -> bool:
    """One environment step into the episode's row; True when the episode ended: success, or the task's simulation
    went unstable (truncated; the episode keeps its score so far and says why)."""
    row["steps"] += 1
    row["score"] = max(row["score"], float(reward))
    for m in task.info_metrics:
        row[f"{m}_max"] = max(row[f"{m}_max"], float(info[m]))
    for m in task.info_minima:
        row[f"{m}_min"] = min(row.get(f"{m}_min", math.inf), float(info[m]))  # from the first step on
    row["success"] = row["success"] or bool(terminated)
    if truncated:
        row["unstable"] = str(info.get("unstable", "truncated"))
    return bool(terminated or truncated)
