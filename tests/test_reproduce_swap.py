"""`make reproduce TASK=swap PROFILE=smoke`, then `make reproduce-vision TASK=swap PROFILE=smoke` on the same data: the
state and vision pipelines for a second task (its own file, so the suite's workers run it beside the Push-T pipelines
rather than after them)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_reproduce import ROOT, run_baselines_smoke, run_state_smoke, run_vision_smoke

from gpc.datasets.store import EpisodeStore


@pytest.mark.slow
@pytest.mark.extended  # make test-extended: CI's 15 minutes hold the Push-T pipelines; swap's stages run in test_swap_task
@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_the_swap_task_runs_the_same_stages(tmp_path):
    """`make reproduce TASK=swap PROFILE=smoke`, then its vision pipeline: the same stages for a second task, its own
    tables, nothing named Push-T."""
    args = run_state_smoke("swap", "Cube & Sphere Swapping", tmp_path)
    run_baselines_smoke(args, tmp_path, "swap")  # V-GPS, DreamerV3- and LaDi-WM-style on a two-object task
    venv = Path(sys.executable).parent.parent
    refused = subprocess.run(["make", "-s", "reproduce-pusht-vision", "TASK=swap", f"VENV={venv}"], cwd=ROOT, capture_output=True,
                             text=True, timeout=60)
    assert refused.returncode != 0 and "are Push-T's spellings; use `make reproduce TASK=swap`" in refused.stderr
    # the vision pipeline on the same expert and exploration stores: every stage for this task, its own table, the
    # paper's swap row beside it, and the visual model judged on both objects
    vres, _, runs = run_vision_smoke(["reproduce-vision" if a == "reproduce" else a for a in args], tmp_path, "swap")
    md = (vres / "swap_vision.md").read_text()
    assert md.startswith("# Vision Cube & Sphere Swapping, PROFILE=smoke") and "0.680" in md  # the paper's BC
    readout = json.loads((runs / "wm-visual-phase2" / "eval" / "world_model_eval.json").read_text())["readout"]
    assert list(readout["objects"]) == ["cube", "sphere"]
    assert EpisodeStore.open(runs / "wm-visual-opt-episodes.zarr").attrs["task"] == "swap"
