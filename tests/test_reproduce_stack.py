"""`make reproduce TASK=stack PROFILE=smoke`: the state pipeline on the 3-D MuJoCo task (its own file, so the suite's
workers run it beside the other pipelines rather than after them)."""

from __future__ import annotations

import shutil

import pytest
from test_reproduce import run_baselines_smoke, run_state_smoke


@pytest.mark.slow
@pytest.mark.extended  # make test-extended: CI's 15 minutes hold the swap pipeline, not every task's
@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_the_stack_task_runs_the_same_stages(tmp_path):
    """Collection, both trainings, ranking, ascent and the ceiling replaying MuJoCo, on 4-d actions and 18-d states."""
    args = run_state_smoke("stack", "Block Stacking", tmp_path)
    run_baselines_smoke(args, tmp_path, "stack")  # V-GPS, DreamerV3- and LaDi-WM-style on this task
