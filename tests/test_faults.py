"""Faults a user meets, injected for real: other processes, signals, full and read-only disks, damaged files.

Every case runs the `gpc` command in its own process and checks three things: the exit code (2 for bad
input or an OS error, 130 / 143 for SIGINT / SIGTERM), that stderr is one line naming the file or option
and the problem (no traceback), and that every byte on disk before the command is still there.
docs/reliability.md lists the promises these cases hold.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import zarr
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.datasets.store import EpisodeStore
from gpc.harness.collection import CollectJob, collect
from gpc.models.policy.config import policy_profile
from gpc.models.policy.module import PolicyModule
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.world_models.config import world_model_profile
from gpc.models.world_models.module import WorldModelModule
from gpc.tasks.pusht import LAYOUT

ROOT = Path(__file__).resolve().parents[1]
GPC = [sys.executable, "-m", "gpc.cli.main"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
FAST = ["--no-images", "--max-steps", "40"]
pytestmark = pytest.mark.usefixtures("one_thread")


# ---------------------------------------------------------------------- helpers
def gpc(*args: str, cwd: Path = ROOT, timeout: int = 300) -> subprocess.CompletedProcess:
    return subprocess.run([*GPC, *args], cwd=cwd, env=ENV, capture_output=True, text=True, timeout=timeout)


def spawn(*args: str, cwd: Path = ROOT, group: bool = False) -> subprocess.Popen:
    """``group``: in a process group of its own, as a shell job is (``kill -- -PGID`` reaches its workers too)."""
    return subprocess.Popen([*GPC, *args], cwd=cwd, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=group)


def inline(*args: str) -> tuple[int, str]:
    """`gpc ARGS` in this process through Typer's runner (for refusals at the door: no interpreter start-up)."""
    res = CliRunner().invoke(app, list(args))
    return res.exit_code, res.output


def wait_for(condition: Callable[[], bool], timeout: float = 120.0) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            if condition():
                return
        except Exception:  # the thing watched may be half made
            pass
        time.sleep(0.05)
    raise AssertionError("timed out waiting")


