"""The drawing collectors' figures: the expert's score and success, the explorer's spread of episode scores.

``python -m gpc.tasks.draw.measure --seeds 100000:100100`` prints them as JSON. Expert episodes stop at success, as
demonstrations do (``expert``), and also run to the end of the expert's tour (``expert_full``: the F1 of a whole
drawing); exploration episodes run all their steps.
"""

from __future__ import annotations

import json
from collections.abc import Sequence

from gpc.tasks.draw.env import MAX_EPISODE_STEPS
from gpc.tasks.draw.expert import DrawExpert
from gpc.tasks.draw.explore import MODES, ExploreConfig, evaluate_explore
from gpc.tasks.draw.record import RecordConfig, record_episode
from gpc.tasks.measure import expert_summary, parse_seeds


def evaluate_expert(seeds: Sequence[int], stop_on_success: bool = True, max_steps: int = MAX_EPISODE_STEPS) -> dict:
    """Mean score (an episode's max F1), success rate, steps and the seeds it missed."""
    config = RecordConfig(max_steps=max_steps, stop_on_success=stop_on_success, images=False)
    return expert_summary(lambda seed: record_episode(DrawExpert(), seed, config)[1], seeds)


def main(argv: Sequence[str] | None = None) -> None:
    seeds, explore_seeds = parse_seeds(__doc__.splitlines()[0], argv)
    explore = {mode: evaluate_explore(explore_seeds, ExploreConfig(mode=mode)) for mode in MODES}
    print(json.dumps({"seeds": f"{seeds.start}:{seeds.stop}", "expert": evaluate_expert(seeds),
                      "expert_full": evaluate_expert(seeds, stop_on_success=False, max_steps=150),
                      "explore_seeds": f"{explore_seeds.start}:{explore_seeds.stop}", "explore": explore}, indent=1))


if __name__ == "__main__":
    main()
