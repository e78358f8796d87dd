"""Signals and kills: a stopped collection, evaluation or training says what it kept and resumes to the uninterrupted result."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest
from faults import eval_args, finish, gpc, inline, one_line, same_store, spawn, wait_for

from gpc.datasets.store import EpisodeStore
from gpc.models.policy.module import PolicyModule

pytestmark = pytest.mark.usefixtures("one_thread")


# ---------------------------------------------------------------------- interrupts are honest
@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> Path:
    clean = tmp_path_factory.mktemp("clean") / "clean.zarr"
    assert gpc("collect", "--out", str(clean), "--episodes", "8", "--no-images", "--max-steps", "120").returncode == 0
    return clean


# make test stops collection with SIGTERM and training with SIGINT (Ctrl-C); make test-extended sends each the other too
@pytest.mark.parametrize("sig,code", [pytest.param(signal.SIGINT, 130, marks=pytest.mark.extended), (signal.SIGTERM, 143)])
def test_a_stopped_collection_says_what_it_kept_and_resumes_to_the_same_store(tmp_path, uninterrupted, sig, code):
    out = tmp_path / "s.zarr"
    proc = spawn("collect", "--out", str(out), "--episodes", "8", "--no-images", "--max-steps", "120")
    wait_for(lambda: EpisodeStore.open(out).n_episodes >= 2)
    rc, err = finish(proc, sig)
    kept = EpisodeStore.open(out).n_episodes
    line = one_line((rc, err), code, f"stopped by {signal.Signals(sig).name}", f"{kept} whole episodes are in {out}", "resume")
    assert "Exception ignored" not in err and 2 <= kept < 8, line  # a signal in pymunk's callback is not swallowed
    assert gpc("collect", "--out", str(out), "--episodes", "8", "--no-images", "--max-steps", "120").returncode == 0
    same_store(out, uninterrupted)


def test_a_signal_to_the_whole_process_group_stops_parallel_collection_promptly(tmp_path):
    """`kill -- -PGID` (timeout, Slurm) ends the workers too; the parent must not wait forever for their episodes."""
    out = tmp_path / "s.zarr"
    proc = spawn("collect", "--out", str(out), "--episodes", "200", "--explore", "--no-images", "--max-steps", "300",
                 "--workers", "2", group=True)
    wait_for(lambda: EpisodeStore.open(out).n_episodes >= 2)
    os.killpg(proc.pid, signal.SIGTERM)
    t0 = time.time()
    rc, err = finish(proc)
    kept = EpisodeStore.open(out).n_episodes
    one_line((rc, err), 143, "stopped by SIGTERM", f"{kept} whole episodes are in {out}", alone=False)
    assert time.time() - t0 < 30


def _workers_of(pid: int) -> list[int]:
    """The multiprocessing workers ``pid`` spawned (Linux's /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[1]) == pid and b"spawn_main" in (stat.parent / "cmdline").read_bytes():
                found.append(int(stat.parent.name))
        except (OSError, IndexError, ValueError):  # a process that ended while read
            pass
    return found


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from Linux's /proc")
def test_a_second_signal_ends_the_parallel_workers_with_their_parent(tmp_path):
    """make passes its SIGTERM on to the job and the user's kill adds one: gpc ends at once, its workers with it
    (they once played their lockstep groups to the end, for minutes, then died on a broken pipe)."""
    out = tmp_path / "s.zarr"
    proc = spawn("collect", "--out", str(out), "--episodes", "200", "--explore", "--no-images", "--max-steps", "300",
                 "--workers", "2")
    wait_for(lambda: EpisodeStore.open(out).n_episodes >= 2)
    workers = _workers_of(proc.pid)
    assert len(workers) == 2
    proc.send_signal(signal.SIGTERM)
    time.sleep(0.05)  # two signals pending at once are one signal
    proc.send_signal(signal.SIGTERM)
    one_line(finish(proc), 143, "second signal ended gpc at once")  # alone: no resource-tracker warning below it
    wait_for(lambda: not any(Path(f"/proc/{pid}").exists() for pid in workers), timeout=10)


@pytest.mark.extended  # make test-extended: recording writes through collection's store writer, stopped above
def test_a_stopped_recording_keeps_whole_episodes_and_resumes_to_the_same_store(tiny_pusht, tmp_path):
    """`gpc record` (a planner's closed-loop episodes): SIGTERM between lockstep groups (of one), then the same command."""
    args = lambda out: ("record", str(tiny_pusht["policy"]), "--planner", "opt", "-M", "2", "--world-model",  # noqa: E731
                        str(tiny_pusht["wm"]), "--episodes", "4", "--seed", "60000", "--batch", "1", "--max-steps", "40",
                        "--out", str(out))
    clean, out = tmp_path / "clean.zarr", tmp_path / "s.zarr"
    assert gpc(*args(clean)).returncode == 0
    proc = spawn(*args(out))
    wait_for(lambda: EpisodeStore.open(out).n_episodes >= 2)
    rc, err = finish(proc, signal.SIGTERM)
    kept = EpisodeStore.open(out).n_episodes
    one_line((rc, err), 143, "stopped by SIGTERM", f"{kept} whole episodes are in {out}", "resume")
    assert 2 <= kept < 4
    assert gpc(*args(out)).returncode == 0
    same_store(out, clean)


def test_a_stopped_or_killed_eval_resumes_to_the_results_of_an_uninterrupted_one(tiny_pusht, tmp_path):
    out, clean = tmp_path / "res", tmp_path / "clean"
    assert gpc(*eval_args(tiny_pusht, clean)).returncode == 0
    proc = spawn(*eval_args(tiny_pusht, out))
    wait_for(lambda: len(list((out / ".groups").glob("group-*.json"))) >= 2)
    one_line(finish(proc, signal.SIGTERM), 143, "stopped by SIGTERM", "lockstep groups are kept", "--resume")
    one_line(inline(*eval_args(tiny_pusht, out)), 2, str(out), "--resume")  # a plain re-run does not clobber them
    proc = spawn(*eval_args(tiny_pusht, out, "--resume"))
    wait_for(lambda: len(list((out / ".groups").glob("group-*.json"))) >= 4)
    finish(proc, signal.SIGKILL)
    assert gpc(*eval_args(tiny_pusht, out, "--resume")).returncode == 0
    rows = lambda d: [{k: r[k] for k in ("seed", "score", "steps", "success", "final_state")}  # noqa: E731
                      for r in json.loads((d / "episodes.json").read_text())]
    assert rows(out) == rows(clean) and not (out / ".groups").exists()


@pytest.mark.parametrize("sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.extended)])  # SIGTERM: Slurm's preemption
def test_a_stopped_training_keeps_its_last_step_and_resumes(tiny_pusht, tmp_path, sig):
    run = tmp_path / "run"
    args = ["train", "policy", "--dataset", str(tiny_pusht["store"]), "--out", str(run), "--profile", "tiny", "--max-steps", "300",
            "--batch-size", "8", "--accelerator", "cpu", "--no-progress", "--checkpoint-every", "10000", "--val-every", "10000"]
    proc = spawn(*args)
    wait_for(lambda: (run / "tensorboard").is_dir() and any((run / "tensorboard").iterdir()), timeout=180)
    time.sleep(1.0)
    name = signal.Signals(sig).name
    line = one_line(finish(proc, sig), 128 + sig, f"stopped by {name}", "training stopped at step", "--resume", alone=False)
    step = int(line.split("training stopped at step ")[1].split(";")[0])
    assert 0 < step < 300 and PolicyModule.load_from_checkpoint(run / "checkpoints" / "last.ckpt") is not None
    import torch

    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == step
    assert not (run / "checkpoints" / "best.ckpt").exists(), "the stop waited for a validation pass"
    done = gpc(*args, "--resume")
    assert done.returncode == 0 and "step 300;" in done.stdout, done.stderr[-1500:]


def test_a_killed_training_loses_at_most_checkpoint_minutes_and_resumes(tiny_pusht, tmp_path):
    """SIGKILL (a machine taken back) runs no handler: slow steps still lose little, because the clock refreshes last.ckpt."""
    import torch

    run = tmp_path / "run"
    args = lambda steps: ["train", "policy", "--dataset", str(tiny_pusht["store"]), "--out", str(run), "--profile", "tiny",  # noqa: E731
                          "--max-steps", str(steps), "--batch-size", "8", "--accelerator", "cpu", "--no-progress",
                          "--checkpoint-every", "100000", "--val-every", "100000", "--checkpoint-minutes", "0.01"]
    proc = spawn(*args(100000))
    last = run / "checkpoints" / "last.ckpt"
    wait_for(lambda: torch.load(last, weights_only=True)["global_step"] > 0, timeout=180)
    first = torch.load(last, weights_only=True)["global_step"]
    wait_for(lambda: torch.load(last, weights_only=True)["global_step"] > first, timeout=60)  # refreshed again, by the clock
    finish(proc, signal.SIGKILL)
    step = torch.load(last, weights_only=True)["global_step"]
    assert 0 < step < 100000 and not (run / "checkpoints" / "best.ckpt").exists()
    done = gpc(*args(step + 5), "--resume")
    assert done.returncode == 0 and f"step {step + 5};" in done.stdout, done.stderr[-1500:]
