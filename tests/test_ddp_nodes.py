"""Training across nodes: two CPU processes as two DDP nodes over loopback (gloo) train what one process trains.

Each "node" is a `python -m gpc.cli.train` process with the rendezvous in its environment, as torchrun or SLURM
would set it (docs/scale-out.md). The component is V-GPS's Q-function: its loss has no random draws, so two
nodes of batch 8 must take the steps one process of batch 16 takes (DDP averages the two halves' gradients; the
distributed sampler gives the two ranks the halves of one shuffled batch), to float rounding.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from gpc.harness.collection import CollectJob, collect

pytestmark = [pytest.mark.slow, pytest.mark.extended]  # make test-extended; make test runs two processes on one node (test_policy)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _train(tmp: Path, out: str, nodes: int, batch: int, env: dict[str, str] | None = None) -> subprocess.Popen:
    args = [sys.executable, "-m", "gpc.cli.train", "value", "--dataset", str(tmp / "expert.zarr"), "--profile", "tiny",
            "--max-steps", "6", "--accelerator", "cpu", "--devices", "1", "--strategy", "ddp", "--num-nodes", str(nodes),
            "--batch-size", str(batch), "--val-ratio", "0", "--no-progress", "--out", str(tmp / out)]
    return subprocess.Popen(args, env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})}, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _weights(path: Path) -> dict[str, torch.Tensor]:
    state = torch.load(path, map_location="cpu", weights_only=False)["state_dict"]
    return {k: v.float() for k, v in state.items() if v.dtype.is_floating_point}


def test_two_nodes_over_loopback_train_the_checkpoint_one_process_trains(tmp_path):
    collect(CollectJob(task="pusht", out=tmp_path / "expert.zarr", episodes=4, images=False, max_steps=60))
    port = str(_free_port())
    nodes = [_train(tmp_path, "two", 2, 8, {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": port, "NODE_RANK": str(r),
                                            "LOCAL_RANK": "0", "RANK": str(r), "WORLD_SIZE": "2"}) for r in (0, 1)]
    one, half = _train(tmp_path, "one", 1, 16), _train(tmp_path, "half", 1, 8)  # the same global batch; and half of it
    for proc in (*nodes, one, half):
        output = proc.communicate(timeout=300)[0]
        assert proc.returncode == 0, output[-2000:]
    two, single, halved = (_weights(tmp_path / run / "checkpoints" / "last.ckpt") for run in ("two", "one", "half"))
    worst = max((two[k] - single[k]).abs().max().item() for k in single)
    moved = max((halved[k] - single[k]).abs().max().item() for k in single)  # what another batch changes
    assert worst < 1e-5 < moved, (worst, moved)
