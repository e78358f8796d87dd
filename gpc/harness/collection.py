"""Collection: scripted episodes from a task, appended whole to an episode store.

Episodes run in worker processes and are written by this process in seed order, so a
store's content depends only on the command, never on ``--workers``. Re-running the
same command resumes: seeds already in the store are skipped.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from gpc import __version__
from gpc.datasets.errors import DataError
from gpc.datasets.store import EpisodeStore
from gpc.tasks import get_task
from gpc.tasks.base import COLLECTORS


@dataclass(frozen=True)
class CollectJob:
    """One `gpc collect` invocation."""

    out: Path
    task: str  # a registered task's name (gpc.tasks.get_task)
    kind: str = "expert"  # expert | explore
    episodes: int = 100
    seed: int = 0
    workers: int = 1
    goal: str = "fixed"
    images: bool = True
    max_steps: int = 300
    overwrite: bool = False

    def __post_init__(self) -> None:
        get_task(self.task).check_goal(self.goal)  # raises for an unknown task
        if self.kind not in COLLECTORS:
            raise ValueError(f"collector {self.kind!r}: use one of {', '.join(COLLECTORS)}")
        for name in ("episodes", "workers", "max_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} {getattr(self, name)}: must be at least 1")
        if self.seed < 0:
            raise ValueError(f"--seed {self.seed}: must be non-negative")

    @property
    def seeds(self) -> list[int]:
        return list(range(self.seed, self.seed + self.episodes))

    def provenance(self) -> dict:
        """What a store records about how it was made; resuming requires it to match."""
        task = get_task(self.task)
        return {
            "task": self.task,
            "env": task.env_params(self.goal, self.max_steps),
            "collector": {"kind": self.kind, **task.collector_params(self.kind, self.max_steps)},
            "keys": task.record_keys(self.images, self.goal),
        }


@dataclass(frozen=True)
class CollectSummary:
    path: str
    written: int
    skipped: int
    episodes: int
    steps: int
    mean_score: float | None  # over the episodes written by this call (None when it wrote none)
    success_rate: float | None
    contact_fraction: float | None


def _run_one(args: tuple[str, str, int, str, bool, int]) -> tuple[dict[str, np.ndarray], dict]:
    task_name, kind, seed, goal, images, max_steps = args
    task = get_task(task_name)
    data, stats = task.record(kind, seed, goal, images, max_steps)
    return data, asdict(stats)


def open_for_job(job: CollectJob) -> EpisodeStore:
    """Create the store, or reopen it for resuming if it was made by the same command."""
    wanted = job.provenance()
    if job.out.exists() and not job.overwrite:
        store = EpisodeStore.open(job.out, writable=True)
        have, want = {k: store.attrs.get(k) for k in wanted}, _plain(wanted)
        if have != want:
            diff = [k for k in wanted if have[k] != want[k]]
            raise DataError(
                f"{job.out}: holds data of another kind ({', '.join(diff)} differ); "
                "choose another --out or pass --overwrite"
            )
        return store
    attrs = {**wanted, "gpc_version": __version__, "created": datetime.now(timezone.utc).isoformat()}
    return EpisodeStore.create(job.out, attrs, overwrite=job.overwrite)


def _plain(value: dict[str, Any]) -> dict[str, Any]:
    """Round-trip through JSON types, as Zarr attributes store them."""
    import json

    return json.loads(json.dumps(value))


def collect(job: CollectJob, on_start: Callable[[int], None] | None = None,
            on_episode: Callable[[dict], None] | None = None) -> CollectSummary:
    """Collect the job's missing seeds into its store.

    ``on_start`` gets the number of seeds already present; ``on_episode`` each new episode's stats.
    """
    store = open_for_job(job)
    present = store.episode_seeds()
    done = set() if present is None else {int(s) for s in present}
    todo = [s for s in job.seeds if s not in done]
    if on_start:
        on_start(len(job.seeds) - len(todo))
    args = [(job.task, job.kind, s, job.goal, job.images, job.max_steps) for s in todo]
    stats: list[dict] = []
    for data, st in _results(args, job.workers):
        store.append_episode(data, seed=st["seed"], score=st["score"])
        stats.append(st)
        if on_episode:
            on_episode(st)
    scores = np.array([s["score"] for s in stats]) if stats else np.zeros(0)
    return CollectSummary(
        path=str(job.out), written=len(stats), skipped=len(job.seeds) - len(todo),
        episodes=store.n_episodes, steps=store.n_steps,
        mean_score=float(scores.mean()) if stats else None,
        success_rate=float(np.mean([s["success"] for s in stats])) if stats else None,
        contact_fraction=float(np.average([s["contact_fraction"] for s in stats],
                                          weights=[s["steps"] for s in stats])) if stats else None,
    )


def _results(args: list, workers: int) -> Iterator[tuple[dict[str, np.ndarray], dict]]:
    if workers == 1 or len(args) <= 1:
        yield from map(_run_one, args)
        return
    with mp.get_context("spawn").Pool(min(workers, len(args))) as pool:
        yield from pool.imap(_run_one, args, chunksize=1)


def evaluate_collector(task: str, kind: str, seeds: Sequence[int], goal: str = "fixed", max_steps: int | None = None,
                       on_episode: Callable[[dict], None] | None = None) -> dict[str, Any]:
    """Closed-loop score of a task's scripted collector (the expert stops at success): max reward per episode."""
    t = get_task(task)
    t.check_goal(goal)
    res: dict[str, Any] = {"seeds": [int(s) for s in seeds], "scores": [], "successes": [], "steps": [], "seconds": []}
    for seed in res["seeds"]:
        t0 = time.perf_counter()
        _, stats = t.record(kind, seed, goal, False, max_steps or t.max_episode_steps)
        row = {"scores": stats.score, "successes": stats.success, "steps": stats.steps, "seconds": time.perf_counter() - t0}
        for key, value in row.items():
            res[key].append(value)
        if on_episode:
            on_episode(row)
    res.update(mean_score=float(np.mean(res["scores"])), success_rate=float(np.mean(res["successes"])),
               median_seconds=float(np.median(res["seconds"])), max_seconds=float(np.max(res["seconds"])))
    return res