def digest(path: Path) -> dict[str, str]:
    """Every file under ``path`` (or the file) -> its SHA-256: 'every byte that was on disk is still there'."""
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    return {str(p.relative_to(path.parent)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


def one_line(done: subprocess.CompletedProcess | tuple[int, str], code: int, *fragments: str, alone: bool = True) -> str:
    """Exit ``code`` and one line from gpc holding every fragment, no traceback; ``alone``: nothing else on stderr
    (a command stopped while working may have logged its progress before)."""
    rc, err = (done.returncode, done.stderr) if isinstance(done, subprocess.CompletedProcess) else done
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert rc == code, (rc, err[-2000:])
    assert "Traceback" not in err and "Exception ignored" not in err, err[-2000:]
    if not alone:
        lines = [line for line in lines if line.startswith("gpc:")]
    assert len(lines) == 1, err[-2000:]
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    return lines[0]


def finish(proc: subprocess.Popen, sig: int | None = None) -> tuple[int, str]:
    if sig is not None:
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    return proc.returncode, err


def arrays(path: Path) -> dict[str, np.ndarray]:
    store = EpisodeStore.open(path)
    return {k: store.read(k) for k in store.keys} | {"ends": store.episode_ends}


def same_store(a: Path, b: Path) -> None:
    x, y = arrays(a), arrays(b)
    assert x.keys() == y.keys()
    for k in x:
        np.testing.assert_array_equal(x[k], y[k])


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> dict[str, Path]:
    """A tiny keypoint policy and state world model, trained a few steps on real expert episodes."""
    tmp = tmp_path_factory.mktemp("faults")
    collect(CollectJob(task="pusht", out=tmp / "expert.zarr", episodes=4, images=False, max_steps=60))
    run = {"batch_size": 32, "progress": False, "accelerator": "cpu"}
    policy = train(PolicyModule, policy_profile("tiny", "keypoints", LAYOUT).config, [tmp / "expert.zarr"],
                   RunConfig(run_dir=tmp / "policy", max_steps=10, **run))
    wm = train(WorldModelModule, world_model_profile("tiny", 1, LAYOUT).config, [tmp / "expert.zarr"],
               RunConfig(run_dir=tmp / "wm", max_steps=10, **run))
    return {"store": tmp / "expert.zarr", "policy": policy.last, "wm": wm.last}


# ---------------------------------------------------------------------- writes are safe by construction
def test_overwrite_replaces_only_a_store_gpc_wrote(tmp_path):
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "thesis.tex").write_text("years of work")
    afile = tmp_path / "notes.txt"
    afile.write_text("mine")
    before = digest(tmp_path)
    one_line(gpc("collect", "--out", str(victim), "--episodes", "1", "--overwrite", *FAST), 2, str(victim), "not a store gpc wrote")
    one_line(gpc("collect", "--out", str(afile), "--episodes", "1", "--overwrite", *FAST), 2, str(afile), "is a file")
    one_line(gpc("collect", "--out", ".", "--episodes", "1", "--overwrite", *FAST, cwd=tmp_path), 2, "not a store gpc wrote")
    assert digest(tmp_path) == before


def test_a_replacement_killed_midway_leaves_the_old_store_and_finishes_when_rerun(tmp_path):
    out, fresh = tmp_path / "s.zarr", tmp_path / "fresh.zarr"
    assert gpc("collect", "--out", str(out), "--episodes", "2", *FAST).returncode == 0
    old = digest(out)
    proc = spawn("collect", "--out", str(out), "--episodes", "6", "--explore", "--overwrite", "--no-images", "--max-steps", "60")
    wait_for(lambda: EpisodeStore.open(tmp_path / ".s.zarr.new").n_episodes >= 2)
    finish(proc, signal.SIGKILL)
    assert digest(out) == old  # the replacement was staged beside the store
    replace = ["--episodes", "6", "--explore", "--no-images", "--max-steps", "60"]
    assert gpc("collect", "--out", str(out), "--overwrite", *replace).returncode == 0
    assert gpc("collect", "--out", str(fresh), *replace).returncode == 0
    same_store(out, fresh)
    assert not (tmp_path / ".s.zarr.new").exists() and not (tmp_path / ".s.zarr.old").exists()


def test_folders_named_like_gpc_staging_places_are_left_alone(tmp_path):
    """gpc touches ``.NAME.old`` / ``.NAME.new`` only as it left them (its journal, its stores), never a user's."""
    old = tmp_path / ".mine.old"
    old.mkdir()
    (old / "thesis.tex").write_text("years of work")
    out = tmp_path / "mine"
    assert gpc("collect", "--out", str(out), "--episodes", "1", *FAST).returncode == 0
    (tmp_path / ".mine.new").mkdir()
    (tmp_path / ".mine.new" / "data.csv").write_text("mine too")
    before = digest(tmp_path)
    one_line(gpc("collect", "--out", str(out), "--episodes", "1", "--overwrite", *FAST), 2, ".mine.new", "move it away")
    assert digest(tmp_path) == before


def test_a_store_reached_through_a_symbolic_link_has_one_lock_and_keeps_its_link(tmp_path):
    real, alias = tmp_path / "real.zarr", tmp_path / "alias.zarr"
    alias.symlink_to(real.name)
    first = spawn("collect", "--out", str(real), "--episodes", "200", "--explore", "--no-images", "--max-steps", "300")
    wait_for(lambda: EpisodeStore.open(real).n_episodes >= 1)
    first.send_signal(signal.SIGSTOP)  # paused mid-collection, lock held, however fast the machine
    one_line(gpc("collect", "--out", str(alias), "--episodes", "12", "--explore", "--no-images", "--max-steps", "300"),
             2, f"pid {first.pid}", "writing this store")
    finish(first, signal.SIGKILL)
    assert gpc("collect", "--out", str(alias), "--episodes", "2", "--overwrite", *FAST).returncode == 0
    assert alias.is_symlink() and EpisodeStore.open(real).n_episodes == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == [".real.zarr.lock", "alias.zarr", "real.zarr"]


def test_a_refused_resume_changes_no_byte_of_the_store(tmp_path):
    out = tmp_path / "s.zarr"
    assert gpc("collect", "--out", str(out), "--episodes", "1", *FAST).returncode == 0
    root = zarr.open_group(str(out), mode="r+")
    wide = np.repeat(root["data/n_contacts"][:], 2, axis=1)
    del root["data/n_contacts"]
    root["data"].create_array("n_contacts", data=wide)
    before = digest(out)
    one_line(gpc("collect", "--out", str(out), "--episodes", "2", *FAST), 2, str(out), "data/n_contacts rows are (2,)")
    assert digest(out) == before


def test_refusing_a_store_of_another_kind_opens_it_read_only(tmp_path):
    """A Diffusion-Policy-layout store with 10 rows past its last episode end is refused, and not 'repaired'."""
    path = tmp_path / "human.zarr"
    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    root.create_group("data").create_array("state", data=np.ones((50, 5), np.float32), chunks=(20, 5))
    root.create_group("meta").create_array("episode_ends", data=np.array([20, 40], np.int64))
    before = digest(path)
    one_line(gpc("collect", "--out", str(path), "--episodes", "1", *FAST), 2, str(path), "another kind")
    assert digest(path) == before and EpisodeStore.open(path).n_steps == 40 and root["data/state"].shape[0] == 50


# ---------------------------------------------------------------------- one writer at a time
def test_a_second_collection_into_the_same_store_fails_at_once_naming_the_first(tmp_path):
    out, clean = tmp_path / "s.zarr", tmp_path / "clean.zarr"
    job = ["--episodes", "12", "--explore", "--no-images", "--max-steps", "300"]
    first = spawn("collect", "--out", str(out), *job)
    wait_for(lambda: EpisodeStore.open(out).n_episodes >= 1)
    first.send_signal(signal.SIGSTOP)  # paused mid-collection: the second always meets a writer still at work
    one_line(gpc("collect", "--out", str(out), *job), 2, f"pid {first.pid}", "writing this store")
    first.send_signal(signal.SIGCONT)
    assert finish(first)[0] == 0
    assert gpc("collect", "--out", str(clean), *job).returncode == 0
    same_store(out, clean)


def test_a_run_directory_a_killed_run_left_is_never_mixed_with_another(trained, tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "run.json").write_text('{"seed": 1}')
    (run / "checkpoints" / "best.ckpt").write_bytes(b"run 1")
    before = digest(run)
    args = ["train", "policy", "--dataset", str(trained["store"]), "--out", str(run), "--profile", "tiny", "--max-steps", "2",
            "--accelerator", "cpu", "--no-progress"]
    one_line(inline(*args), 2, str(run), "already holds a training run")
    one_line(inline(*args, "--resume"), 2, str(run), "stopped before its first checkpoint")
    assert digest(run) == before


def test_a_second_training_into_the_same_run_directory_fails_naming_the_first(trained, tmp_path):
    args = ["train", "policy", "--dataset", str(trained["store"]), "--out", str(tmp_path / "run"), "--profile", "tiny",
            "--max-steps", "400", "--batch-size", "8", "--accelerator", "cpu", "--no-progress"]
    first = spawn(*args)
    wait_for(lambda: (tmp_path / "run" / "run.json").is_file())
    one_line(gpc(*args), 2, f"pid {first.pid}", "writing this run directory")
    finish(first, signal.SIGKILL)


# ---------------------------------------------------------------------- interrupts are honest
@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> Path:
    clean = tmp_path_factory.mktemp("clean") / "clean.zarr"
    assert gpc("collect", "--out", str(clean), "--episodes", "8", "--no-images", "--max-steps", "120").returncode == 0
    return clean


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
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


def _eval(trained: dict[str, Path], out: Path, *extra: str) -> list[str]:
    return ["eval", str(trained["policy"]), "--planner", "rank", "-K", "3", "--world-model", str(trained["wm"]),
            "--seeds", "100000:100012", "--batch", "2", "--max-steps", "60", "--out", str(out), *extra]


def test_a_stopped_or_killed_eval_resumes_to_the_results_of_an_uninterrupted_one(trained, tmp_path):
    out, clean = tmp_path / "res", tmp_path / "clean"
    assert gpc(*_eval(trained, clean)).returncode == 0
    proc = spawn(*_eval(trained, out))
    wait_for(lambda: len(list((out / ".groups").glob("group-*.json"))) >= 2)
    one_line(finish(proc, signal.SIGTERM), 143, "stopped by SIGTERM", "lockstep groups are kept", "--resume")
    one_line(gpc(*_eval(trained, out)), 2, str(out), "--resume")  # a plain re-run does not clobber them
    proc = spawn(*_eval(trained, out, "--resume"))
    wait_for(lambda: len(list((out / ".groups").glob("group-*.json"))) >= 4)
    finish(proc, signal.SIGKILL)
    assert gpc(*_eval(trained, out, "--resume")).returncode == 0
    rows = lambda d: [{k: r[k] for k in ("seed", "score", "steps", "success", "final_state")}  # noqa: E731
                      for r in json.loads((d / "episodes.json").read_text())]
    assert rows(out) == rows(clean) and not (out / ".groups").exists()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])  # SIGTERM: what Slurm's preemption sends
