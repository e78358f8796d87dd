"""Push-T simulator throughput on one core: stepping with reward, rendering, save/restore, collection.

Targets (issue 2): >= 3,000 state steps/s with reward (gym-pusht: ~1,570), restore <= 50 us.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from benchmarks.common import median_seconds, publish
from gpc.tasks.pusht.env import PushTEnv
from gpc.tasks.pusht.record import RecordConfig, record_episode


def run(doc: Path | None) -> list[list[str]]:
    """The targets are per core: pin this process to one core while timing."""
    cores = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    if cores:
        os.sched_setaffinity(0, {min(cores)})
    try:
        return _run(doc)
    finally:
        if cores:
            os.sched_setaffinity(0, cores)


def _run(doc: Path | None) -> list[list[str]]:
    env = PushTEnv(obs_type="state")
    env.reset(seed=100000)
    rng = np.random.default_rng(0)
    targets = rng.uniform(150, 350, size=(4096, 2))
    i = [0]

    def step() -> None:
        i[0] = (i[0] + 1) % len(targets)
        env.step(targets[i[0]])

    t_step = median_seconds(step, number=2000)
    t_render = median_seconds(env.render, number=300)
    pix = PushTEnv(obs_type="pixels")
    pix.reset(seed=100000)
    t_pix = median_seconds(lambda: pix.step(targets[0]), number=300)
    snap = env.sim.snapshot()
    t_snap = median_seconds(env.sim.snapshot, number=20000)
    t_restore = median_seconds(lambda: env.sim.restore(snap), number=20000)

    from gpc.tasks.pusht import scripted_policy

    times = []
    for kind in ("expert", "explore"):
        for seed in range(3):
            t0 = time.perf_counter()
            _, stats = record_episode(scripted_policy(kind), seed,
                                      RecordConfig(stop_on_success=kind == "expert", images=True))
            times.append((kind, time.perf_counter() - t0, stats.steps))
    expert = [t for k, t, _ in times if k == "expert"]
    explore = [t for k, t, _ in times if k == "explore"]
    rows = [
        ["state step + reward", f"{1 / t_step:,.0f} steps/s", f"{t_step * 1e6:.0f} us", ">= 3,000 steps/s"],
        ["render 96x96", f"{1 / t_render:,.0f} frames/s", f"{t_render * 1e6:.0f} us", ""],
        ["pixels step (step + render)", f"{1 / t_pix:,.0f} steps/s", f"{t_pix * 1e6:.0f} us", ""],
        ["snapshot", f"{1 / t_snap:,.0f} /s", f"{t_snap * 1e6:.1f} us", ""],
        ["restore", f"{1 / t_restore:,.0f} /s", f"{t_restore * 1e6:.1f} us", "<= 50 us"],
        ["expert episode (with images)", f"{np.median(expert):.2f} s median", f"{max(expert):.2f} s max", "< 3 s"],
        ["explore episode (with images)", f"{np.median(explore):.2f} s median", f"{max(explore):.2f} s max", ""],
    ]
    header = ["work", "throughput", "latency (median)", "target"]
    publish("Push-T simulator, one core", "sim", header, rows, doc, key=1)
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--doc", type=Path, default=None, help="write the latest figures to this doc (docs/benchmarks.md)")
    run(parser.parse_args().doc)
