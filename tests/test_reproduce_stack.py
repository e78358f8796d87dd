"""`make reproduce TASK=stack PROFILE=smoke`, then `make reproduce-vision TASK=stack PROFILE=smoke`: the state and vision
pipelines on the 3-D MuJoCo task (its own file, so the suite's workers run it beside the other pipelines rather than
after them)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from test_reproduce import run_baselines_smoke, run_state_smoke, run_vision_smoke

from gpc.datasets.store import EpisodeStore


@pytest.mark.slow
@pytest.mark.extended  # make test-extended: CI's 15 minutes hold the Push-T pipelines, not every task's
@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_the_stack_task_runs_the_same_stages(tmp_path):
    """Collection, both trainings, ranking, ascent and the ceiling replaying MuJoCo, on 4-d actions and 18-d states; then
    vision: a visual model read by the learned state reader (the red cube's position and height), an image reward
    that reads the state and scores it with the stack's own reward."""
    args = run_state_smoke("stack", "Block Stacking", tmp_path)
    runs, results = tmp_path / "runs", tmp_path / "results"
    state_eval = json.loads((runs / "wm-phase2" / "eval" / "world_model_eval.json").read_text())
    assert "object_height" in state_eval["steps"][0]["model"] and state_eval["unit"] == "mm"
    assert "| object mm | object height mm |" in (runs / "wm-phase2" / "eval" / "world_model_eval.md").read_text()
    opt = json.loads((results / "opt-M3" / "summary.json").read_text())["run"]["controller"]["planner"]
    assert opt["lr"] == pytest.approx(0.4 / 256)  # the default step: 1/256 of the 0.4 m action box, not Push-T's 2 px
    # Its planners use the on-policy model (WM_PLAN.stack): phase 2 continued on the policy's own recorded episodes too
    record = json.loads((runs / "wm-onpolicy" / "run.json").read_text())
    assert [Path(d).name for d in record["datasets"]] == ["expert.zarr", "explore.zarr", "policy-episodes.zarr"]
    assert EpisodeStore.open(runs / "policy-episodes-heldout.zarr").n_episodes == 2
    used = json.loads((results / "rank-K4" / "summary.json").read_text())["run"]["checkpoints"]
    assert str(runs / "wm-onpolicy" / "checkpoints" / "last.ckpt") in used
    run_baselines_smoke(args, tmp_path, "stack", stores=3, suffix="-onpolicy")  # V-GPS, DreamerV3-, LaDi-style: its data
    vres, _, runs = run_vision_smoke(["reproduce-vision" if a == "reproduce" else a for a in args], tmp_path, "stack")
    assert (vres / "stack_vision.md").read_text().startswith("# Vision Block Stacking, PROFILE=smoke")
    planning = json.loads((runs / "wm-visual-onpolicy-1step" / "eval" / "world_model_eval.json").read_text())
    assert "readout" not in planning and list(planning["state_readout"]) == ["red", "red height", "agent"]
    assert planning["state_readout_config"]["checkpoint"] == str(runs / "reward" / "checkpoints" / "last.ckpt")
    reward = json.loads((runs / "reward" / "run.json").read_text())["config"]
    assert reward["state_reward"] == "gpc.tasks.stack.reward:stack_reward" and reward["state_dim"] == 18
