"""The parts of the Push-T smoke pipeline that make test leaves to make test-extended for CI's 15 minutes: the vision
pipeline and its baselines, the ascent probe and the random-goal pipeline, on the same smoke settings as
test_reproduce's state pipeline."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_reproduce import ROOT, run_vision_baselines_smoke, run_vision_smoke


@pytest.mark.slow
@pytest.mark.extended  # make test-extended: eight minutes beyond test_reproduce's
@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_vision_baselines_the_probe_and_a_random_goal_on_the_smoke_pipeline(tmp_path):
    venv = Path(sys.executable).parent.parent
    args = ["make", "-s", "reproduce-pusht", "PROFILE=smoke", f"VENV={venv}", f"RUN_DIR={tmp_path / 'runs'}",
            f"RESULTS={tmp_path / 'results'}", "WORKERS=1"]
    vargs = [a.replace("reproduce-pusht", "reproduce-pusht-vision") for a in args]
    vres, shared, runs = run_vision_smoke(vargs, tmp_path, "pusht")
    plain = subprocess.run(vargs + ["VWM_PLAN=student", "-n"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert plain.returncode == 0 and "--world-model " + str(runs / "wm-visual-1step" / "checkpoints" / "last.ckpt") in plain.stdout
    assert str(shared / "vopt-M2") in plain.stdout and "--planner gt-sim" not in plain.stdout  # the ceiling is shared
    teacher = subprocess.run(vargs + ["VWM_PLAN=teacher", "-n"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert teacher.returncode == 0 and "--world-model " + str(runs / "wm-visual-phase2" / "checkpoints" / "last.ckpt") in teacher.stdout
    assert "wm-visual-1step" not in teacher.stdout and "results-vision-teacher" in teacher.stdout
    other = subprocess.run(vargs + ["SEEDS=100005:100007"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert other.returncode != 0 and "holds results for seeds 100000:100002, not 100005:100007 (SEEDS)" in other.stderr
    run_vision_baselines_smoke(vargs, tmp_path, "pusht")
    probe = subprocess.run(vargs[:2] + ["probe-opt-vision"] + vargs[3:], cwd=ROOT,
                           capture_output=True, text=True, timeout=300)
    assert probe.returncode == 0, probe.stdout[-2000:] + probe.stderr[-2000:]
    probed = json.loads((vres / "ascent-vopt-M2.json").read_text())
    assert probed["decisions"] > 0 and probed["steps"] == 2  # GPC-OPT M=2 with the on-policy student, replayed

    state_model = subprocess.run(args[:2] + [str(tmp_path / "runs" / "wm-phase2.done")] + args[3:], cwd=ROOT,
                                 capture_output=True, text=True, timeout=600)
    assert state_model.returncode == 0, state_model.stdout[-2000:] + state_model.stderr[-2000:]
    wm = tmp_path / "runs" / "wm-phase2" / "checkpoints" / "last.ckpt"
    wm_stamp = wm.stat().st_mtime_ns
    # GOAL=random: its own expert store and policy, the shared world model, BC and one planner run for real; the
    # rest of its table comes from the same rules as above, so a dry run shows them (a full table costs 90 s more)
    rg = [a.replace(f"RESULTS={tmp_path / 'results'}", f"RESULTS={tmp_path / 'results-rg'}") for a in args] + ["GOAL=random"]
    ranked = tmp_path / "results-rg" / "rank-K4" / "summary.json"
    random_goal = subprocess.run(rg[:2] + [str(ranked.parents[1] / "bc" / "summary.json"), str(ranked)] + rg[3:], cwd=ROOT,
                                 capture_output=True, text=True, timeout=600)
    assert random_goal.returncode == 0, random_goal.stdout[-2000:] + random_goal.stderr[-2000:]
    assert (tmp_path / "runs" / "policy-random-goal" / "checkpoints" / "last.ckpt").exists()
    assert (tmp_path / "runs" / "expert-random-goal.zarr" / "data" / "goal_keypoint").exists()
    assert wm.stat().st_mtime_ns == wm_stamp  # the goal-agnostic world model is shared, not retrained
    run = json.loads(ranked.read_text())["run"]
    assert run["config"]["goal"] == "random" and "policy-random-goal" in run["controller"]["policy"]
    assert json.loads((tmp_path / "results-rg" / "bc" / "summary.json").read_text())["run"]["config"]["goal"] == "random"
    rest = subprocess.run(rg + ["-n"], cwd=ROOT, capture_output=True, text=True, timeout=60).stdout
    assert rest.count("gpc eval") == 6 and rest.count("--goal random") == 6 and "--planner rank -K 4" not in rest
    assert "gpc train" not in rest and "gpc collect" not in rest and "random goal" in rest  # the table's title
