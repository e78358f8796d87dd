"""What the fault tests share: running `gpc` in its own process, waiting on it, and checking its one-line refusals.

Every fault case (tests/test_faults_*.py) runs the `gpc` command and checks three things: the exit code (2 for bad
input or an OS error, 130 / 143 for SIGINT / SIGTERM), that stderr is one line naming the file or option and the
problem (no traceback), and that every byte on disk before the command is still there. Cases that stop, kill or race
a command run it in its own process; refusals at the door run in this one through Typer's runner (`inline`), which
sees the same exit code and line without a process start that imports Lightning (about 6 s each on 2 cores).
docs/reliability.md lists the promises these cases hold.
"""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import zarr
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.datasets.store import EpisodeStore
from gpc.harness.collection import CollectJob, collect
from gpc.models.policy.config import policy_profile
from gpc.models.policy.module import PolicyModule
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.profiles import world_model_profile
from gpc.tasks.pusht import LAYOUT

ROOT = Path(__file__).resolve().parents[1]
GPC = [sys.executable, "-m", "gpc.cli.main"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
FAST = ["--no-images", "--max-steps", "40"]


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


def wait_deferring(proc: subprocess.Popen, timeout: float = 120.0) -> None:
    """Until ``proc`` catches SIGTERM (Linux's /proc), i.e. gpc's ``deferred_signals`` is in place: a signal sent
    earlier would land in the interpreter's start-up instead of the command (a busy machine starts it slowly)."""
    def catching() -> bool:
        caught = next(line for line in Path(f"/proc/{proc.pid}/status").read_text().splitlines() if line.startswith("SigCgt:"))
        return bool(int(caught.split()[1], 16) >> (signal.SIGTERM - 1) & 1)

    wait_for(catching, timeout)


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



def train_tiny(tmp: Path) -> dict[str, Path]:
    """A tiny keypoint policy and state world model, trained a few steps on real expert episodes."""
    collect(CollectJob(task="pusht", out=tmp / "expert.zarr", episodes=4, images=False, max_steps=60))
    run = {"batch_size": 32, "progress": False, "accelerator": "cpu"}
    policy = train(PolicyModule, policy_profile("tiny", "keypoints", LAYOUT).config, [tmp / "expert.zarr"],
                   RunConfig(run_dir=tmp / "policy", max_steps=10, **run))
    wm = train(WorldModelModule, world_model_profile("tiny", 1, LAYOUT).config, [tmp / "expert.zarr"],
               RunConfig(run_dir=tmp / "wm", max_steps=10, **run))
    return {"store": tmp / "expert.zarr", "policy": policy.last, "wm": wm.last}


def eval_args(models: dict[str, Path], out: Path, *extra: str) -> list[str]:
    return ["eval", str(models["policy"]), "--planner", "rank", "-K", "3", "--world-model", str(models["wm"]),
            "--seeds", "100000:100012", "--batch", "2", "--max-steps", "60", "--out", str(out), *extra]


def wide_store(path: Path) -> Path:
    """A store whose state rows are 3 wide where Push-T stores 5: training works, evaluation must refuse."""
    store = EpisodeStore.create(path, {"task": "pusht"})
    rng = np.random.default_rng(0)
    for _ in range(3):
        store.append_episode({"state": rng.uniform(0, 512, (30, 3)).astype(np.float32),
                              "keypoint": rng.uniform(0, 512, (30, 9, 2)).astype(np.float32),
                              "action": rng.uniform(0, 512, (30, 2)).astype(np.float32)})
    return path


def string_store(path: Path) -> Path:
    """A Diffusion-Policy-layout store whose ``state`` holds strings: no reader may take it for numbers."""
    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    data = root.create_group("data")
    data.create_array("state", data=np.array([["a"] * 5] * 20))
    data.create_array("keypoint", data=np.ones((20, 9, 2), np.float32))
    data.create_array("action", data=np.ones((20, 2), np.float32))
    root.create_group("meta").create_array("episode_ends", data=np.array([20], np.int64))
    return path