def test_a_stopped_training_keeps_its_last_step_and_resumes(trained, tmp_path, sig):
    run = tmp_path / "run"
    args = ["train", "policy", "--dataset", str(trained["store"]), "--out", str(run), "--profile", "tiny", "--max-steps", "300",
            "--batch-size", "8", "--accelerator", "cpu", "--no-progress", "--checkpoint-every", "10000"]
    proc = spawn(*args)
    wait_for(lambda: (run / "tensorboard").is_dir() and any((run / "tensorboard").iterdir()), timeout=180)
    time.sleep(1.0)
    name = signal.Signals(sig).name
    line = one_line(finish(proc, sig), 128 + sig, f"stopped by {name}", "training stopped at step", "--resume", alone=False)
    step = int(line.split("training stopped at step ")[1].split(";")[0])
    assert 0 < step < 300 and PolicyModule.load_from_checkpoint(run / "checkpoints" / "last.ckpt") is not None
    import torch

    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == step
    done = gpc(*args, "--resume")
    assert done.returncode == 0 and "step 300;" in done.stdout, done.stderr[-1500:]


# ---------------------------------------------------------------------- validated at the door
def _string_store(path: Path) -> Path:
    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    data = root.create_group("data")
    data.create_array("state", data=np.array([["a"] * 5] * 20))
    data.create_array("keypoint", data=np.zeros((20, 9, 2), np.float32))
    data.create_array("action", data=np.zeros((20, 2), np.float32))
    root.create_group("meta").create_array("episode_ends", data=np.array([20], np.int64))
    return path


