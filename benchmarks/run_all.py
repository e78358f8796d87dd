"""`make bench`: every benchmark, figures printed and the latest written to docs/benchmarks.md."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import (  # noqa: E402
    bench_memory,
    bench_planners,
    bench_policy,
    bench_sim,
    bench_tasks,
    bench_vision_planners,
    bench_vlm,
    bench_world_model,
)

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--doc", type=Path, default=None)
    parser.add_argument("--only", default=None,
                        choices=["sim", "tasks", "policy", "vlm", "world-model", "planners", "vision-planners", "memory"])
    args = parser.parse_args()
    if args.only in (None, "sim"):
        bench_sim.run(args.doc)
    if args.only in (None, "tasks"):
        bench_tasks.run(args.doc)
    if args.only in (None, "policy"):
        bench_policy.run(args.doc, obs="keypoints")
        bench_policy.run(args.doc, obs="image")
    if args.only in (None, "vlm"):
        bench_vlm.run(args.doc)
    if args.only in (None, "world-model"):
        bench_world_model.run(args.doc)
    if args.only in (None, "planners"):
        bench_planners.run(args.doc)
    if args.only in (None, "vision-planners"):
        bench_vision_planners.run(args.doc)
    if args.only in (None, "memory"):
        bench_memory.run(args.doc)
