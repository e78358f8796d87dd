"""A failed start leaves nothing behind: options out of range, seeds past 32 bits, a failure after the output was
made, refusals naming the lock's holder, foreign policies named plainly; every entry on disk as it was before."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from faults import ENV, eval_args, inline, one_line

from gpc.tasks.base import MAX_SEED

pytestmark = pytest.mark.usefixtures("one_thread")

FOREIGN = Path(__file__).parent / "fixtures" / "foreign"
HUGE = "99999999999999999999999"


def entries(root: Path) -> dict[str, str]:
    """Every entry under ``root`` (hidden ones, folders and lock files included) -> its bytes' SHA-256 or "folder"."""
    return {str(p.relative_to(root)): "folder" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*"))}


def _mine(tmp: Path) -> Path:
    """A user's folder with a file, beside which the commands write."""
    (tmp / "mine").mkdir()
    (tmp / "mine" / "notes.md").write_text("keep")
    return tmp


# ---------------------------------------------------------------------- numbers out of range, named at the door
@pytest.mark.parametrize("case", ["episodes", "seed", "seed plus episodes", "workers", "seeds range", "seeds huge", "threads",
                                  "train seed", "sampling list"])
def test_an_option_out_of_range_is_named_and_leaves_nothing(tiny_pusht, tmp_path, case):
    tmp = _mine(tmp_path)
    out = str(tmp / "new" / "out")
    collect = ["collect", "--out", out, "--no-images", "--max-steps", "5"]
    args, named = {
        "episodes": (collect + ["-n", HUGE], "'--episodes'"),
        "seed": (collect + ["--seed", str(MAX_SEED + 1)], "'--seed'"),
        "seed plus episodes": (collect + ["--seed", str(MAX_SEED), "-n", "2"], f"--seed {MAX_SEED} with --episodes 2"),
        "workers": (collect + ["-j", HUGE], "'--workers'"),
        "seeds range": (eval_args(tiny_pusht, Path(out)) + ["--seeds", f"{MAX_SEED}:{MAX_SEED + 2}"],
                        f"--seeds {MAX_SEED}:{MAX_SEED + 2}: seed {MAX_SEED + 1} is past {MAX_SEED}"),
        "seeds huge": (eval_args(tiny_pusht, Path(out)) + ["--seeds", f"1:{HUGE}"], f"--seeds 1:{HUGE}"),
        "threads": (["record", str(tiny_pusht["policy"]), "--out", out, "--threads", HUGE], "'--threads'"),
        "train seed": (["train", "policy", "-d", str(tiny_pusht["store"]), "--out", out, "--seed", str(MAX_SEED + 1)], "'--seed'"),
        "sampling list": (["eval-expert", "--seeds", f"1,{MAX_SEED + 1}", "--out", out], f"seed {MAX_SEED + 1} is past"),
    }[case]
    before = entries(tmp)
    one_line(inline(*args), 2, named)
    assert entries(tmp) == before  # no store, no results folder, no .groups, no lock file, no parent folder


# ---------------------------------------------------------------------- a failure after the output was made
def _boom(*args, **kwargs):
    raise ValueError("boom: the first episode failed")


def test_a_collection_failing_before_its_first_episode_leaves_nothing(tmp_path, monkeypatch):
    """The store (and the folders above it, and its lock file) this invocation made are removed; the user's are not."""
    import gpc.harness.collection as collection

    tmp = _mine(tmp_path)
    before = entries(tmp)
    monkeypatch.setattr(collection, "_run_one", _boom)
    for out in (tmp / "a" / "b" / "s.zarr", tmp / "mine" / "s.zarr"):
        one_line(inline("collect", "--out", str(out), "-n", "2", "--no-images", "--max-steps", "5"), 2, "boom", alone=False)
        assert entries(tmp) == before
    monkeypatch.undo()  # the corrected command runs at once
    assert inline("collect", "--out", str(tmp / "a" / "s.zarr"), "-n", "1", "--no-images", "--max-steps", "5")[0] == 0


def test_an_eval_failing_in_its_first_group_leaves_nothing(tiny_pusht, tmp_path, monkeypatch):
    """No results folder, .groups or lock file stays; a folder of the user's keeps exactly what it held."""
    import gpc.harness.evaluation as evaluation

    tmp = _mine(tmp_path)
    before = entries(tmp)
    monkeypatch.setattr(evaluation, "run_group", _boom)
    for out in (tmp / "new" / "res", tmp / "mine"):
        one_line(inline(*eval_args(tiny_pusht, out)), 2, "boom", alone=False)
        assert entries(tmp) == before
    one_line(inline(*eval_args(tiny_pusht, tmp / "res"), "--sampling-seeds", "0,1"), 2, "boom", alone=False)
    assert entries(tmp) == before


# ---------------------------------------------------------------------- unclear messages made plain
def test_n_obs_steps_0_in_a_lerobot_config_is_named_with_its_file(tmp_path):
    policy = tmp_path / "policy"
    shutil.copytree(FOREIGN / "lerobot_keypoints", policy)
    config = json.loads((policy / "config.json").read_text())
    (policy / "config.json").write_text(json.dumps({**config, "n_obs_steps": 0}))
    before = entries(tmp_path)
    one_line(inline("inspect", str(policy)), 2, str(policy / "config.json"), "n_obs_steps 0")
    assert entries(tmp_path) == before


def test_a_lerobot_policy_given_to_export_is_named_as_such(tmp_path):
    before = entries(tmp_path)
    one_line(inline("export", str(FOREIGN / "lerobot_keypoints"), "--out", str(tmp_path / "x.ckpt")), 2,
             str(FOREIGN / "lerobot_keypoints"), "is a LeRobot policy, not a gpc checkpoint")
    assert entries(tmp_path) == before


def test_an_unknown_planner_lists_every_accepted_value(tiny_pusht, tmp_path):
    line = one_line(inline(*eval_args(tiny_pusht, tmp_path / "res"), "--planner", "foo"), 2, "--planner 'foo'")
    names = ("bc,", "rank,", "opt,", "rank-opt,", "gt-sim,", "cem,", "mppi,", "grad,", "vgps,", "dreamer,", "ladi")
    assert all(f" {name}" in line for name in names)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("what", ["results folder", "store"])
def test_a_second_writer_is_refused_naming_the_holders_pid(tiny_pusht, tmp_path, what):
    """Another process holds the folder's lock (a run under way: its records half made); the refusal names its pid,
    not what the half-made records say ("already holds results")."""
    out = tmp_path / ("res" if what == "results folder" else "s.zarr")
    if what == "results folder":
        (out / ".groups").mkdir(parents=True)
        (out / ".groups" / "run.json").write_text(json.dumps({"run": {"another": "run"}}))
        args = eval_args(tiny_pusht, out)
    else:
        assert inline("collect", "--out", str(out), "-n", "1", "--no-images", "--max-steps", "5")[0] == 0
        args = ["collect", "--out", str(out), "-n", "1", "--no-images", "--max-steps", "6"]  # another kind of data
    hold = ("import sys, time\nfrom gpc.datasets.locks import exclusive\n"
            f"with exclusive({str(out)!r}, 'x'):\n    print('held', flush=True)\n    time.sleep(120)\n")
    holder = subprocess.Popen([sys.executable, "-c", hold], env=ENV, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        before = entries(tmp_path)
        one_line(inline(*args), 2, str(out), f"another gpc process (pid {holder.pid}) is writing this {what}")
        assert entries(tmp_path) == before
    finally:
        holder.kill()
        holder.wait()


def test_a_lock_file_left_by_a_finished_writer_is_taken_over(tmp_path):
    """Removing a lock file on a failed start is safe: a locker that opened the removed file locks anew."""
    from gpc.datasets.locks import exclusive, lock_path

    target = tmp_path / "t"
    with pytest.raises(ValueError, match="fails"), exclusive(target, "store"):
        assert lock_path(target).is_file()
        raise ValueError("fails")
    assert not lock_path(target).exists() and not os.listdir(tmp_path)
    with exclusive(target, "store"):
        target.mkdir()
    assert lock_path(target).read_text().strip() == str(os.getpid())  # kept beside a target that was made


def test_a_video_failing_midway_leaves_no_folder_it_made(tiny_pusht, tmp_path, monkeypatch):
    import gpc.harness.video as video

    tmp = _mine(tmp_path)
    before = entries(tmp)
    monkeypatch.setattr(video.interrupts, "check", _boom)  # fails after the first frame is written
    one_line(inline("data", "video", str(tiny_pusht["store"]), "--out", str(tmp / "a" / "b" / "v.mp4")), 2, "boom")
    assert entries(tmp) == before


@pytest.mark.parametrize("command", ["train", "data export"])
def test_a_training_or_conversion_failing_after_it_began_leaves_nothing(tiny_pusht, tmp_path, monkeypatch, command):
    """The run directory (run.json written) or the dataset being staged, their lock file and parent folders go."""
    import gpc.harness.lerobot_data as lerobot_data
    import gpc.models.training.trainer as trainer

    tmp = _mine(tmp_path)
    before = entries(tmp)
    out = str(tmp / "a" / "b" / "out")
    if command == "train":
        monkeypatch.setattr(trainer, "fit_module", _boom)
        args = ["train", "policy", "-d", str(tiny_pusht["store"]), "--out", out, "--profile", "tiny", "--accelerator", "cpu",
                "--no-progress", "--max-steps", "2"]
    else:
        monkeypatch.setattr(lerobot_data, "write_lerobot", _boom)
        args = ["data", "export", str(tiny_pusht["store"]), "--out", out]
    one_line(inline(*args), 2, "boom", alone=False)
    assert entries(tmp) == before
