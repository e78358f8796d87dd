"""`make reproduce TASK=draw PROFILE=smoke`: the state pipeline for a task without objects (its own file, so the
suite's workers run it beside the other pipelines)."""

from __future__ import annotations

import shutil

import pytest
from test_reproduce import run_baselines_smoke, run_state_smoke


@pytest.mark.slow
@pytest.mark.extended  # make test-extended: CI's 15 minutes hold the swap pipeline, not every task's
@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_the_draw_task_runs_the_same_stages(tmp_path):
    """Collection, training, ranking, ascent through the drawing's own reward on states, and the ceiling."""
    args = run_state_smoke("draw", "Triangle Drawing", tmp_path)
    run_baselines_smoke(args, tmp_path, "draw")  # V-GPS, DreamerV3- and LaDi-WM-style on this task
