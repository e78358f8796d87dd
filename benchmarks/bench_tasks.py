"""Every other task's simulator on one core, through the task interface (what collection, evaluation and the
ground-truth ceiling call): stepping with reward, rendering, save and restore, scripted episodes.

Push-T has its own, older benchmark (``bench_sim``); this one times any registered task the same way, so a task's
cost is measured where it is added (issue 45: Block Stacking's MuJoCo steps per second, with and without rendering).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from benchmarks.common import median_seconds, publish
from gpc.tasks import get_task

TASKS = ("swap", "draw", "stack")
SEED = 100000


def run(doc: Path | None, tasks: Sequence[str] = TASKS) -> list[list[str]]:
    """Pinned to one core while timing, as ``bench_sim`` is."""
    cores = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    if cores:
        os.sched_setaffinity(0, {min(cores)})
    try:
        rows = [row for name in tasks for row in _task_rows(name)]
    finally:
        if cores:
            os.sched_setaffinity(0, cores)
    header = ["task", "work", "throughput", "latency (median)"]
    publish("Task simulators, one core", "tasks", header, rows, doc, key=2)
    return rows


def _task_rows(name: str) -> list[list[str]]:
    task = get_task(name)
    box = task.layout.action
    env = task.make_env("fixed")
    env.reset(seed=SEED)
    # Random targets over the action box, a new one every step (the env clips each entry to its own range).
    targets = np.random.default_rng(0).uniform(box.low, box.high, size=(4096, box.dim))
    i = [0]

    def step() -> None:
        i[0] = (i[0] + 1) % len(targets)
        env.step(targets[i[0]])

    t_step = median_seconds(step, number=300)
    t_frame = median_seconds(lambda: env.frame(96), number=200)
    t_pixels = median_seconds(lambda: (step(), env.frame(96)), number=200)
    saved = task.observe(env, False, True)[task.sim_key]
    t_save = median_seconds(lambda: task.observe(env, False, True), number=500)
    simulator = task.simulator()  # the ceiling's world model: restores a saved state before each proposal's rollout
    t_restore = median_seconds(lambda: simulator.restore(saved), number=500)
    episodes = {}
    for kind in ("expert", "explore"):
        times = []
        for seed in range(3):
            t0 = time.perf_counter()
            task.record(kind, SEED + seed, "fixed", True, task.max_episode_steps)
            times.append(time.perf_counter() - t0)
        episodes[kind] = times
    return [
        [name, "state step + reward", f"{1 / t_step:,.0f} steps/s", f"{t_step * 1e6:.0f} us"],
        [name, "render 96x96 (env.frame)", f"{1 / t_frame:,.0f} frames/s", f"{t_frame * 1e6:.0f} us"],
        [name, "pixels step (step + render)", f"{1 / t_pixels:,.0f} steps/s", f"{t_pixels * 1e6:.0f} us"],
        [name, "save (observe the simulator state)", f"{1 / t_save:,.0f} /s", f"{t_save * 1e6:.1f} us"],
        [name, "restore (the ceiling's simulator)", f"{1 / t_restore:,.0f} /s", f"{t_restore * 1e6:.1f} us"],
        *[[name, f"{kind} episode (with images)", f"{np.median(t):.2f} s median", f"{max(t):.2f} s max"]
          for kind, t in episodes.items()],
    ]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--doc", type=Path, default=None, help="write the latest figures to this doc (docs/benchmarks.md)")
    parser.add_argument("--task", action="append", choices=TASKS, help="only this task (repeatable; default: every one)")
    args = parser.parse_args()
    run(args.doc, args.task or TASKS)
