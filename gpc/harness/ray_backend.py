"""`--backend ray`: the lockstep groups of `gpc eval` / `gpc record` and the episodes of `gpc collect` on a Ray cluster.

The unit of work is the local backend's (``evaluation._work`` runs a group, ``collection._run_one``
an episode): each Ray actor is one worker process that loads the checkpoints once and serves many
units. Checkpoints travel as bytes through Ray's object store (``ray.put`` once, fetched by each
actor), so no node needs the driver's filesystem. Results come back in order whatever finishes
first, and every unit's randomness is its own, so results equal ``--backend local --workers 1``.
An actor that dies (its process killed, its node lost) has its unit run again on another one; a
stop (Ctrl-C) kills the actors between two polls and keeps what was finished.

Ray is imported here only, and only when a command asks for it (``pip install "gpc[ray]"``).
A cluster this module starts listens on the loopback interface only; Ray passes arguments and
results between its processes pickled, over its own transport (docs/scale-out.md).
"""

from __future__ import annotations

import io
import logging
import math
import os
import shutil
import tarfile
import tempfile
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from gpc.harness import interrupts

INSTALL = 'pip install "gpc[ray]"'
MAX_TRIES = 3  # runs of one unit on actors that died under it before the command gives up


@dataclass(frozen=True)
class RayOptions:
    """Where the work runs: a cluster's address (None: start one on this machine) and each worker's share of it."""

    address: str | None = None  # --ray-address: "auto", "HOST:PORT" of a running head node, or None
    cpus: float = 1.0  # --worker-cpus: CPUs Ray reserves per worker (actor)
    gpus: float = 0.0  # --worker-gpus: GPUs per worker (1 with --device cuda)

    def __post_init__(self) -> None:
        if self.cpus < 0 or self.gpus < 0:
            raise ValueError(f"--worker-cpus {self.cpus} / --worker-gpus {self.gpus}: must not be negative")


def require() -> Any:
    """The ``ray`` module, or one line saying how to install it (a ``ValueError``: exit 2)."""
    try:
        import ray
    except ImportError:
        raise ValueError(f"--backend ray: Ray is not installed; install it with {INSTALL}") from None
    return ray


def _connect(options: RayOptions, workers: int = 1) -> bool:
    """Join the cluster (an existing connection is kept); returns whether this call started it.

    A cluster started here offers at least what ``workers`` reserve (``--workers 4`` on 2 cores runs four workers, as
    the local backend's four processes would); a cluster that offers less refuses in one line, where Ray itself would
    wait for the missing workers without end."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # nothing is reported anywhere
    if options.address is None:  # read when ray is first imported: the local cluster's servers bind 127.0.0.1 only
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    ray = require()
    if ray.is_initialized():
        return False
    common = {"include_dashboard": False, "log_to_driver": False, "logging_level": logging.ERROR}
    try:
        if options.address is None:
            # "local": a new cluster of its own, even where another runs on this machine (a test's, a `ray start`)
            ray.init(address="local", num_cpus=max(os.cpu_count() or 1, math.ceil(workers * options.cpus)), **common)
        else:
            ray.init(address=options.address, **common)
    except ConnectionError as exc:
        raise OSError(f"--ray-address {options.address}: no Ray cluster answers there ({str(exc).splitlines()[0]})") from None
    offered = ray.cluster_resources()
    for what, each in (("CPU", options.cpus), ("GPU", options.gpus)):
        if workers * each > offered.get(what, 0.0):
            ray.shutdown()
            where = "this machine's cluster" if options.address is None else f"the cluster at {options.address}"
            raise ValueError(f"--workers {workers} x --worker-{what.lower()}s {each:g} need {workers * each:g} {what}s; "
                             f"{where} has {offered.get(what, 0.0):g}: give fewer workers or a smaller share each")
    return True


# ---------------------------------------------------------------------- checkpoints through the object store
def _pack(path: str) -> bytes:
    """A checkpoint file's bytes, or a directory (a LeRobot policy) as an uncompressed tar."""
    p = Path(path)
    if p.is_file():
        return p.read_bytes()
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        tar.add(p, arcname=p.name)
    return buffer.getvalue()


