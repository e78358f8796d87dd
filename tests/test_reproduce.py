"""`make reproduce-pusht PROFILE=smoke` end to end, in a scratch directory, then resumed."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


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
    again = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0
    assert '"written": 0' in again.stdout  # both collections resumed with nothing left to do
    assert "Trainer.fit" not in again.stdout + again.stderr  # the trained policy was kept
