"""The CLI through Typer's runner: real stores on disk, one-line errors with exit code 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.datasets.store import EpisodeStore

runner = CliRunner()


def gpc(*args: str):
    """Run `gpc ARGS` through Typer's runner, with the console script's one-line error handling."""
    return runner.invoke(app, list(args))


def _store(path: Path, n_eps: int = 3, nan: bool = False) -> Path:
    store = EpisodeStore.create(path, {"task": "pusht"})
    for i in range(n_eps):
        state = np.tile(np.array([100.0, 100.0, 256.0, 256.0, np.pi / 4], np.float32), (5 + i, 1))
        if nan and i == n_eps - 1:
            state[:] = 0
        store.append_episode({"state": state, "action": np.full((5 + i, 2), 100, np.float32),
                              "n_contacts": np.zeros((5 + i, 1), np.float32)}, seed=i)
    if nan:
        import zarr

        zarr.open_group(str(path), mode="r+")["data/state"][3, 1] = np.nan
    return path


def test_help_lists_commands_and_options():
    out = gpc("--help").output
    for cmd in ("collect", "data", "check-sim", "eval-expert"):
        assert cmd in out
    col = gpc("collect", "--help").output
    for opt in ("--explore", "--episodes", "--seed", "--workers", "--out", "--overwrite"):
        assert opt in col


def test_the_command_and_collection_start_without_lightning():
    """Lightning takes 2-5 s to import and torch 2-3 s: `gpc --help`, `gpc compare` and `gpc data` skip both, every
    collection process (and its workers) skips Lightning."""
    import subprocess
    import sys

    loaded = "print(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'lightning'}))"
    code = ("import sys, gpc.cli.main, gpc.harness.comparison, gpc.harness.stores, gpc.tasks.pusht.record; "
            f"{loaded}; import gpc.harness.collection; {loaded}")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.split("\n")[:2] == ["[]", "['torch']"], out.stdout + out.stderr


def test_data_info_table_and_json(tmp_path):
    path = _store(tmp_path / "s.zarr")
    res = gpc("data", "info", str(path), "--json")
    assert res.exit_code == 0, res.output
    info = json.loads(res.output)
    assert info["episodes"] == 3 and info["steps"] == 18
    assert info["keys"]["state"]["shape"] == [18, 5]
    assert info["score"]["mean"] == pytest.approx(1.0) and info["score"]["success_rate"] == 1.0  # recomputed: block on the goal
    assert info["contact_fraction"] == 0.0
    table = gpc("data", "info", str(path))
    assert table.exit_code == 0 and "3 episodes" in table.output


def test_data_info_on_the_human_data(human_data):
    res = gpc("data", "info", str(human_data), "--json")
    assert res.exit_code == 0, res.output
    info = json.loads(res.output)
    assert info["episodes"] == 186 and info["keys"]["img"]["shape"] == [22972, 96, 96, 3]
    assert 0.8 < info["score"]["mean"] < 0.95  # human demonstrations average ~0.89


def test_data_video_writes_an_mp4(tmp_path):
    path = _store(tmp_path / "s.zarr")
    out = tmp_path / "ep.mp4"
    res = gpc("data", "video", str(path), "--episode", "1", "--out", str(out))
    assert res.exit_code == 0, res.output
    import cv2

    cap = cv2.VideoCapture(str(out))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 6


@pytest.mark.parametrize(
    "case, expect",
    [
        ("missing", "no such file"),
        ("not_store", "not a Zarr episode store"),
        ("nan", "NaN"),
        ("episode_range", "out of range"),
    ],
)
def test_bad_store_input_is_one_line_exit_2(tmp_path, case, expect):
    path = tmp_path / "s.zarr"
    args = ["data", "info", str(path)]
    if case == "not_store":
        path.mkdir()
        (path / "notes.txt").write_text("x")
    elif case == "nan":
        _store(path, nan=True)
    elif case == "episode_range":
        _store(path)
        args = ["data", "video", str(path), "--episode", "9"]
    before = sorted(p.name for p in tmp_path.rglob("*"))
    res = gpc(*args)
    assert res.exit_code == 2
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and expect in lines[0] and "Traceback" not in res.output
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing on disk altered


@pytest.mark.parametrize(
    "args, expect",
    [
        (["--episodes", "0"], "--episodes"),
        (["--workers", "-1"], "--workers"),
        (["--task", "cartpole"], "unknown task 'cartpole'"),
        (["--goal", "moving"], "--goal 'moving'"),
    ],
)
def test_bad_collect_options_are_one_line_exit_2(tmp_path, args, expect):
    res = gpc("collect", "--out", str(tmp_path / "x.zarr"), *args)
    assert res.exit_code == 2, res.output
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and expect in lines[0]
    assert not (tmp_path / "x.zarr").exists()


def test_store_missing_keys_for_check_sim(tmp_path):
    path = EpisodeStore.create(tmp_path / "s.zarr", {"task": "pusht"})
    path.append_episode({"state": np.zeros((3, 5), np.float32)})
    res = gpc("check-sim", "--data", str(tmp_path / "s.zarr"))
    assert res.exit_code == 2 and "missing key data/action" in res.output