def _unpack(data: bytes, name: str, is_dir: bool, into: Path) -> str:
    into.mkdir()
    if not is_dir:
        (into / name).write_bytes(data)
    else:
        with tarfile.open(fileobj=io.BytesIO(data)) as tar:
            tar.extractall(into, filter="data")  # names and modes checked: nothing lands outside ``into``
    return str(into / name)


def checkpoint_paths(factory: Any) -> dict[str, str]:
    """The recipe's checkpoint fields and their paths (policy, world model, learned reward) that exist here."""
    from gpc.harness.recipes import PlannerRecipe

    if not isinstance(factory, PlannerRecipe):
        return {}
    fields = {"policy": factory.policy, "world_model": factory.world_model, "reward": factory.reward.checkpoint}
    return {key: path for key, path in fields.items() if path and Path(path).exists()}


def _localized(factory: Any, blobs: dict[str, tuple[Any, str, bool]], into: Path) -> Any:
    """The recipe with each shipped checkpoint written under ``into`` (inside the actor) and pointed at there."""
    import ray

    local = {key: _unpack(ray.get(ref), name, is_dir, into / key) for key, (ref, name, is_dir) in blobs.items()}
    if "reward" in local:
        factory = replace(factory, reward=replace(factory.reward, checkpoint=local.pop("reward")))
    return replace(factory, **local) if local else factory


class Worker:
    """One Ray actor: builds the controller once (``evaluation._init_worker``), then serves groups or episodes."""

    def __init__(self, factory: Any, threads: int, tasks: Sequence[Any], blobs: dict[str, tuple[Any, str, bool]]) -> None:
        from gpc.harness.evaluation import _init_worker

        folder = Path(tempfile.mkdtemp(prefix="gpc-ray-"))
        try:  # the checkpoints are read into memory here; their copies go at once
            _init_worker(_localized(factory, blobs, folder) if factory is not None else _no_controller, threads, True, tasks)
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def where(self) -> tuple[int, str]:
        """This worker's process id and Ray node."""
        import ray

        return os.getpid(), ray.get_runtime_context().get_node_id()

    def group(self, job: Any) -> dict[str, Any]:
        from gpc.harness.evaluation import _work

        return _work(job)

    def episode(self, args: Any) -> Any:
        from gpc.harness.collection import _run_one

        return _run_one(args)


def _no_controller() -> Any:
    """Scripted collection needs no controller."""
    return None


# ---------------------------------------------------------------------- the pool
@dataclass
class Status:
    """What the progress bar shows and the tests read: workers alive, units rerun, where the workers run."""

    alive: int = 0
    reruns: int = 0
    busy: dict[int, int] = field(default_factory=dict)  # unit index -> the pid of the actor running it
    nodes: set[str] = field(default_factory=set)  # the Ray nodes the first workers were placed on
    pids: list[int] = field(default_factory=list)  # the first workers' process ids


STATUS = Status()


class _Pool:
    """``workers`` actors; a dead one is replaced (Ray places it where resources allow)."""

    def __init__(self, ray: Any, make: Callable[[], Any], workers: int) -> None:
        self.ray, self.make = ray, make
        self.actors = [make() for _ in range(workers)]
        self.pids: dict[Any, int] = {}
        self.ready: set[Any] = set()  # workers known to be up: placed, or a unit finished since they started

    def place(self) -> set[str]:
        """Wait for the workers to start (their checkpoints loaded); the nodes they run on."""
        places = self.ray.get([actor.where.remote() for actor in self.actors])
        self.pids = {actor: pid for actor, (pid, _) in zip(self.actors, places)}
        self.ready = set(self.actors)
        return {node for _, node in places}

    def replace(self, actor: Any) -> None:
        self.ready.discard(actor)
        self.ray.kill(actor, no_restart=True)
        self.actors[self.actors.index(actor)] = self.make()

    def close(self) -> None:
        for actor in self.actors:
            self.ray.kill(actor, no_restart=True)


