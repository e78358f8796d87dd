"""The stacking collectors' figures: the expert's score and success, the explorer's contact shares.

``python -m gpc.tasks.stack.measure --seeds 100000:100100`` prints them as JSON (expert episodes stop at success, as
demonstrations do; exploration episodes run all their steps).
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence

from gpc.tasks.measure import expert_summary, parse_seeds
from gpc.tasks.stack.env import MAX_EPISODE_STEPS
from gpc.tasks.stack.expert import StackExpert
from gpc.tasks.stack.explore import evaluate_explore
from gpc.tasks.stack.record import RecordConfig, record_episode


def evaluate_expert(seeds: Sequence[int], max_steps: int = MAX_EPISODE_STEPS) -> dict:
    """Mean score (an episode's max reward), success rate, steps and the seeds it missed."""
    config = RecordConfig(max_steps=max_steps, images=False)
    return expert_summary(lambda seed: record_episode(StackExpert(), seed, config)[1], seeds)


def main(argv: Sequence[str] | None = None) -> None:
    seeds, explore_seeds = parse_seeds(__doc__.splitlines()[0], argv)
    t0 = time.perf_counter()
    explore = evaluate_explore(explore_seeds)
    explore["seconds"] = time.perf_counter() - t0
    print(json.dumps({"expert": evaluate_expert(seeds), "seeds": f"{seeds.start}:{seeds.stop}", "explore": explore},
                     indent=1))


if __name__ == "__main__":
    main()
