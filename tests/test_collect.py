"""Collection end to end: real simulator, real expert, real Zarr on disk."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.datasets.store import EpisodeStore

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[1]
FAST = ["--no-images", "--max-steps", "40"]


def _collect(out: Path, *extra: str):
    return runner.invoke(app, ["collect", "--out", str(out), *FAST, *extra])


def _arrays(path: Path) -> dict[str, np.ndarray]:
    store = EpisodeStore.open(path)
    return {k: store.read(k) for k in store.keys} | {"ends": store.episode_ends, "seeds": store.episode_seeds()}


def test_store_is_identical_for_any_worker_count(tmp_path):
    a, b = tmp_path / "a.zarr", tmp_path / "b.zarr"
    assert _collect(a, "--episodes", "3", "--seed", "5").exit_code == 0
    res = _collect(b, "--episodes", "3", "--seed", "5", "--workers", "2")
    assert res.exit_code == 0, res.output
    x, y = _arrays(a), _arrays(b)
    assert x.keys() == y.keys()
    for k in x:
        np.testing.assert_array_equal(x[k], y[k])
    np.testing.assert_array_equal(x["seeds"], [5, 6, 7])
    attrs = EpisodeStore.open(a).attrs
    assert attrs["task"] == "pusht" and attrs["collector"]["kind"] == "expert" and "gpc_version" in attrs


def test_rerun_resumes_without_duplicates(tmp_path):
    out = tmp_path / "s.zarr"
    assert _collect(out, "--episodes", "2").exit_code == 0
    res = _collect(out, "--episodes", "4")
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output[res.output.index("{"):])
    assert summary["written"] == 2 and summary["skipped"] == 2
    np.testing.assert_array_equal(EpisodeStore.open(out).episode_seeds(), [0, 1, 2, 3])
    rerun = _collect(out, "--episodes", "4").output
    again = json.loads(rerun[rerun.index("{"):], parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert again["written"] == 0 and again["mean_score"] is None  # strict JSON: no NaN when nothing was written


def test_refuses_a_store_of_another_kind_unless_overwrite(tmp_path):
    out = tmp_path / "s.zarr"
    assert _collect(out, "--episodes", "1").exit_code == 0
    before = _arrays(out)
    res = _collect(out, "--episodes", "1", "--explore")
    assert res.exit_code == 2 and "another kind" in res.output and "--overwrite" in res.output
    after = _arrays(out)
    for k in before:
        np.testing.assert_array_equal(before[k], after[k])
    assert _collect(out, "--episodes", "1", "--explore", "--overwrite").exit_code == 0
    assert EpisodeStore.open(out).attrs["collector"]["kind"] == "explore"


def test_sigkilled_collection_resumes_to_the_same_store(tmp_path):
    killed, clean = tmp_path / "killed.zarr", tmp_path / "clean.zarr"
    cmd = [sys.executable, "-m", "gpc.cli.main", "collect", "--out", str(killed), "--episodes", "6", *FAST]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 60
    while time.time() < deadline:  # kill once a couple of episodes have landed, mid-collection
        try:
            if EpisodeStore.open(killed).n_episodes >= 2:
                break
        except Exception:
            pass
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    partial = EpisodeStore.open(killed)
    assert 1 <= partial.n_episodes < 6
    assert _collect(killed, "--episodes", "6").exit_code == 0
    assert _collect(clean, "--episodes", "6").exit_code == 0
    x, y = _arrays(killed), _arrays(clean)
    for k in x:
        np.testing.assert_array_equal(x[k], y[k])


def test_exploration_store_is_contact_rich(tmp_path):
    out = tmp_path / "e.zarr"
    res = runner.invoke(app, ["collect", "--explore", "--out", str(out), "--episodes", "3", "--no-images",
                              "--max-steps", "120"])
    assert res.exit_code == 0, res.output
    info = json.loads(runner.invoke(app, ["data", "info", str(out), "--json"]).output)
    assert info["contact_fraction"] >= 0.4
    assert info["keys"]["state"]["shape"] == [360, 5]
