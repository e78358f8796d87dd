"""`--backend ray`: the same results as one local process, on a two-node Ray cluster of this machine (127.0.0.1).

One cluster serves the module (a head and a second node, one CPU each, so the two workers land on
two nodes); the commands join it instead of starting their own.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import sys
import time
from pathlib import Path

import pytest
from faults import digest, inline

from gpc.datasets.store import EpisodeStore
from gpc.harness import interrupts, ray_backend
from gpc.harness.evaluation import EvalConfig, evaluate
from gpc.harness.recipes import make_recipe
from gpc.harness.results import run_into

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.slow]  # Ray's start-up: make test runs them, test-fast not
SEEDS = tuple(range(100000, 100008))


@pytest.fixture(scope="module")
def cluster():
    """A head node and a second node, both listening on 127.0.0.1 only; torn down after the module."""
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"  # read when ray is imported: loopback, as the backend does
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    import ray
    from ray.cluster_utils import Cluster

    nodes = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    nodes.add_node(num_cpus=1)
    ray.init(address=nodes.address, log_to_driver=False)
    nodes.wait_for_nodes()
    yield nodes
    ray.shutdown()
    for node in [*nodes.worker_nodes, nodes.head_node]:  # at once: a graceful stop drains each node for up to 30 s
        nodes.remove_node(node, allow_graceful=False)


def _eval(models: dict, out: Path, *extra: str) -> list[str]:
    return ["eval", str(models["policy"]), "--planner", "rank", "-K", "3", "--world-model", str(models["wm"]),
            "--seeds", "100000:100006", "--batch", "2", "--max-steps", "30", "--out", str(out), *extra]


def _numbers(out: Path) -> tuple[list, dict]:
    summary = json.loads((out / "summary.json").read_text())
    return json.loads((out / "episodes.json").read_text()), {k: summary[k] for k in ("mean_score", "success_rate", "n_action_steps")}


def _bytes(store: Path) -> dict[str, str]:
    """Every file of a store, by its path inside, but the root attributes (which hold the time it was created)."""
    files = {name.split("/", 1)[1]: sha for name, sha in digest(store).items()}
    return {name: sha for name, sha in files.items() if name not in (".zattrs", "zarr.json")}


def _attrs(store: Path) -> dict:
    attrs = dict(EpisodeStore.open(store).attrs)
    return {key: value for key, value in attrs.items() if key != "created"}


def test_eval_on_two_nodes_equals_one_local_process(cluster, tiny_pusht, tmp_path):
    code, output = inline(*_eval(tiny_pusht, tmp_path / "local"))
    assert code == 0, output
    code, output = inline(*_eval(tiny_pusht, tmp_path / "ray", "--backend", "ray", "--workers", "2"))
    assert code == 0, output
    assert len(ray_backend.STATUS.nodes) == 2  # one worker on each node
    assert "decisions/s" in output and "workers alive" in output
    assert (tmp_path / "ray" / "episodes.json").read_bytes() == (tmp_path / "local" / "episodes.json").read_bytes()
    assert _numbers(tmp_path / "ray") == _numbers(tmp_path / "local")


@pytest.mark.extended  # make test-extended (CI's make test runs the two-node equality)
def test_record_and_collect_on_ray_write_the_local_stores_byte_for_byte(cluster, tiny_pusht, tmp_path):
    record = ["record", str(tiny_pusht["policy"]), "--planner", "rank", "-K", "3", "--world-model", str(tiny_pusht["wm"]),
              "--episodes", "4", "--seed", "60000", "--batch", "2", "--max-steps", "20"]
    collect = ["collect", "--episodes", "4", "--no-images", "--max-steps", "40"]
    for name, args in (("record", record), ("collect", collect)):
        local, on_ray = tmp_path / f"{name}-local.zarr", tmp_path / f"{name}-ray.zarr"
        assert inline(*args, "--out", str(local))[0] == 0
        code, output = inline(*args, "--out", str(on_ray), "--backend", "ray", "--workers", "2")
        assert code == 0, output
        assert _bytes(on_ray) == _bytes(local) and len(_bytes(local)) > 5, name
        assert _attrs(on_ray) == _attrs(local), name


@pytest.fixture(scope="module")
def planned(tiny_pusht):
    """GPC-RANK on 8 seeds in groups of one, and its results in one local process."""
    recipe = make_recipe(tiny_pusht["policy"], "rank", world_model=str(tiny_pusht["wm"]), k=3)
    config = EvalConfig(seeds=SEEDS, task="pusht", max_steps=30, batch=1, workers=2, backend=ray_backend.RayOptions())
    return recipe, config, evaluate(recipe, dataclasses.replace(config, workers=1, backend=None))["episodes"]


@pytest.mark.extended  # make test-extended (CI's make test runs the two-node equality)
def test_a_killed_worker_has_its_groups_run_again_elsewhere(cluster, planned):
    recipe, config, local = planned
    killed: list[int] = []

    def kill(group: dict) -> None:
        if not killed:  # after the first group: the other worker is inside one
            pid = next(iter(ray_backend.STATUS.busy.values()))
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    result = evaluate(recipe, config, on_group=kill)
    assert killed and ray_backend.STATUS.reruns >= 1
    assert [r["seed"] for r in result["episodes"]] == list(SEEDS)  # every seed exactly once
    assert result["episodes"] == local


@pytest.mark.extended  # make test-extended (CI's make test runs the two-node equality)
def test_a_stopped_ray_eval_ends_its_workers_keeps_its_groups_and_resumes(cluster, planned, tmp_path):
    recipe, config, local = planned

    def stop(group: dict) -> None:
        interrupts._requested.append(signal.SIGINT)  # what Ctrl-C does inside `gpc`'s deferred_signals

    try:
        with pytest.raises(interrupts.Interrupted) as stopped:
            run_into(tmp_path, recipe, config, on_group=stop)
    finally:
        interrupts._requested.clear()
    assert f"1 of {len(SEEDS)} lockstep groups are kept" in stopped.value.kept and stopped.value.exit_code == 130
    assert ray_backend.STATUS.alive == 0
    deadline = time.time() + 20
    while time.time() < deadline and any(Path(f"/proc/{pid}").exists() for pid in ray_backend.STATUS.pids):
        time.sleep(0.2)
    assert not any(Path(f"/proc/{pid}").exists() for pid in ray_backend.STATUS.pids)  # the workers were ended
    ran: list[dict] = []
    result = run_into(tmp_path, recipe, config, resume=True, on_group=ran.append)
    assert len(ran) == len(SEEDS) - 1 and result["episodes"] == local


def test_without_ray_the_backend_says_how_to_install_it(tiny_pusht, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails, as where it is not installed
    for args in (_eval(tiny_pusht, tmp_path / "e"), ["collect", "--out", str(tmp_path / "c.zarr")]):
        code, output = inline(*args, "--backend", "ray")
        assert code == 2 and output.strip() == 'gpc: error: --backend ray: Ray is not installed; install it with pip install "gpc[ray]"'
    assert not list(tmp_path.iterdir())


def test_backend_and_device_options_are_checked_before_any_work(tiny_pusht, tmp_path):
    import torch

    for extra, message in ((("--ray-address", "127.0.0.1:6379"), "--ray-address: applies to --backend ray"),
                           (("--backend", "slurm"), "--backend 'slurm': use one of local, ray"),
                           (("--device", "tpu"), "--device 'tpu': use one of cpu, cuda")):
        code, output = inline(*_eval(tiny_pusht, tmp_path / "e"), *extra)
        assert code == 2 and output.strip() == f"gpc: error: {message}", output
    if not torch.cuda.is_available():
        code, output = inline(*_eval(tiny_pusht, tmp_path / "e"), "--device", "cuda")
        assert code == 2 and "--device cuda: torch sees no CUDA GPU on this machine" in output
    assert not list(tmp_path.iterdir())
    # a GPU run is another run (its numbers differ): the device is part of the identity, left out on the CPU
    recipe = make_recipe(tiny_pusht["policy"], "rank", world_model=str(tiny_pusht["wm"]), k=3, device="cuda")
    assert recipe.summary()["device"] == "cuda" and "device" not in dataclasses.replace(recipe, device="cpu").summary()


@pytest.mark.extended  # make test-extended: a minute of Ray start-ups
def test_a_cluster_started_here_runs_more_workers_than_cores_and_a_short_one_refuses(tmp_path):
    """gpc's own cluster offers what the workers reserve (Ray would otherwise wait for the missing ones without end);
    a cluster that offers less (no GPU here for --worker-gpus 1) is refused in one line, before any episode."""
    import subprocess

    gpc = Path(sys.executable).parent / "gpc"
    workers = (os.cpu_count() or 1) + 1
    args = [str(gpc), "collect", "--task", "draw", "--episodes", str(workers), "--no-images", "--backend", "ray"]
    done = subprocess.run([*args, "--workers", str(workers), "--out", str(tmp_path / "many.zarr")], capture_output=True,
                          text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-2000:]
    assert len(EpisodeStore.open(tmp_path / "many.zarr").episode_ends) == workers
    import torch

    if not torch.cuda.is_available():
        short = subprocess.run([*args, "--workers", "2", "--worker-gpus", "1", "--out", str(tmp_path / "gpu.zarr")],
                               capture_output=True, text=True, timeout=300)
        assert short.returncode == 2 and short.stderr.strip().splitlines() == [
            "gpc: error: --workers 2 x --worker-gpus 1 need 2 GPUs; this machine's cluster has 0: give fewer workers or a "
            "smaller share each"], short.stderr[-2000:]
        assert not (tmp_path / "gpu.zarr").exists()
