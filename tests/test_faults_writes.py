"""Faults around writing: a store is replaced only when gpc wrote it, staged beside it, and written by one process at a time."""

from __future__ import annotations

import signal

import numpy as np
import pytest
import zarr
from faults import FAST, digest, finish, gpc, inline, one_line, same_store, spawn, wait_for

from gpc.datasets.store import EpisodeStore

pytestmark = pytest.mark.usefixtures("one_thread")


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
    job = ["--episodes", "3", "--explore", "--no-images", "--max-steps", "150"]
    first = spawn("collect", "--out", str(out), *job)
    wait_for(lambda: EpisodeStore.open(out).n_episodes >= 1)
    first.send_signal(signal.SIGSTOP)  # paused mid-collection: the second always meets a writer still at work
    one_line(gpc("collect", "--out", str(out), *job), 2, f"pid {first.pid}", "writing this store")
    first.send_signal(signal.SIGCONT)
    assert finish(first)[0] == 0
    assert gpc("collect", "--out", str(clean), *job).returncode == 0
    same_store(out, clean)


def test_a_run_directory_a_killed_run_left_is_never_mixed_with_another(tiny_pusht, tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "run.json").write_text('{"seed": 1}')
    (run / "checkpoints" / "best.ckpt").write_bytes(b"run 1")
    before = digest(run)
    args = ["train", "policy", "--dataset", str(tiny_pusht["store"]), "--out", str(run), "--profile", "tiny", "--max-steps", "2",
            "--accelerator", "cpu", "--no-progress"]
    one_line(inline(*args), 2, str(run), "already holds a training run")
    one_line(inline(*args, "--resume"), 2, str(run), "stopped before its first checkpoint")
    assert digest(run) == before


def test_a_second_training_into_the_same_run_directory_fails_naming_the_first(tiny_pusht, tmp_path):
    args = ["train", "policy", "--dataset", str(tiny_pusht["store"]), "--out", str(tmp_path / "run"), "--profile", "tiny",
            "--max-steps", "400", "--batch-size", "8", "--accelerator", "cpu", "--no-progress"]
    first = spawn(*args)
    wait_for(lambda: (tmp_path / "run" / "run.json").is_file())
    one_line(inline(*args), 2, f"pid {first.pid}", "writing this run directory")
    finish(first, signal.SIGKILL)
