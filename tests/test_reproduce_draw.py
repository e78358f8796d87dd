"""`make reproduce TASK=draw PROFILE=smoke`, then `make reproduce-vision TASK=draw PROFILE=smoke`: the state and vision
pipelines for a task without objects (its own file, so the suite's workers run it beside the other pipelines)."""

from __future__ import annotations

import json
import shutil

import pytest
from test_reproduce import run_baselines_smoke, run_state_smoke, run_vision_smoke


@pytest.mark.slow
@pytest.mark.extended  # make test-extended: CI's 15 minutes hold the Push-T pipelines, not every task's
@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_the_draw_task_runs_the_same_stages(tmp_path):
    """Collection, training, ranking, ascent through the drawing's own reward on states, and the ceiling; then vision:
    a visual model judged on its ink, an image reward that reads the state and scores it with the drawing's F1."""
    args = run_state_smoke("draw", "Triangle Drawing", tmp_path)
    run_baselines_smoke(args, tmp_path, "draw")  # V-GPS, DreamerV3- and LaDi-WM-style on this task
    vres, _, runs = run_vision_smoke(["reproduce-vision" if a == "reproduce" else a for a in args], tmp_path, "draw")
    assert (vres / "draw_vision.md").read_text().startswith("# Vision Triangle Drawing, PROFILE=smoke")
    evaluated = json.loads((runs / "wm-visual-phase2" / "eval" / "world_model_eval.json").read_text())
    assert "readout" not in evaluated and list(evaluated["regions"]) == ["ink"]  # no object: the ink, pixel by pixel
    reward = json.loads((runs / "reward" / "run.json").read_text())["config"]
    assert reward["state_reward"] == "gpc.tasks.draw.reward:from_layout" and reward["state_dim"] == 33
