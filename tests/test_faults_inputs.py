"""Bad input and hostile disks: refused at the door in one line, before any work, leaving nothing behind."""

from __future__ import annotations

import shutil
import subprocess
import time
import uuid
from pathlib import Path

import pytest
from faults import FAST, eval_args, gpc, inline, one_line, string_store, wide_store

from gpc.datasets.store import EpisodeStore
from gpc.models.policy.config import policy_profile
from gpc.models.policy.module import PolicyModule
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.tasks.pusht import LAYOUT

pytestmark = pytest.mark.usefixtures("one_thread")


# ---------------------------------------------------------------------- validated at the door
@pytest.mark.parametrize("case", ["gpu", "devices 0", "devices abc", "strings", "wide state", "no episodes long enough"])
def test_a_training_refused_at_the_door_leaves_nothing_behind(tiny_pusht, tmp_path, case):
    store, extra, expect = str(tiny_pusht["store"]), [], ""
    if case == "gpu":
        extra, expect = ["--accelerator", "gpu"], "--accelerator gpu: no GPU"
    elif case.startswith("devices"):
        extra, expect = ["--devices", case.split()[1]], f"--devices '{case.split()[1]}'"
    elif case == "strings":
        store, expect = str(string_store(tmp_path / "s.zarr")), "data/state holds <U1 values, not numbers"
    elif case == "wide state":
        store, expect = str(wide_store(tmp_path / "w.zarr")), "data/state rows are (3,); task pusht stores (5,)"
    else:
        extra, expect = ["--val-ratio", "0.5"], "longer than every episode"
        store = str(tmp_path / "short.zarr")
        assert inline("collect", "--out", store, "--episodes", "2", "--no-images", "--max-steps", "5")[0] == 0
    run = tmp_path / "run"
    args = ["train", "policy", "--dataset", store, "--out", str(run), "--profile", "tiny", "--max-steps", "2", "--no-progress"]
    one_line(inline(*args, *([] if "--accelerator" in extra else ["--accelerator", "cpu"]), *extra), 2, expect)
    assert not run.exists()  # a failed start leaves no run directory


def test_a_damaged_chunk_or_metadata_file_is_named(tiny_pusht, tmp_path):
    copy = tmp_path / "copy.zarr"
    shutil.copytree(tiny_pusht["store"], copy)
    chunk = next(p for p in sorted((copy / "data" / "state").iterdir()) if p.name[0].isdigit())
    chunk.write_bytes(chunk.read_bytes()[: len(chunk.read_bytes()) // 2])  # truncated
    args = ["train", "policy", "--dataset", str(copy), "--out", str(tmp_path / "run"), "--profile", "tiny", "--max-steps", "2",
            "--accelerator", "cpu", "--no-progress"]
    one_line(inline(*args), 2, str(copy), "data/state chunk 0", "is damaged")
    assert not (tmp_path / "run").exists()
    (copy / "data" / "action" / ".zarray").write_text('{"chunks": [')
    one_line(gpc("data", "info", str(copy)), 2, str(copy / "data" / "action" / ".zarray"), "unreadable Zarr store")


def test_a_policy_of_another_observation_width_is_refused_by_eval(tmp_path):
    store = wide_store(tmp_path / "w.zarr")
    policy = train(PolicyModule, policy_profile("tiny", "keypoints", LAYOUT).config, [store],
                   RunConfig(run_dir=tmp_path / "p", max_steps=2, batch_size=8, progress=False, accelerator="cpu"))
    one_line(inline("eval", str(policy.last), "--seeds", "100000", "--out", str(tmp_path / "res")), 2,
             "trained on state rows of (3,)", "task pusht observes (5,)")
    assert not (tmp_path / "res").exists()


# ---------------------------------------------------------------------- outputs checked before the work
def test_output_paths_are_checked_before_any_work(tiny_pusht, tmp_path):
    afile = tmp_path / "file"
    afile.write_text("keep")
    t0 = time.time()
    one_line(inline(*eval_args(tiny_pusht, afile)), 2, str(afile), "is a file")
    one_line(gpc("data", "video", str(tiny_pusht["store"]), "--out", str(tmp_path)), 2, str(tmp_path), "is a folder")
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


def test_a_read_only_filesystem_is_refused_before_the_work(tiny_pusht, tmp_path):
    ro = tmp_path / "ro"
    if not _mount(ro, "size=1m"):
        pytest.skip("cannot mount a tmpfs here (needs root): the read-only case is not run")
    try:
        (ro / "inside").mkdir()
        subprocess.run(["mount", "-o", "remount,ro", str(ro)], check=True, capture_output=True)
        one_line(gpc("collect", "--out", str(ro / "s.zarr"), "--episodes", "1", *FAST), 2, str(ro), "read-only file system")
        one_line(inline(*eval_args(tiny_pusht, ro / "inside" / "res")), 2, str(ro / "inside" / "res"), "read-only file system")
        args = ["train", "policy", "--dataset", str(tiny_pusht["store"]), "--out", str(ro / "run"), "--profile", "tiny",
                "--max-steps", "2", "--accelerator", "cpu", "--no-progress"]
        one_line(inline(*args), 2, str(ro), "ead-only file system")
    finally:
        subprocess.run(["umount", "-l", str(ro)], capture_output=True)
