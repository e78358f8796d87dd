"""Where `gpc eval`, `gpc record` and `gpc collect` run their work: local processes or a Ray cluster (docs/scale-out.md)."""

from __future__ import annotations

from contextlib import contextmanager
from typing import Annotated, Any

import typer

from gpc.cli.limits import MAX_PROCESSES
from gpc.cli.run_options import with_shared_options

BACKENDS = ("local", "ray")
Backend = Annotated[str, typer.Option("--backend", help="local: processes on this machine; ray: actors on a Ray cluster (pip install \"gpc\\[ray]\"). The results are the same.")]
RayAddress = Annotated[str | None, typer.Option("--ray-address", help="--backend ray: a running cluster (HOST:PORT of its head, or auto); default: start one on this machine, listening on 127.0.0.1 only.")]
WorkerCpus = Annotated[float, typer.Option("--worker-cpus", min=0, max=MAX_PROCESSES, help="--backend ray: CPUs each worker reserves.")]
WorkerGpus = Annotated[float | None, typer.Option("--worker-gpus", min=0, max=MAX_PROCESSES, help="--backend ray: GPUs each worker reserves (default: 1 with --device cuda, else 0).")]

BACKEND_OPTIONS = (("backend", Backend, "local"), ("ray_address", RayAddress, None), ("worker_cpus", WorkerCpus, 1.0),
                   ("worker_gpus", WorkerGpus, None))
with_backend_options = with_shared_options(BACKEND_OPTIONS, "scale")


def backend_from_options(scale: dict[str, Any] | None, device: str = "cpu") -> Any:
    """``None`` for the local backend, else the ``RayOptions`` the options describe (Ray checked to be installed)."""
    assert scale is not None  # with_backend_options passes them
    if scale["backend"] not in BACKENDS:
        raise ValueError(f"--backend {scale['backend']!r}: use one of {', '.join(BACKENDS)}")
    if scale["backend"] == "local":
        given = [name for name, key in (("--ray-address", "ray_address"), ("--worker-gpus", "worker_gpus")) if scale[key] is not None]
        if given or scale["worker_cpus"] != 1.0:
            raise ValueError(f"{(given or ['--worker-cpus'])[0]}: applies to --backend ray")
        return None
    from gpc.harness import ray_backend

    ray_backend.require()
    gpus = scale["worker_gpus"] if scale["worker_gpus"] is not None else (1.0 if device == "cuda" else 0.0)
    return ray_backend.RayOptions(address=scale["ray_address"], cpus=scale["worker_cpus"], gpus=gpus)


@contextmanager
def cluster_bar(label: str, total: Any, done: int = 0) -> Any:
    """One bar over the seeds of the whole cluster, with episode decisions per second and the workers alive;
    yields the callback that advances it by a finished group."""
    import time

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from gpc.harness import ray_backend

    bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                   TextColumn("{task.fields[rate]:.1f} decisions/s, {task.fields[alive]} workers alive"), TimeRemainingColumn())
    tid = bar.add_task(label, total=total, completed=done, rate=0.0, alive=0)
    since, decisions = time.perf_counter(), [0]

    def advance(group: dict[str, Any]) -> None:
        decisions[0] += ray_backend.decisions(group)
        bar.update(tid, advance=len(group["episodes"]), rate=ray_backend.rate(decisions[0], since), alive=ray_backend.STATUS.alive)

    with bar:
        yield advance
