"""The swap collectors' figures: the expert's score and success, the explorer's contact shares.

``python -m gpc.tasks.swap.measure --seeds 100000:100100`` prints them as JSON (expert episodes stop at success, as
demonstrations do; exploration episodes run all their steps).
"""

from __future__ import annotations

import json
from collections.abc import Sequence

from gpc.tasks.measure import expert_summary, parse_seeds
from gpc.tasks.swap.env import MAX_EPISODE_STEPS
from gpc.tasks.swap.expert import SwapExpert
from gpc.tasks.swap.explore import ExploreConfig, evaluate_explore
from gpc.tasks.swap.record import RecordConfig, record_episode


def evaluate_expert(seeds: Sequence[int], max_steps: int = MAX_EPISODE_STEPS) -> dict:
    """Mean score (an episode's max reward), success rate, steps and the seeds it missed."""
    config = RecordConfig(max_steps=max_steps, images=False)
    return expert_summary(lambda seed: record_episode(SwapExpert(), seed, config)[1], seeds)


def main(argv: Sequence[str] | None = None) -> None:
    seeds, explore_seeds = parse_seeds(__doc__.splitlines()[0], argv)
    explore = {mode: evaluate_explore(explore_seeds, ExploreConfig(mode=mode)) for mode in ("mixed", "pushes", "perturbed")}
    keep = ("steps", "contact_fraction", "agent_cube", "agent_sphere", "cube_sphere", "moving")
    print(json.dumps({"expert": evaluate_expert(seeds), "seeds": f"{seeds.start}:{seeds.stop}",
                      "explore": {mode: {k: r[k] for k in keep} for mode, r in explore.items()}}, indent=1))


if __name__ == "__main__":
    main()
