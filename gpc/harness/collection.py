"""Collection: episodes of a task's scripted collectors, or of a policy or planner in closed loop, appended
whole to an episode store.

Episodes run in worker processes and are written by this process in seed order, so a
store's content depends only on the command, never on ``--workers``. Re-running the
same command resumes: seeds already in the store are skipped. Closed-loop episodes
(``gpc record``) are the very episodes ``gpc eval`` scores for those seeds: the data a
world model needs where the planner drives the scene, not only where the expert does.
"""

from __future__ import annotations

import inspect
import json
import multiprocessing as mp
import os
import shutil
import time
from collections.abc import Callable, Generator, Sequence
from contextlib import closing
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from gpc import __version__
from gpc.datasets.errors import DataError
from gpc.datasets.fresh import Fresh, fresh
from gpc.datasets.locks import check_free, exclusive
from gpc.datasets.store import EpisodeStore, store_record
from gpc.harness import interrupts
from gpc.harness.evaluation import EvalConfig, map_groups
from gpc.harness.files import check_out, write_atomic
from gpc.harness.ownership import claim
from gpc.harness.stores import check_stores, foreign_files
from gpc.tasks import get_task, register_task, user_tasks
from gpc.tasks.base import COLLECTORS, EXPERT_ACTION_KEY, ActionNoise, Task, check_seeds
from gpc.tasks.measure import summarise

CLOSED_LOOP = "closed-loop"