def run_ordered(ray: Any, pool: _Pool, method: str, items: Sequence[Any], every: float = 0.25) -> Iterator[Any]:
    """Each item through ``actor.<method>``, one at a time per actor, yielded in the items' order.

    A unit whose actor died is put first in line again (``MAX_TRIES`` at most); an error inside a unit
    is raised here as itself. A stop is checked every ``every`` seconds while waiting.
    """
    from ray.exceptions import RayActorError, RayTaskError, WorkerCrashedError

    todo: deque[int] = deque(range(len(items)))
    done: dict[int, Any] = {}
    pending: dict[Any, tuple[int, Any]] = {}
    tries, upto = dict.fromkeys(range(len(items)), 0), 0
    STATUS.reruns, STATUS.busy = 0, {}
    while upto < len(items):
        busy = {actor for _, actor in pending.values()}
        for actor in [a for a in pool.actors if a not in busy]:
            if todo:
                i = todo.popleft()
                pending[getattr(actor, method).remote(items[i])] = (i, actor)
        ready, _ = ray.wait(list(pending), num_returns=1, timeout=every)
        interrupts.check()
        for ref in ready:
            i, actor = pending.pop(ref)
            try:
                done[i] = ray.get(ref)
                pool.ready.add(actor)
            except RayTaskError as exc:  # the unit itself failed: the local backend raises the same
                raise (exc.cause if isinstance(exc.cause, BaseException) else exc) from None
            except (RayActorError, WorkerCrashedError) as exc:
                tries[i] += 1
                if tries[i] >= MAX_TRIES:
                    raise OSError(f"a Ray worker died under the same unit of work {tries[i]} times (last: "
                                  f"{str(exc).splitlines()[0]}); what was finished is kept") from None
                pool.replace(actor)
                todo.appendleft(i)
                STATUS.reruns += 1
        STATUS.busy, STATUS.alive = {i: pool.pids.get(actor, -1) for i, actor in pending.values()}, len(pool.ready)
        while upto in done:
            yield done.pop(upto)
            upto += 1


def _units(factory: Any, threads: int, options: RayOptions, workers: int, method: str, items: Sequence[Any]) -> Iterator[Any]:
    """Start or join the cluster, run ``items`` on ``workers`` actors, then end them (and a cluster started here)."""
    from gpc.tasks import user_tasks

    started = _connect(options, min(workers, len(items)))
    ray = require()
    try:
        blobs = {key: (ray.put(_pack(path)), Path(path).name, Path(path).is_dir())
                 for key, path in checkpoint_paths(factory).items()}
        actor = ray.remote(num_cpus=options.cpus, num_gpus=options.gpus, max_restarts=0)(Worker)
        pool = _Pool(ray, lambda: actor.remote(factory, threads, user_tasks(), blobs), min(workers, len(items)))
        try:
            STATUS.nodes = pool.place()
            STATUS.alive, STATUS.pids = len(pool.ready), list(pool.pids.values())
            yield from run_ordered(ray, pool, method, items)
        finally:
            pool.close()
            STATUS.alive = 0
    finally:
        if started:
            ray.shutdown()


def map_groups(factory: Callable[[], Any], jobs: list, config: Any) -> Iterator[dict[str, Any]]:
    """``evaluation.map_groups`` on Ray: each ``(seeds, config)`` job a lockstep group, in order."""
    yield from _units(factory, config.threads, config.backend, config.workers, "group", jobs)


def map_episodes(args: list, workers: int, options: RayOptions) -> Iterator[Any]:
    """``collection._results`` on Ray: each scripted episode's (arrays, stats), in seed order."""
    yield from _units(None, 1, options, workers, "episode", args)


def decisions(group: dict[str, Any]) -> int:
    """Episode decisions a finished group made (the progress bar's rate)."""
    return int(sum(group.get("call_sizes", [])))


def rate(done: int, since: float) -> float:
    return done / max(time.perf_counter() - since, 1e-9)