def _wide_store(path: Path) -> Path:
    store = EpisodeStore.create(path, {"task": "pusht"})
    rng = np.random.default_rng(0)
    for _ in range(3):
        store.append_episode({"state": rng.uniform(0, 512, (30, 3)).astype(np.float32),
                              "keypoint": rng.uniform(0, 512, (30, 9, 2)).astype(np.float32),
                              "action": rng.uniform(0, 512, (30, 2)).astype(np.float32)})
    return path


@pytest.mark.parametrize("case", ["gpu", "devices 0", "devices abc", "strings", "wide state", "no episodes long enough"])
def test_a_training_refused_at_the_door_leaves_nothing_behind(trained, tmp_path, case):
    store, extra, expect = str(trained["store"]), [], ""
    if case == "gpu":
        extra, expect = ["--accelerator", "gpu"], "--accelerator gpu: no GPU"
    elif case.startswith("devices"):
        extra, expect = ["--devices", case.split()[1]], f"--devices '{case.split()[1]}'"
    elif case == "strings":
        store, expect = str(_string_store(tmp_path / "s.zarr")), "data/state holds <U1 values, not numbers"
    elif case == "wide state":
        store, expect = str(_wide_store(tmp_path / "w.zarr")), "data/state rows are (3,); task pusht stores (5,)"
    else:
        extra, expect = ["--val-ratio", "0.5"], "longer than every episode"
        store = str(tmp_path / "short.zarr")
        assert gpc("collect", "--out", store, "--episodes", "2", "--no-images", "--max-steps", "5").returncode == 0
    run = tmp_path / "run"
    args = ["train", "policy", "--dataset", store, "--out", str(run), "--profile", "tiny", "--max-steps", "2", "--no-progress"]
    one_line(gpc(*args, *([] if "--accelerator" in extra else ["--accelerator", "cpu"]), *extra), 2, expect)
    assert not run.exists()  # a failed start leaves no run directory


