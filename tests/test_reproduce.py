"""`make reproduce-pusht PROFILE=smoke` end to end, in a scratch directory, then resumed."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from gpc.datasets.store import EpisodeStore

ROOT = Path(__file__).resolve().parents[1]


def assert_table_is_what_was_measured(table: dict, md: str, runs: list[Path]) -> None:
    """Each row holds its own run's measured mean score, and its paired difference is the mean of the per-seed
    differences to BC (the first run) recomputed here from the episode files; the Markdown prints those figures."""
    bc = {r["seed"]: r["score"] for r in json.loads((runs[0] / "episodes.json").read_text())}
    for row, run in zip(table["rows"], runs, strict=True):
        episodes = {r["seed"]: r["score"] for r in json.loads((run / "episodes.json").read_text())}
        summary = json.loads((run / "summary.json").read_text())
        assert sorted(episodes) == sorted(bc) and row["seeds"] == len(bc)
        assert row["score"] == pytest.approx(summary["mean_score"]) == pytest.approx(sum(episodes.values()) / len(bc))
        assert row["score_diff"] == pytest.approx(sum(episodes[s] - bc[s] for s in bc) / len(bc))
        assert row["score_ci"][0] <= row["score_diff"] <= row["score_ci"][1]
        assert f"| {row['label']} | " in md and f"{row['score']:.3f}" in md


# Another task's state smoke pipeline ranks, ascends through the task's own reward and replays the ceiling; Push-T's
# runs every planner (the prior-free ones read nothing task-specific), which keeps `make test` within CI's budget.
TASK_SMOKE_PLANNERS = {"rank-K4": "rank K=4", "opt-M3": "opt M=3"}


def run_state_smoke(task: str, title: str, tmp_path: Path) -> list[str]:
    """`make reproduce TASK=task PROFILE=smoke` under ``tmp_path``: the stores and the table are the task's, and each row
    is what its run measured. Returns the make command (its RUN_DIR and RESULTS), for a vision run on the same data."""
    venv = Path(sys.executable).parent.parent
    args = ["make", "-s", "reproduce", f"TASK={task}", "PROFILE=smoke", f"VENV={venv}", f"RUN_DIR={tmp_path / 'runs'}",
            f"RESULTS={tmp_path / 'results'}", "WORKERS=1", f"PLANNERS={' '.join(TASK_SMOKE_PLANNERS)}"]
    done = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    for store in ("expert.zarr", "explore.zarr"):
        assert EpisodeStore.open(tmp_path / "runs" / store).attrs["task"] == task
    table = json.loads((tmp_path / "results" / f"{task}_state.json").read_text())
    assert table["task"] == task and [r["label"] for r in table["rows"]] == ["bc", *TASK_SMOKE_PLANNERS.values(), "gt-sim K=4"]
    md = (tmp_path / "results" / f"{task}_state.md").read_text()
    assert md.startswith(f"# State {title}, PROFILE=smoke")
    assert_table_is_what_was_measured(table, md, [tmp_path / "results" / n for n in ("bc", *TASK_SMOKE_PLANNERS, "gt-sim-K4")])
    return args


BASELINE_ROWS = ["bc", "vgps K=4", "dreamer K=4", "ladi K=4", "rank K=4", "gt-sim K=4"]


def run_baselines_smoke(args: list[str], tmp_path: Path, task: str, stores: int = 2, suffix: str = "") -> None:
    """`make reproduce-baselines` on a state smoke pipeline's data and policy (``args``: its make command): each baseline
    trains on the planning model's ``stores`` with the task's reward (its run named with ``suffix``) and ranks the
    policy's proposals; the table holds what each run measured."""
    done = subprocess.run(["reproduce-baselines" if a == "reproduce" else a for a in args], cwd=ROOT, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    results = tmp_path / "results"
    table = json.loads((results / f"{task}_baselines.json").read_text())
    assert [r["label"] for r in table["rows"]] == BASELINE_ROWS
    for run, kind in (("vgps", "value"), ("latent", "latent-world-model"), ("ladi", "ladi-world-model")):
        record = json.loads((tmp_path / "runs" / f"{run}{suffix}" / "run.json").read_text())
        assert record["kind"] == kind and record["config"]["task"] == task and len(record["datasets"]) == stores
    assert_table_is_what_was_measured(table, (results / f"{task}_baselines.md").read_text(),
                                      [results / n for n in ("bc", "vgps-K4", "dreamer-K4", "ladi-K4", "rank-K4", "gt-sim-K4")])


def run_vision_baselines_smoke(vargs: list[str], tmp_path: Path, task: str) -> None:
    """`make reproduce-baselines-vision` after a vision smoke pipeline (``vargs``: its make command): each baseline trains
    on the stores reading what the image policy reads (its frozen encoder for LaDi) and ranks the image policy's
    proposals; the table pairs them with the vision table's BC, GPC row and ceiling, read from their own folders."""
    command = ["reproduce-baselines-vision" if a.startswith("reproduce") else a for a in vargs]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    shared, runs = tmp_path / "results-vision", tmp_path / "runs"
    table = json.loads((tmp_path / "results-vision-baselines" / f"{task}_baselines_vision.json").read_text())
    assert [r["label"] for r in table["rows"]] == ["bc", "vgps K=4", "dreamer K=4", "ladi K=4", "rank K=3", "gt-sim K=3"]
    for run in ("vgps", "latent", "ladi"):
        record = json.loads((runs / f"{run}-visual" / "run.json").read_text())
        assert record["config"]["encoder"]["obs_type"] == "image" and record["config"]["task"] == task
    ladi = json.loads((runs / "ladi-visual" / "run.json").read_text())["config"]
    assert ladi["policy"] == str(runs / "vpolicy" / "checkpoints" / "last.ckpt")  # the image policy's frozen encoder
    vb = tmp_path / "results-vision-baselines"
    assert_table_is_what_was_measured(table, (vb / f"{task}_baselines_vision.md").read_text(), [
        shared / "bc", vb / "vvgps-K4", vb / "vdreamer-K4", vb / "vladi-K4", tmp_path / "results-vision-onpolicy" / "vrank-K3",
        shared / "vgt-sim-K3"])


def run_vision_smoke(args: list[str], tmp_path: Path, task: str) -> tuple[Path, Path, Path]:
    """Run a task's vision smoke pipeline (``args``: the make command, RUN_DIR and RESULTS under ``tmp_path``) and check
    its table and its chain of models; returns (the planners' results, the shared BC and ceiling results, the runs)."""
    vision = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert vision.returncode == 0, vision.stdout[-2000:] + vision.stderr[-2000:]
    # the default model (VWM_PLAN=onpolicy) has its own rows; BC and the ceiling read none, so every model's table shares them
    vres, shared, runs = tmp_path / "results-vision-onpolicy", tmp_path / "results-vision", tmp_path / "runs"
    table = json.loads((vres / f"{task}_vision.json").read_text())
    assert table["task"] == task and [r["label"] for r in table["rows"]] == ["bc", "rank K=3", "opt M=2", "gt-sim K=3"]
    assert_table_is_what_was_measured(table, (vres / f"{task}_vision.md").read_text(),
                                      [shared / "bc", vres / "vrank-K3", vres / "vopt-M2", shared / "vgt-sim-K3"])
    assert "gap closed" in (vres / f"{task}_vision.md").read_text()
    for stage in ("vpolicy", "wm-visual-phase1", "reward"):  # every stage trained for this task
        assert json.loads((runs / stage / "run.json").read_text())["config"]["task"] == task
    phase2 = json.loads((runs / "wm-visual-phase2" / "run.json").read_text())
    assert phase2["init"] == str(runs / "wm-visual-phase1" / "checkpoints" / "last.ckpt")  # one schedule: no restarts
    student = json.loads((runs / "wm-visual-1step" / "run.json").read_text())
    assert student["init"] == str(runs / "wm-visual-phase2" / "checkpoints" / "last.ckpt")
    assert student["config"]["distill_from"] == student["init"] and student["config"]["dynamics"]["sampler"]["steps"] == 1
    # the on-policy model: GPC-OPT's own episodes recorded with the student, the teacher fine-tuned on them too, then
    # distilled again; that model plans
    recorded = runs / "wm-visual-opt-episodes.zarr"
    assert EpisodeStore.open(recorded).attrs["collector"]["world_model"] == str(
        runs / "wm-visual-1step" / "checkpoints" / "last.ckpt")
    tuned = json.loads((runs / "wm-visual-onpolicy" / "run.json").read_text())
    assert tuned["init"] == str(runs / "wm-visual-phase2" / "checkpoints" / "last.ckpt") and str(recorded) in tuned["datasets"]
    assert json.loads((runs / "wm-visual-onpolicy-1step" / "run.json").read_text())["init"] == str(
        runs / "wm-visual-onpolicy" / "checkpoints" / "last.ckpt")
    planned = json.loads((vres / "vopt-M2" / "summary.json").read_text())["run"]["controller"]
    assert planned["world_model"] == str(runs / "wm-visual-onpolicy-1step" / "checkpoints" / "last.ckpt")
    return vres, shared, runs


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_smoke_profile_runs_every_stage_and_resumes(tmp_path):
    venv = Path(sys.executable).parent.parent
    args = ["make", "-s", "reproduce-pusht", "PROFILE=smoke", f"VENV={venv}", f"RUN_DIR={tmp_path / 'runs'}",
            f"RESULTS={tmp_path / 'results'}", "WORKERS=1"]
    first = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
    summary = json.loads((tmp_path / "results" / "bc" / "summary.json").read_text())
    assert len(json.loads((tmp_path / "results" / "bc" / "episodes.json").read_text())) == 4
    assert 0.0 <= summary["mean_score"] <= 1.0
    assert (tmp_path / "runs" / "policy" / "checkpoints" / "last.ckpt").exists()
    table = json.loads((tmp_path / "results" / "pusht_state.json").read_text())
    labels = [r["label"] for r in table["rows"]]
    assert labels == ["bc", "rank K=4", "opt M=3", "rank-opt 4x3", "cem 8x2", "mppi 8x2", "grad 4x3", "gt-sim K=4"]
    md = (tmp_path / "results" / "pusht_state.md").read_text()
    assert_table_is_what_was_measured(table, md, [tmp_path / "results" / n for n in (
        "bc", "rank-K4", "opt-M3", "rank-opt-4x3", "cem-8x2", "mppi-8x2", "grad-4x3", "gt-sim-K4")])
    assert (tmp_path / "results" / "pusht_state.png").stat().st_size > 1000
    outputs = sorted((tmp_path / "results").rglob("summary.json")) + [tmp_path / "runs" / "expert.zarr" / "zarr.json"]
    stamps = {p: p.stat().st_mtime_ns for p in outputs if p.exists()}
    again = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stdout[-2000:] + again.stderr[-2000:]
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps  # every stage was up to date: nothing rewritten
    assert "| bc |" in again.stdout  # the table is printed again
    (tmp_path / "results" / "rank-K4" / "summary.json").unlink()  # one lost result: only that stage runs again
    third = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert third.returncode == 0 and (tmp_path / "results" / "rank-K4" / "summary.json").exists()
    assert {p: p.stat().st_mtime_ns for p in stamps if "rank-K4" not in str(p)} == {
        p: t for p, t in stamps.items() if "rank-K4" not in str(p)}
    # the paper's Table I: its seven planners on Ray, beside the BC and ceiling already measured, in a table of its own
    table1 = subprocess.run([a.replace("reproduce-pusht", "reproduce-pusht-table1") for a in args] + ["BACKEND=ray", "-n"],
                            cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert table1.returncode == 0, table1.stderr[-2000:]
    evals = [line for line in table1.stdout.splitlines() if "gpc eval" in line]
    assert [e.split("--planner ")[1].split(" --")[0].strip() for e in evals] == [
        "rank -K 100", "rank -K 1000", "rank -K 5000", "opt -M 30", "rank-opt -K 10 -M 30", "rank-opt -K 20 -M 30",
        "rank-opt -K 30 -M 20"]  # BC and the ceiling are up to date
    assert all("--backend ray" in e for e in evals)
    assert f"--out {tmp_path / 'results' / 'pusht_table1.md'}" in table1.stdout and "--paper pusht-state" in table1.stdout
    vargs = [a.replace("reproduce-pusht", "reproduce-pusht-vision") for a in args]  # its pipeline: test_reproduce_more
    other = subprocess.run(args + ["SEEDS=100005:100007"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert other.returncode != 0 and "holds results for seeds 100000:100004, not 100005:100007 (SEEDS)" in other.stderr
    elsewhere = [a.replace(f"RESULTS={tmp_path / 'results'}", f"RESULTS={tmp_path / 'results-s'}") for a in args]
    seeds = subprocess.run(elsewhere + ["SEEDS=100005:100007", "-n"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert "--seeds 100005:100007" in seeds.stdout and "--seeds 100000:" not in seeds.stdout  # its own folder: evaluated
    (tmp_path / "runs" / "wm-phase2.done").touch()  # a newer world model makes its planners stale, not the ceiling
    stale = subprocess.run(args + ["-n"], cwd=ROOT, capture_output=True, text=True, timeout=60).stdout
    assert "--planner rank -K 4" in stale and "--planner gt-sim" not in stale
    bad = subprocess.run(args + ["GOAL=moving"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert bad.returncode != 0 and "GOAL=moving: use fixed or random" in bad.stderr
    # the image policy reads no goal: GOAL=random is refused, not only renamed
    no_goal = subprocess.run(vargs + ["GOAL=random", "-n"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert no_goal.returncode != 0 and "GOAL=random: the vision pipeline has fixed goals only" in no_goal.stderr


def dry_run(target: str, *options: str) -> list[str]:
    """The commands ``make -n TARGET OPTIONS`` would run with this environment's gpc, one per line (continuations joined)."""
    venv = Path(sys.executable).parent.parent
    done = subprocess.run(["make", "-n", target, f"VENV={venv}", *options], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.replace("\\\n", " ").splitlines()


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_another_planning_model_shares_bc_and_the_ceiling(tmp_path):
    """WM_PLAN=onpolicy plans into its own results folder; BC and the ceiling read no world model, so its table takes
    them from the default model's folder instead of evaluating them again (24 minutes of Cube & Sphere Swapping's)."""
    evals = {}
    for plan in ("phase2", "onpolicy"):
        done = dry_run("reproduce", "TASK=swap", "PROFILE=smoke", f"RUN_DIR={tmp_path / 'runs'}", f"WM_PLAN={plan}")
        lines = [line for line in done if "gpc eval " in line and "gpc eval world-model" not in line]
        evals[plan] = {line.split("--out ")[1].split()[0] for line in lines}
    assert {"results/swap-smoke/bc", "results/swap-smoke/gt-sim-K4"} <= evals["phase2"] & evals["onpolicy"]
    assert "results/swap-smoke-wm-onpolicy/rank-K4" in evals["onpolicy"] and "results/swap-smoke/rank-K4" in evals["phase2"]
    assert not any(out.startswith("results/swap-smoke-wm-onpolicy/") for out in evals["onpolicy"] & evals["phase2"])


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_the_vision_tables_use_their_papers_seeds(tmp_path):
    """Table III (Swapping, Drawing, Stacking) is scored on 50 seeds with its rows, Push-T's vision table (Table II) on
    100 with K=50 as well; SEEDS still rules."""
    def evals(task: str, *extra: str) -> dict[str, str]:  # each evaluation's folder -> its seeds
        done = dry_run("reproduce-vision", f"TASK={task}", "PROFILE=cpu", f"RUN_DIR={tmp_path / task}",
                       f"RESULTS={tmp_path / task / 'results'}", *extra)
        return {Path(line.split("--out ")[1].split()[0]).name: line.split("--seeds ")[1].split()[0]
                for line in done if "gpc eval " in line and "--seeds" in line}

    table3 = {"bc", "vrank-K100", "vopt-M25", "vrank-opt-10x25", "vgt-sim-K100"}  # Table III's rows and the ceiling
    for task in ("draw", "swap", "stack"):
        assert evals(task) == dict.fromkeys(table3, "100000:100050"), task
    assert evals("pusht") == dict.fromkeys(table3 | {"vrank-K50"}, "100000:100100")  # Table II's, on 100 seeds
    assert set(evals("draw", "SEEDS=100000:100010").values()) == {"100000:100010"}


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_the_ranking_probe_judges_the_tables_scorer_on_validation_seeds(tmp_path):
    """`make probe-rank-vision` probes the world model and reward the table's GPC-RANK plans with, on validation seeds."""
    def commands(target: str) -> list[str]:
        return [line for line in dry_run(target, "TASK=draw", "PROFILE=cpu", f"RUN_DIR={tmp_path}") if "gpc eval " in line]

    probe = next(line for line in commands("probe-rank-vision") if "eval ranking" in line).split()
    rank = next(line for line in commands("reproduce-vision") if "--planner rank -K 100 " in line).split()
    for option in ("--reward-checkpoint", "--precision"):
        assert probe[probe.index(option) + 1] == rank[rank.index(option) + 1]
    assert probe[probe.index("--scorer") + 1] == "rank=" + rank[rank.index("--world-model") + 1]
    assert probe[probe.index("-K") + 1] == "100" and probe[probe.index("--seeds") + 1].startswith("2000")


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_an_ensemble_plan_trains_its_members_and_plans_with_one_file(tmp_path):
    """WM_PLAN=ensemble: the on-policy model and one more per ENSEMBLE_SEEDS (each with its seed), joined by `gpc
    ensemble` with PESSIMISM; every planner's --world-model is that file, its results in their own folder."""
    runs = tmp_path / "runs"
    lines = dry_run("reproduce", "TASK=swap", "PROFILE=smoke", f"RUN_DIR={runs}", "WM_PLAN=ensemble", "ENSEMBLE_SEEDS=3 4",
                    "PESSIMISM=0.5")
    trains = [line for line in lines if "gpc train world-model" in line and "--phase 2" in line]
    seeds = sorted(line.split("--seed ")[1].split()[0] for line in trains if "policy-episodes.zarr" in line)
    assert seeds == ["0", "3", "4"]  # the on-policy model and its two siblings, on the same data
    ensemble = f"{runs}/wm-onpolicy-ensemble-p0.5.ckpt"
    joined = [line for line in lines if "gpc ensemble" in line]
    assert len(joined) == 1 and "--pessimism 0.5" in joined[0] and joined[0].count("/checkpoints/last.ckpt") == 3
    planners = [line for line in lines if "gpc eval " in line and "--world-model" in line]
    assert planners and all(f"--world-model {ensemble}" in line for line in planners if "gt-sim" not in line)
    assert all("results/swap-smoke-wm-ensemble/" in line for line in planners if "gt-sim" not in line)
