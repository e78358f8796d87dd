"""The drawing collectors' figures: the expert's score and success, the explorer's spread of episode scores.

``python -m gpc.tasks.draw.measure --seeds 100000:100100`` prints them as JSON. Expert episodes stop at success, as
demonstrations do (``expert``), and also run to the end of the expert's tour (``expert_full``: the F1 of a whole
drawing); exploration episodes run all their steps.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence

import numpy as np

from gpc.tasks.draw.env import MAX_EPISODE_STEPS
from gpc.tasks.draw.expert import DrawExpert
from gpc.tasks.draw.explore import MODES, ExploreConfig, evaluate_explore
from gpc.tasks.draw.record import RecordConfig, record_episode


def evaluate_expert(seeds: Sequence[int], stop_on_success: bool = True, max_steps: int = MAX_EPISODE_STEPS) -> dict:
    """Mean score (an episode's max F1), success rate, steps and the seeds it missed."""
    config = RecordConfig(max_steps=max_steps, stop_on_success=stop_on_success, images=False)
    t0 = time.perf_counter()
    stats = [record_episode(DrawExpert(), int(seed), config)[1] for seed in seeds]
    scores = np.array([s.score for s in stats])
    return {"episodes": len(stats), "mean_score": float(scores.mean()), "min_score": float(scores.min()),
            "success_rate": float(np.mean([s.success for s in stats])), "mean_steps": float(np.mean([s.steps for s in stats])),
            "misses": [{"seed": s.seed, "score": s.score} for s in stats if not s.success], "seconds": time.perf_counter() - t0}


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="100000:100100", help="START:STOP")
    parser.add_argument("--explore-seeds", default=None, help="START:STOP for exploration (default: --seeds)")
    args = parser.parse_args(argv)
    start, stop = (int(x) for x in args.seeds.split(":"))
    e_start, e_stop = (int(x) for x in (args.explore_seeds or args.seeds).split(":"))
    explore = {mode: evaluate_explore(range(e_start, e_stop), ExploreConfig(mode=mode)) for mode in MODES}
    print(json.dumps({"seeds": args.seeds, "expert": evaluate_expert(range(start, stop)),
                      "expert_full": evaluate_expert(range(start, stop), stop_on_success=False, max_steps=150),
                      "explore_seeds": args.explore_seeds or args.seeds, "explore": explore}, indent=1))


if __name__ == "__main__":
    main()