@dataclass(frozen=True)
class CollectJob:
    """One `gpc collect` invocation."""

    out: Path
    task: str  # a registered task's name (gpc.tasks.get_task)
    kind: str = "expert"  # expert | explore | closed-loop (``controller``'s episodes)
    episodes: int = 100
    seed: int = 0
    workers: int = 1
    goal: str = "fixed"
    images: bool = True
    max_steps: int | None = None  # steps per episode at most (None: the task's episode length)
    overwrite: bool = False
    controller: Any = None  # closed-loop: a picklable recipe (``gpc.harness.recipes.PlannerRecipe``)
    batch: int = 25  # closed-loop: episodes stepped in lockstep per controller call (gpc eval's default)
    threads: int = 1  # closed-loop: torch threads per process (as in ``gpc eval``, the episodes depend on it)
    backend: Any = None  # None: local processes; a ``ray_backend.RayOptions``: Ray actors (the same store)
    noise: ActionNoise | None = None  # expert only: DART demonstrations (the labels stored as ``expert_action``)

    def __post_init__(self) -> None:
        task = get_task(self.task)  # raises for an unknown task
        task.check_goal(self.goal)
        if self.max_steps is None:
            object.__setattr__(self, "max_steps", task.max_episode_steps)
        if self.kind not in (*COLLECTORS, CLOSED_LOOP):
            raise ValueError(f"collector {self.kind!r}: use one of {', '.join(COLLECTORS)}")
        if (self.kind == CLOSED_LOOP) != (self.controller is not None):
            raise ValueError(f"collector {self.kind!r}: a controller is recorded by, and only by, the {CLOSED_LOOP} collector")
        for name in ("episodes", "workers", "max_steps", "batch", "threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} {getattr(self, name)}: must be at least 1")
        check_seeds(self.seed, self.seed + self.episodes - 1, f"--seed {self.seed} with --episodes {self.episodes}")
        if self.noise is not None and self.kind != "expert":
            raise ValueError("--dart: action noise applies to the expert's demonstrations, not to --explore or gpc record")
        if self.noise is not None and len(inspect.signature(task.record).parameters) < 6:
            raise ValueError(f"--dart: task {self.task}'s record takes no action noise (docs/new-task.md)")

    @property
    def steps(self) -> int:
        """Steps per episode at most (the task's episode length unless given)."""
        assert self.max_steps is not None  # filled in __post_init__
        return self.max_steps

    @property
    def seeds(self) -> list[int]:
        return list(range(self.seed, self.seed + self.episodes))

    def provenance(self) -> dict:
        """What a store records about how it was made; resuming requires it to match."""
        task = get_task(self.task)
        if self.kind == CLOSED_LOOP:  # the controller's part of a run's identity, as `gpc eval --resume` matches it
            from gpc.harness.identity import controller_identity

            made_by = controller_identity(self.controller)
            collector = {**made_by["controller"], "checkpoints": made_by["checkpoints"], "batch": self.batch,
                         "threads": self.threads, "max_steps": self.steps}
        else:
            collector = task.collector_params(self.kind, self.steps)
        keys = task.record_keys(self.images, self.goal)
        if self.noise is not None:  # a store with it names it: its actions are not the expert's own
            collector, keys = {**collector, "dart": asdict(self.noise)}, sorted(keys + [EXPERT_ACTION_KEY])
        return {
            "task": self.task,
            "env": task.env_params(self.goal, self.steps),
            "collector": {"kind": self.kind, **collector},
            "keys": keys,
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


def _run_one(args: tuple[str, str, int, str, bool, int, ActionNoise | None]) -> tuple[dict[str, np.ndarray], dict]:
    task_name, kind, seed, goal, images, max_steps, noise = args
    task = get_task(task_name)
    # a task written before --dart takes five arguments: it is called as it was
    data, stats = task.record(kind, seed, goal, images, max_steps, *([noise] if noise is not None else []))
    return data, asdict(stats)


def _matching(store: EpisodeStore, wanted: dict[str, Any], out: Path) -> None:
    """Resuming needs the store to have been made by the same command (task, env, collector, keys)."""
    have, want = {k: store.attrs.get(k) for k in wanted}, _plain(wanted)
    if have != want:
        from gpc.harness.identity import first_difference

        diff = [k for k in wanted if have[k] != want[k]]
        raise DataError(f"{out}: holds data of another kind ({', '.join(diff)} differ: "
                        f"{first_difference(have[diff[0]], want[diff[0]], diff[0])}); choose another --out or pass --overwrite")


def _ours(out: Path) -> None:
    """``--overwrite`` replaces only a store this project wrote: its ``gpc_format`` record proves it."""
    if not out.is_dir():
        raise DataError(f"{out}: is a file, not a store gpc wrote; refusing to replace it (remove it yourself or choose another --out)")
    if not _wrote(out):
        raise DataError(f"{out}: is not a store gpc wrote (no gpc_format record); refusing to replace it "
                        "(remove it yourself or choose another --out)")
    foreign = foreign_files(out)
    if foreign:
        shown = ", ".join(str(p.relative_to(out)) for p in foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
        raise DataError(f"{out}: holds files gpc did not write ({shown}); --overwrite would delete them: "
                        "move them out of the store first")


def _wrote(path: Path) -> bool:
    """Whether ``path`` is a store gpc wrote (read-only; its data may be damaged)."""
    return "gpc_format" in store_record(path)


def _real(out: Path) -> Path:
    """The store itself when ``--out`` is a symbolic link: it is replaced there, and the link is kept."""
    return Path(os.path.realpath(out))


def check_store_out(out: Path, overwrite: bool) -> None:
    """What ``check_job`` can refuse from the path alone: run first where the job needs models loaded to be known."""
    out = Path(out)
    check_free(out, "store")  # a store another process is writing: its pid, not what its half-made records say
    new, old, journal = _staging(_real(out))
    for place in (new, old) if overwrite else ():  # gpc's own staging places, touched only as it left them
        if (place.exists() or place.is_symlink()) and not (_wrote(place) and (place == new or journal.exists())):
            raise DataError(f"{place}: is in the way of {out} (gpc stages a store being replaced there) and is not "
                            "one gpc left there; move it away")
    if not out.exists():
        check_out(out.parent)
    elif overwrite:
        _ours(out)
    elif not out.is_dir():
        raise DataError(f"{out}: is a file, not a store; choose another --out")


def check_job(job: CollectJob) -> None:
    """Refuse, reading only, a ``--out`` the job may not write (before its lock exists: nothing is left behind)."""
    out = Path(job.out)
    check_store_out(out, job.overwrite)
    if out.is_dir() and not job.overwrite:
        store = EpisodeStore.open(out)
        _matching(store, job.provenance(), out)
        if store.n_episodes:  # the rows it holds are the task's (a store edited by hand is refused, not grown)
            check_stores(get_task(job.task), [out], store.keys)


def _staging(out: Path) -> tuple[Path, Path, Path]:
    """Where a replacement is written before it takes the store's place, where the old store waits meanwhile,
    and the journal that exists only while the two trade places."""
    return (out.parent / f".{out.name}.new", out.parent / f".{out.name}.old",
            out.parent / f".{out.name}.swapping")


def _finish_swap(out: Path) -> None:
    """Complete a replacement a crash cut while the stores traded places (the old store is never lost).

    Only the journal says a replacement was under way: a folder of that name is otherwise left alone."""
    _, old, journal = _staging(out)
    if not journal.exists():
        return
    if _wrote(old):
        if out.exists():
            shutil.rmtree(old)
        else:
            os.rename(old, out)
    journal.unlink()


def open_for_job(job: CollectJob) -> tuple[EpisodeStore, bool]:
    """The store to write and whether it is a replacement being staged beside the old one.

    A store of the same command is reopened to resume (checked read-only first: refusing changes
    nothing); ``--overwrite`` stages a new store beside one gpc wrote and leaves anything else alone.
    """
    wanted, out = job.provenance(), _real(Path(job.out))
    attrs = {**wanted, "gpc_version": __version__, "created": datetime.now(timezone.utc).isoformat()}
    check_job(job)
    if out.exists() and not job.overwrite:
        return EpisodeStore.open(out, writable=True), False
    if out.exists():
        staging = _staging(out)[0]
        if staging.exists():
            shutil.rmtree(staging)  # an earlier replacement that was stopped (a store gpc wrote: check_job saw to it)
        return EpisodeStore.create(staging, attrs), True
    return EpisodeStore.create(out, attrs), False


def _swap(out: Path) -> None:
    """The staged store takes the old one's place: two renames under a journal, then the old store goes."""
    staging, old, journal = _staging(out)
    journal.touch()
    os.rename(out, old)
    os.rename(staging, out)
    shutil.rmtree(old)
    journal.unlink()


def _plain(value: dict[str, Any]) -> dict[str, Any]:
    """Round-trip through JSON types, as Zarr attributes store them."""
    return json.loads(json.dumps(value))


def collect(job: CollectJob, on_start: Callable[[int], None] | None = None,
            on_episode: Callable[[dict], None] | None = None) -> CollectSummary:
    """Collect the job's missing seeds into its store, one writer at a time.

    ``on_start`` gets the number of seeds already present; ``on_episode`` each new episode's stats.
    A stop (``Interrupted``) between episodes keeps every whole episode written so far.
    """
    out = Path(job.out)
    check_job(job)
    with exclusive(out, "store"):
        real = _real(out)
        _finish_swap(real)
        with fresh(_staging(real)[0] if job.overwrite and real.exists() else real) as made:  # a failed start: removed
            store, replacing, stats, todo = _collect_into(job, made, on_start, on_episode)
        if replacing:
            _swap(real)
            store = EpisodeStore.open(out)
    scores = np.array([s["score"] for s in stats]) if stats else np.zeros(0)
    return CollectSummary(
        path=str(job.out), written=len(stats), skipped=len(job.seeds) - len(todo),
        episodes=store.n_episodes, steps=store.n_steps,
        mean_score=float(scores.mean()) if stats else None,
        success_rate=float(np.mean([s["success"] for s in stats])) if stats else None,
        contact_fraction=float(np.average([s["contact_fraction"] for s in stats],
                                          weights=[s["steps"] for s in stats])) if stats else None,
    )


def _collect_into(job: CollectJob, made: Fresh, on_start: Callable[[int], None] | None,
                  on_episode: Callable[[dict], None] | None) -> tuple[EpisodeStore, bool, list[dict], list[int]]:
    """Open the job's store and append its missing episodes; ``made`` is kept from the first episode on (a new store)."""
    out = Path(job.out)
    store, replacing = open_for_job(job)
    present = store.episode_seeds()
    done = set() if present is None else {int(s) for s in present}
    todo = [s for s in job.seeds if s not in done]
    if on_start:
        on_start(len(job.seeds) - len(todo))
    args = [(job.task, job.kind, s, job.goal, job.images, job.steps, job.noise) for s in todo]
    episodes = _closed_loop(job, todo) if job.kind == CLOSED_LOOP else _results(args, job.workers, job.backend)
    stats: list[dict] = []
    try:
        with closing(episodes) as each:  # a stop between episodes ends the workers now
            for data, st in each:
                try:
                    store.append_episode(data, seed=st["seed"], score=st["score"])
                except OSError as exc:  # a full disk: the episode being written is not committed
                    kept = (f"{out} is unchanged" if replacing else f"{out} is not kept (no episode was written)"
                            if made.new and not made.kept else f"{store.n_episodes} whole episodes are kept in {out}")
                    raise DataError(f"{out}: cannot be written ({exc.strerror or exc}); {kept}") from None
                if not replacing:
                    made.keep()  # a store holding an episode is a result: never removed
                stats.append(st)
                if on_episode:
                    on_episode(st)
                interrupts.check()
    except interrupts.Interrupted as stop:
        stop.kept = (f"{out} is unchanged (its replacement was stopped; run the same command to start it again)"
                     if replacing else f"{store.n_episodes} whole episodes are in {out} (run the same command to resume)")
        raise
    return store, replacing, stats, todo


def _init_worker(tasks: Sequence[Task]) -> None:
    interrupts.ignore_in_worker()
    for task in tasks:  # tasks the parent registered by hand
        register_task(task)


def _results(args: list, workers: int, backend: Any = None) -> Generator[tuple[dict[str, np.ndarray], dict], None, None]:
    if backend is not None:
        from gpc.harness import ray_backend

        yield from ray_backend.map_episodes(args, workers, backend)
        return
    if workers == 1 or len(args) <= 1:
        yield from map(_run_one, args)
        return
    with mp.get_context("spawn").Pool(min(workers, len(args)), initializer=_init_worker, initargs=(user_tasks(),)) as pool:
        yield from interrupts.polled(pool, pool.imap(_run_one, args, chunksize=1))


def _closed_loop(job: CollectJob, todo: list[int]) -> Generator[tuple[dict[str, np.ndarray], dict], None, None]:
    """The controller's episodes of the ``todo`` seeds, in seed order. Lockstep groups are cut from all the job's
    seeds, as ``gpc eval`` cuts them, so a resumed job runs each episode exactly as an uninterrupted one would."""
    config = EvalConfig(seeds=tuple(job.seeds), task=job.task, goal=job.goal, max_steps=job.steps, batch=job.batch,
                        workers=job.workers, threads=job.threads, record=True, backend=job.backend)
    wanted = set(todo)
    jobs = [(group, config) for group in config.groups() if wanted & set(group)]
    for group in map_groups(job.controller, jobs, config):
        for row, data in zip(group["episodes"], group["recordings"]):
            if row["seed"] in wanted:
                contacts = float(np.mean(data["n_contacts"] > 0)) if "n_contacts" in data else 0.0
                yield data, {"seed": row["seed"], "steps": row["steps"], "score": row["score"],
                             "success": row["success"], "contact_fraction": contacts}


def evaluate_collector(task: str, kind: str, seeds: Sequence[int], goal: str = "fixed", max_steps: int | None = None,
                       on_episode: Callable[[dict], None] | None = None, out: Path | None = None) -> dict[str, Any]:
    """Closed-loop score of a task's scripted collector (the expert stops at success): max reward per episode.

    The result holds a Markdown row (``markdown``); ``out``: also write ``KIND.json`` and ``KIND.md`` there.
    """
    t = get_task(task)
    t.check_goal(goal)
    if out is None:
        return _score_collector(t, kind, seeds, goal, max_steps, on_episode, None)
    check_out(out)
    claim([out / f"{kind}.json", out / f"{kind}.md"])
    with exclusive(out, "results folder"):
        return _score_collector(t, kind, seeds, goal, max_steps, on_episode, out)


def _score_collector(t: Task, kind: str, seeds: Sequence[int], goal: str, max_steps: int | None,
                     on_episode: Callable[[dict], None] | None, out: Path | None) -> dict[str, Any]:
    res: dict[str, Any] = {"seeds": [int(s) for s in seeds], "scores": [], "successes": [], "steps": [], "seconds": []}
    episodes = []
    for seed in res["seeds"]:
        t0 = time.perf_counter()
        _, stats = t.record(kind, seed, goal, False, max_steps or t.max_episode_steps)
        episodes.append(stats)
        row = {"scores": stats.score, "successes": stats.success, "steps": stats.steps, "seconds": time.perf_counter() - t0}
        for key, value in row.items():
            res[key].append(value)
        if on_episode:
            on_episode(row)
        try:
            interrupts.check()
        except interrupts.Interrupted as stop:
            stop.kept = f"{len(res['scores'])} of {len(res['seeds'])} episodes were scored; nothing is written"
            raise
    res.update(summarise(episodes), median_seconds=float(np.median(res["seconds"])), max_seconds=float(np.max(res["seconds"])))
    res["markdown"] = (
        f"| seeds | goal | mean score | success rate | s/episode p50 | s/episode max |\n|---|---|---|---|---|---|\n"
        f"| {res['seeds'][0]}..{res['seeds'][-1]} ({len(res['seeds'])}) | {goal} | {res['mean_score']:.3f} | "
        f"{res['success_rate']:.2f} | {res['median_seconds']:.2f} | {res['max_seconds']:.2f} |")
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        write_atomic(out / f"{kind}.json", json.dumps({k: v for k, v in res.items() if k != "markdown"}, indent=2, default=float))
        write_atomic(out / f"{kind}.md", res["markdown"] + "\n")
    return res
