"""What a table costs: decisions x seconds per decision, per controller, from `gpc eval` result folders.

Decisions are counted from each folder's episodes (an episode ends at success, so better planners take fewer),
seconds per decision are the run's own (a lockstep call's time over its episodes) or, with ``--seconds``, another
machine's figure for the same controller (the paper's GPU timings). A planning budget for a bigger run, measured
on one that was run.

    python -m benchmarks.table_cost RESULT_DIR [RESULT_DIR ...] [--seconds NAME=S ...]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path


def cost(folder: Path, seconds: float | None = None) -> dict[str, float]:
    """``folder``'s decisions, seconds per decision (its own unless given) and hours."""
    summary = json.loads((folder / "summary.json").read_text())
    episodes = json.loads((folder / "episodes.json").read_text())
    episodes = episodes["episodes"] if isinstance(episodes, dict) else episodes
    steps = summary.get("n_action_steps") or 8  # BC's summary names none: the policy's 8
    decisions = sum(math.ceil(e["steps"] / steps) for e in episodes)
    per = summary["decision_latency_s"]["mean"] if seconds is None else seconds
    return {"episodes": len(episodes), "decisions": decisions, "s_per_decision": per, "hours": decisions * per / 3600}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--seconds", action="append", default=[], help="NAME=S: seconds per decision for the folder NAME.")
    args = parser.parse_args()
    given = {name: float(s) for name, _, s in (item.partition("=") for item in args.seconds)}
    print("| controller | episodes | decisions | s/decision | hours |\n|---|---|---|---|---|")
    total = 0.0
    for folder in args.folders:
        row = cost(folder, given.get(folder.name))
        total += row["hours"]
        print(f"| {folder.name} | {row['episodes']} | {row['decisions']:,} | {row['s_per_decision']:.3g} | {row['hours']:.1f} |")
    print(f"| total | | | | {total:.1f} |")


if __name__ == "__main__":
    main()
