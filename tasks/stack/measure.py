"""The stacking collectors' figures: the expert's score and success, the explorer's contact shares.

``python -m gpc.tasks.stack.measure --seeds 100000:100100`` prints them as JSON (expert episodes stop at success, as
demonstrations do; exploration episodes run all their steps).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence

import numpy as np

from gpc.tasks.stack.env import MAX_EPISODE_STEPS
from gpc.tasks.stack.expert import StackExpert
from gpc.tasks.stack.explore import evaluate_explore
from gpc.tasks.stack.record import RecordConfig, record_episode


def evaluate_expert(seeds: Sequence[int], max_steps: int = MAX_EPISODE_STEPS) -> dict:
    """Mean score (an episode's max reward), success rate, steps and the seeds it missed."""
    config = RecordConfig(max_steps=max_steps, images=False)
    t0 = time.perf_counter()
    stats = [record_episode(StackExpert(), int(seed), config)[1] for seed in seeds]
    return {"episodes": len(stats), "mean_score": float(np.mean([s.score for s in stats])),
            "min_score": float(min(s.score for s in stats)), "success_rate": float(np.mean([s.success for s in stats])),
            "mean_steps": float(np.mean([s.steps for s in stats])), "max_steps_used": int(max(s.steps for s in stats)),
            "contact_fraction": float(np.mean([s.contact_fraction for s in stats])),
            "misses": [{"seed": s.seed, "score": s.score} for s in stats if not s.success], "seconds": time.perf_counter() - t0}


def _range(text: str) -> range:
    start, stop = (int(x) for x in text.split(":"))
    return range(start, stop)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="100000:100100", help="START:STOP")
    parser.add_argument("--explore-seeds", default=None, help="START:STOP for exploration (default: --seeds)")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    explore = evaluate_explore(_range(args.explore_seeds or args.seeds))
    explore["seconds"] = time.perf_counter() - t0
    print(json.dumps({"expert": evaluate_expert(_range(args.seeds)), "seeds": args.seeds, "explore": explore}, indent=1))


if __name__ == "__main__":
    main()
