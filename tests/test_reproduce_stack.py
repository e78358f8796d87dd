"""`make reproduce TASK=stack PROFILE=smoke`: the state pipeline on the 3-D MuJoCo task (its own file, so the suite's
workers run it beside the other pipelines rather than after them)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_reproduce import ROOT, assert_table_is_what_was_measured

from gpc.datasets.store import EpisodeStore


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_the_stack_task_runs_the_same_stages(tmp_path):
    """Collection, both trainings and every planner (the ceiling replaying MuJoCo) on 4-d actions and 18-d states."""
    venv = Path(sys.executable).parent.parent
    args = ["make", "-s", "reproduce", "TASK=stack", "PROFILE=smoke", f"VENV={venv}", f"RUN_DIR={tmp_path / 'runs'}",
            f"RESULTS={tmp_path / 'results'}", "WORKERS=1"]
    done = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    store = EpisodeStore.open(tmp_path / "runs" / "expert.zarr")
    assert store.attrs["task"] == "stack"
    table = json.loads((tmp_path / "results" / "stack_state.json").read_text())
    assert table["task"] == "stack" and [r["label"] for r in table["rows"]] == [
        "bc", "rank K=4", "opt M=3", "rank-opt 4x3", "cem 8x2", "mppi 8x2", "grad 4x3", "gt-sim K=4"]
    md = (tmp_path / "results" / "stack_state.md").read_text()
    assert md.startswith("# State Block Stacking, PROFILE=smoke")
    assert_table_is_what_was_measured(table, md, [tmp_path / "results" / n for n in (
        "bc", "rank-K4", "opt-M3", "rank-opt-4x3", "cem-8x2", "mppi-8x2", "grad-4x3", "gt-sim-K4")])
