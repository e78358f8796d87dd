"""gpc installs beside Hugging Face's `datasets` (a LeRobot dependency) in one fresh environment, and works there.

A new virtual environment gets `datasets` first, then torch and gpc itself (a regular, non-editable
install of this checkout: what a user's `pip install` builds). Both packages import as themselves,
`gpc --help` answers, and a tiny collect + train + eval runs from a directory outside the checkout.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from test_packaging import copy_project

ROOT = Path(__file__).resolve().parents[1]
TORCH_SPEC = os.environ.get("TORCH_SPEC", "torch==2.13.0")  # the Makefile's: the small CPU build


def run(args: list[str], cwd: Path, timeout: int = 600) -> str:
    """pip installs with --no-compile (byte-compiling every installed file was two thirds of the install time); so
    that each run does not compile its imports again, this throwaway environment may write bytecode."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    done = subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env={**env, "PIP_DISABLE_PIP_VERSION_CHECK": "1", "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, f"{' '.join(args[:4])}: {done.stdout[-1500:]}{done.stderr[-1500:]}"
    return done.stdout


@pytest.mark.slow
@pytest.mark.extended  # make test-extended (3 min of pip); make test checks the package list in test_packaging
def test_gpc_and_hugging_face_datasets_share_one_environment(tmp_path):
    venv = tmp_path / "venv"
    run([sys.executable, "-m", "venv", str(venv)], tmp_path)
    python, gpc = venv / "bin" / "python", venv / "bin" / "gpc"
    run([str(python), "-m", "pip", "install", "-q", "--no-compile", "datasets"], tmp_path)
    run([str(python), "-m", "pip", "install", "-q", "--no-compile", TORCH_SPEC], tmp_path)
    source = copy_project(tmp_path / "source")
    run([str(python), "-m", "pip", "install", "-q", "--no-compile", str(source)], tmp_path)
    probe = ("import datasets, gpc.datasets, gpc.models.policy.module, gpc.harness.evaluation, gpc.cli.main; "
             "assert 'site-packages/datasets/' in datasets.__file__, datasets.__file__; "
             "assert 'site-packages/gpc/datasets/' in gpc.datasets.__file__, gpc.datasets.__file__; "
             "print(datasets.Dataset.from_dict({'a': [1, 2]}).num_rows)")
    assert run([str(python), "-c", probe], tmp_path).strip() == "2"
    for name in ("models", "tasks", "gpc_cli"):  # no top-level import name of ours is left behind
        assert "ModuleNotFoundError" in subprocess.run([str(python), "-c", f"import {name}"], cwd=tmp_path,
                                                       capture_output=True, text=True).stderr
    assert "collect" in run([str(gpc), "--help"], tmp_path)
    run([str(gpc), "collect", "--out", "expert.zarr", "--episodes", "3", "--no-images", "--max-steps", "40"], tmp_path)
    run([str(gpc), "train", "policy", "--dataset", "expert.zarr", "--profile", "tiny", "--max-steps", "2", "--batch-size", "8",
         "--accelerator", "cpu", "--no-progress", "--out", "policy"], tmp_path)
    out = run([str(gpc), "eval", "policy/checkpoints/last.ckpt", "--seeds", "100000:100002", "--max-steps", "8",
               "--batch", "2", "--out", "bc"], tmp_path)
    assert "mean score" in out and (tmp_path / "bc" / "summary.json").is_file()