def test_a_damaged_chunk_or_metadata_file_is_named(trained, tmp_path):
    copy = tmp_path / "copy.zarr"
    shutil.copytree(trained["store"], copy)
    chunk = next(p for p in sorted((copy / "data" / "state").iterdir()) if p.name[0].isdigit())
    chunk.write_bytes(chunk.read_bytes()[: len(chunk.read_bytes()) // 2])  # truncated
    args = ["train", "policy", "--dataset", str(copy), "--out", str(tmp_path / "run"), "--profile", "tiny", "--max-steps", "2",
            "--accelerator", "cpu", "--no-progress"]
    one_line(gpc(*args), 2, str(copy), "data/state chunk 0", "cannot be decoded")
    assert not (tmp_path / "run").exists()
    (copy / "data" / "action" / ".zarray").write_text('{"chunks": [')
    one_line(gpc("data", "info", str(copy)), 2, str(copy / "data" / "action" / ".zarray"), "unreadable Zarr store")


def test_a_policy_of_another_observation_width_is_refused_by_eval(tmp_path):
    store = _wide_store(tmp_path / "w.zarr")
    policy = train(PolicyModule, policy_profile("tiny", "keypoints", LAYOUT).config, [store],
                   RunConfig(run_dir=tmp_path / "p", max_steps=2, batch_size=8, progress=False, accelerator="cpu"))
    one_line(gpc("eval", str(policy.last), "--seeds", "100000", "--out", str(tmp_path / "res")), 2,
             "trained on state rows of (3,)", "task pusht observes (5,)")
    assert not (tmp_path / "res").exists()


# ---------------------------------------------------------------------- outputs checked before the work
def test_output_paths_are_checked_before_any_work(trained, tmp_path):
    afile = tmp_path / "file"
    afile.write_text("keep")
    t0 = time.time()
    one_line(gpc(*_eval(trained, afile)), 2, str(afile), "is a file")
    one_line(gpc("data", "video", str(trained["store"]), "--out", str(tmp_path)), 2, str(tmp_path), "is a folder")
    assert not list(tmp_path.glob(".*partial*")) and afile.read_text() == "keep"
    assert time.time() - t0 < 60


def _mount(path: Path, options: str) -> bool:
    path.mkdir()
    return subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True).returncode == 0


@pytest.fixture
def small_disk(tmp_path):
    disk = tmp_path / f"disk-{uuid.uuid4().hex[:6]}"
    if not _mount(disk, "size=1m"):
        pytest.skip("cannot mount a tmpfs here (needs root): the full-disk case is not run")
    yield disk
    subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def test_a_full_disk_stops_collection_in_one_line_keeping_whole_episodes(small_disk):
    out = small_disk / "s.zarr"
    done = gpc("collect", "--out", str(out), "--episodes", "40", "--max-steps", "300")  # frames fill 1 MiB
    one_line(done, 2, str(out), "No space left on device", "whole episodes are kept")
    kept = EpisodeStore.open(out)
    assert 0 <= kept.n_episodes < 40 and all(kept.read(k).shape[0] == kept.n_steps for k in kept.keys)


def test_a_read_only_filesystem_is_refused_before_the_work(trained, tmp_path):
    ro = tmp_path / "ro"
    if not _mount(ro, "size=1m"):
        pytest.skip("cannot mount a tmpfs here (needs root): the read-only case is not run")
    try:
        (ro / "inside").mkdir()
        subprocess.run(["mount", "-o", "remount,ro", str(ro)], check=True, capture_output=True)
        one_line(gpc("collect", "--out", str(ro / "s.zarr"), "--episodes", "1", *FAST), 2, str(ro), "read-only file system")
        one_line(gpc(*_eval(trained, ro / "inside" / "res")), 2, str(ro / "inside" / "res"), "read-only file system")
        args = ["train", "policy", "--dataset", str(trained["store"]), "--out", str(ro / "run"), "--profile", "tiny",
                "--max-steps", "2", "--accelerator", "cpu", "--no-progress"]
        one_line(gpc(*args), 2, str(ro), "ead-only file system")
    finally:
        subprocess.run(["umount", "-l", str(ro)], capture_output=True)


# ---------------------------------------------------------------------- comparisons refuse what is not comparable
def test_compare_refuses_runs_of_other_settings_and_names_damaged_files(trained, tmp_path):
    base = ["eval", str(trained["policy"]), "--seeds", "100000:100002", "--batch", "2"]
    assert gpc(*base, "--max-steps", "20", "--out", str(tmp_path / "bc")).returncode == 0
    assert gpc(*base, "--max-steps", "30", "--out", str(tmp_path / "bc30")).returncode == 0
    out = str(tmp_path / "t.md")
    one_line(gpc("compare", str(tmp_path / "bc30"), "--baseline", str(tmp_path / "bc"), "--out", out), 2,
             "--max-steps 30 differs from the baseline's 20")
    (tmp_path / "bc30" / "summary.json").write_text('{"config": ')
    one_line(gpc("compare", str(tmp_path / "bc30"), "--baseline", str(tmp_path / "bc"), "--out", out), 2,
             str(tmp_path / "bc30" / "summary.json"), "not valid JSON")
    assert not Path(out).exists()


def test_results_of_another_kind_are_never_replaced(trained, tmp_path):
    res = tmp_path / "res"
    assert gpc("eval", str(trained["policy"]), "--seeds", "100000:100002", "--max-steps", "5", "--out", str(res)).returncode == 0
    before = digest(res)
    one_line(inline("compare", str(res), "--baseline", str(res), "--out", str(res / "summary.md")), 2,
             "not a comparison gpc wrote")
    one_line(inline("eval", str(trained["policy"]), "--seeds", "100000:100002", "--max-steps", "5", "--sampling-seeds", "0,1",
                    "--out", str(res)), 2, str(res), "already holds results")
    one_line(inline("eval", str(trained["policy"]), "--sampling-seeds", "0,0", "--out", str(tmp_path / "twice")), 2,
             "--sampling-seeds: 0 given twice")
    assert digest(res) == before and not (res / "sampling-seed-0").exists()
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    one_line(inline("data", "video", str(trained["store"]), "--out", str(notes)), 2, str(notes), ".mp4 file")
    one_line(inline("check-sim", "--data", str(trained["store"]), "--out", str(tmp_path)), 2, str(tmp_path), "is a folder")
    assert notes.read_text() == "mine"


@pytest.mark.parametrize("case", ["summary list", "episodes not objects", "score a string", "no ceiling seed",
                                  "zarray empty", "precision 64", "lr nan", "lr inf", "steps", "aggregate"])
def test_damaged_results_and_bad_values_are_one_line(trained, tmp_path, case):
    policy, wm = str(trained["policy"]), str(trained["wm"])
    plan = ["eval", policy, "--planner", "rank", "--world-model", wm, "--seeds", "100000", "--out", str(tmp_path / "r")]
    train_args = ["train", "policy", "--dataset", str(trained["store"]), "--out", str(tmp_path / "run"), "--profile", "tiny",
                  "--max-steps", "2", "--accelerator", "cpu", "--no-progress"]
    if case in ("summary list", "episodes not objects", "score a string", "no ceiling seed"):
        res = tmp_path / "r"
        assert inline("eval", policy, "--seeds", "100000:100002", "--max-steps", "5", "--out", str(res))[0] == 0
        cmd = ["compare", str(res), "--baseline", str(res), "--out", str(tmp_path / "c.md")]
        if case == "summary list":
            (res / "summary.json").write_text("[]")
            one_line(inline("eval", policy, "--seeds", "100000:100002", "--out", str(res)), 2, str(res / "summary.json"),
                     "not a gpc results record")
            return
        if case == "no ceiling seed":
            top = tmp_path / "top"
            assert inline("eval", policy, "--seeds", "100000", "--max-steps", "5", "--out", str(top))[0] == 0
            one_line(inline(*cmd, "--ceiling", str(top)), 2, "--ceiling lacks seed(s) [100001]")
            return
        rows = json.loads((res / "episodes.json").read_text())
        (res / "episodes.json").write_text(json.dumps([1] if case == "episodes not objects" else
                                                      [{**r, "score": "high"} for r in rows]))
        one_line(inline(*cmd), 2, str(res / "episodes.json"))
    elif case == "zarray empty":
        copy = tmp_path / "copy.zarr"
        shutil.copytree(trained["store"], copy)
        (copy / "meta" / "episode_ends" / ".zarray").write_text("{}")
        one_line(inline("data", "info", str(copy)), 2, str(copy / "meta" / "episode_ends" / ".zarray"), "damaged metadata")
    elif case == "precision 64":
        one_line(inline(*train_args, "--precision", "64-true"), 2, "--precision 64-true")
        assert not (tmp_path / "run").exists()
    elif case.startswith("lr"):
        one_line(inline(*plan, "--lr", case.split()[1]), 2, f"--lr {case.split()[1]}")
        assert not (tmp_path / "r").exists()
    elif case == "steps":
        one_line(inline("eval", policy, "--steps", "100000", "--out", str(tmp_path / "r")), 2, "--steps 100000")
    else:
        one_line(inline(*plan, "--reward-aggregate", "foo"), 2, "--reward-aggregate 'foo'")


def test_the_rest_of_the_reported_cases_are_one_line_each(trained, tmp_path):
    """Ctrl-C of eval-expert; --lr names only --lr; data info of a store laid out otherwise; a summary missing a key."""
    proc = spawn("eval-expert", "--seeds", "100000:100100")
    time.sleep(6.0)
    one_line(finish(proc, signal.SIGINT), 130, "stopped by SIGINT", "episodes were scored", alone=False)
    lr = one_line(gpc("eval", str(trained["policy"]), "--planner", "rank", "--world-model", str(trained["wm"]), "--lr", "-5",
                      "--out", str(tmp_path / "lr")), 2, "--lr -5")
    assert "temperature" not in lr and "init_std" not in lr
    info = gpc("data", "info", str(_wide_store(tmp_path / "w.zarr")))
    assert info.returncode == 0 and "no task figures" in info.stdout and "Traceback" not in info.stderr
    assert gpc("eval", str(trained["policy"]), "--seeds", "100000", "--max-steps", "5", "--out", str(tmp_path / "bc")).returncode == 0
    summary = json.loads((tmp_path / "bc" / "summary.json").read_text())
    del summary["decision_latency_s"]
    (tmp_path / "bc" / "summary.json").write_text(json.dumps(summary))
    one_line(gpc("compare", str(tmp_path / "bc"), "--baseline", str(tmp_path / "bc"), "--out", str(tmp_path / "t.md")), 2,
             str(tmp_path / "bc" / "summary.json"), "'decision_latency_s'")
