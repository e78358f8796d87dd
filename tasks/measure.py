"""What every task's ``python -m gpc.tasks.TASK.measure`` shares: its arguments and the expert's summary.

A task's measure module records its expert on seeds (episodes stop at success, as demonstrations do) and its
explorer (episodes run all their steps), and prints the figures its docs quote as JSON.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from gpc.tasks.base import EpisodeStats


def seed_range(text: str) -> range:
    """``START:STOP`` as a range of seeds."""
    start, stop = (int(x) for x in text.split(":"))
    return range(start, stop)


def parse_seeds(description: str, argv: Sequence[str] | None) -> tuple[range, range]:
    """``--seeds`` (the expert's, the test seeds by default) and ``--explore-seeds`` (the same unless given)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--seeds", default="100000:100100", help="START:STOP")
    parser.add_argument("--explore-seeds", default=None, help="START:STOP for exploration (default: --seeds)")
    args = parser.parse_args(argv)
    return seed_range(args.seeds), seed_range(args.explore_seeds or args.seeds)


def summarise(stats: Sequence[EpisodeStats]) -> dict[str, Any]:
    """Scripted episodes in figures: mean and least score (an episode's max reward), success rate, mean and most
    steps, contact share and the seeds missed (also what `gpc eval-expert` writes)."""
    scores = np.array([s.score for s in stats])
    return {"episodes": len(stats), "mean_score": float(scores.mean()), "min_score": float(scores.min()),
            "success_rate": float(np.mean([s.success for s in stats])), "mean_steps": float(np.mean([s.steps for s in stats])),
            "max_steps_used": int(max(s.steps for s in stats)),
            "contact_fraction": float(np.mean([s.contact_fraction for s in stats])),
            "misses": [{"seed": s.seed, "score": s.score} for s in stats if not s.success]}


def expert_summary(record: Callable[[int], EpisodeStats], seeds: Iterable[int]) -> dict[str, Any]:
    """``summarise`` of ``record`` run on each seed, with the seconds taken."""
    t0 = time.perf_counter()
    stats = [record(int(seed)) for seed in seeds]
    return {**summarise(stats), "seconds": time.perf_counter() - t0}
