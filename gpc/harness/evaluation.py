"""The closed-loop harness: any controller, many seeds, Diffusion Policy's scoring.

Episodes are split into fixed groups of ``batch`` seeds; a group's episodes step in
lockstep and the controller is called once per decision for the whole group (one batched
policy call, not one per episode). Groups are the same whatever ``--workers`` is, each
episode draws its randomness from its own generator (seeded by the sampling seed and the
env seed), and every process uses the same number of torch threads, so results are
identical for any worker count. Finished episodes stay in their group's batch with their
last observation, which keeps each batched call identical from run to run.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import statistics
import time
from collections import deque
from collections.abc import Callable, Generator, Sequence
from contextlib import closing
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gpc.harness import interrupts
from gpc.harness.episode_rows import add_step, new_row
from gpc.harness.files import write_atomic
from gpc.harness.memory import keep_freed_memory
from gpc.harness.video import futures_panel
from gpc.models.planning.protocols import Controller, Plan
from gpc.models.world_models.pictures import last_step_pictures
from gpc.tasks import get_task, register_task, user_tasks
from gpc.tasks.base import ACTION_KEY, GOAL_KEY, IMAGE_KEY, Task, check_seeds


@dataclass(frozen=True)
class EvalConfig:
    """Which episodes to run and how."""

    seeds: tuple[int, ...]
    task: str  # a registered task's name (gpc.tasks.get_task)
    goal: str = "fixed"
    max_steps: int | None = None  # steps per episode at most (None: the task's episode length)
    batch: int = 25  # episodes per lockstep group (one controller call per decision per group)
    workers: int = 1  # processes; results do not depend on it
    threads: int = 1  # torch threads per process; results do depend on it (float reduction order)
    sampling_seed: int = 0  # with the env seed, seeds each episode's random stream
    video_dir: str | None = None
    videos: int = 0  # MP4s for the first N seeds (with the planned chunk drawn)
    video_size: int = 384
    record: bool = False  # keep every episode's steps in the task's store layout (`gpc record`)
    backend: Any = None  # None: local processes; a ``ray_backend.RayOptions``: actors on a Ray cluster (same results)

    def __post_init__(self) -> None:
        task = get_task(self.task)
        task.check_goal(self.goal)
        if self.max_steps is None:
            object.__setattr__(self, "max_steps", task.max_episode_steps)
        if not self.seeds:
            raise ValueError("--seeds: no seeds given")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError("--seeds: a seed is listed twice")
        check_seeds(min(self.seeds), max(self.seeds), "--seeds")
        for name in ("max_steps", "batch", "workers", "threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} {getattr(self, name)}: must be at least 1")
        if self.videos and not self.video_dir:
            raise ValueError("--videos needs an output directory")

    def groups(self) -> list[tuple[int, ...]]:
        s = self.seeds
        return [s[i : i + self.batch] for i in range(0, len(s), self.batch)]


def episode_generator(sampling_seed: int, env_seed: int) -> torch.Generator:
    """The random stream of one episode: the same for every planner and batch layout (paired runs)."""
    state = np.random.SeedSequence([sampling_seed, env_seed]).generate_state(2, dtype=np.uint32)
    return torch.Generator().manual_seed(int(state[0]) << 32 | int(state[1]))


def run_group(controller: Controller, seeds: Sequence[int], config: EvalConfig) -> dict[str, Any]:
    """Run one lockstep group to the end: per-seed results and the group's call timings."""
    task = get_task(config.task)
    images, sim = IMAGE_KEY in controller.obs_keys or config.record, task.sim_key in controller.obs_keys
    envs = [task.make_env(config.goal) for _ in seeds]
    for env, seed in zip(envs, seeds):
        env.reset(seed=seed)
    gens = [episode_generator(config.sampling_seed, s) for s in seeds]
    if hasattr(controller, "start"):
        controller.start(seeds)
    stats_before = controller.stats() if hasattr(controller, "stats") else {}
    keys = tuple(controller.obs_keys)
    observe = lambda env: task.with_derived(task.observe(env, images, sim), keys)  # noqa: E731
    hist = [deque([observe(env)] * controller.n_obs_steps, maxlen=controller.n_obs_steps) for env in envs]
    rows = [new_row(task, s) for s in seeds]
    done = [False] * len(seeds)
    latencies: list[float] = []
    sizes: list[int] = []  # episodes planned for in each call
    parts: dict[str, float] = {}
    films: dict[int, list[np.ndarray]] = {i: [] for i, s in enumerate(seeds) if config.videos and s in config.seeds[: config.videos]}
    recorders = [_Recorder(task, config.goal) for _ in seeds] if config.record else []
    live = list(range(len(seeds)))
    while live:
        obs = {k: np.stack([np.stack([h[k] for h in hist[i]]) for i in live]) for k in hist[0][0]}
        t0 = time.perf_counter()
        plan = controller.plan(obs, [gens[i] for i in live])
        latencies.append(time.perf_counter() - t0)
        sizes.append(len(live))
        interrupts.check()  # between decisions: the group is given up whole, never half recorded
        for name, sec in plan.seconds.items():
            parts[name] = parts.get(name, 0.0) + sec
        for r, i in enumerate(live):
            env = envs[i]
            for j, action in enumerate(plan.actions[r]):
                if i in films:
                    films[i].extend(_film_frames(task, env, plan, r, j, config.video_size))
                if recorders:
                    recorders[i].add(hist[i][-1], action)
                _, reward, terminated, truncated, info = env.step(np.asarray(action, dtype=np.float64))
                if recorders:
                    recorders[i].after(info)
                ended = add_step(task, rows[i], reward, terminated, truncated, info)
                hist[i].append(observe(env))  # every step: the history is consecutive steps, as in training
                if ended or rows[i]["steps"] >= (config.max_steps or task.max_episode_steps):
                    done[i] = True
                    break
            rows[i]["final_state"] = [float(v) for v in hist[i][-1]["state"]]
        still = [i for i in live if not done[i]]
        if still != live and still and hasattr(controller, "start"):
            controller.start([seeds[i] for i in still])
        live = still  # a finished episode is not planned for: the rest's decisions come sooner
    for i, film in films.items():
        from gpc.harness.video import write_mp4

        assert config.video_dir is not None  # EvalConfig refuses videos without a directory
        write_mp4(film, Path(config.video_dir) / f"seed{seeds[i]}.mp4")
    stats = _counts(controller.stats(), stats_before) if hasattr(controller, "stats") else {}
    return {"episodes": rows, "calls": latencies, "call_sizes": sizes, "group_size": len(seeds), "parts": parts, "stats": stats,
            "n_action_steps": getattr(controller, "n_action_steps", None),
            **({"recordings": [r.arrays() for r in recorders]} if recorders else {})}


class _Recorder:
    """One closed-loop episode in the task's store layout, as its scripted collectors record one: each step holds
    the observation before acting and the action; a recorded key that is not observed (Push-T's ``n_contacts``) is
    the step information of the step that led to the observation (0 at the reset)."""

    def __init__(self, task: Task, goal: str) -> None:
        self.keys = task.record_keys(True, goal)
        self.rows: dict[str, list[np.ndarray]] = {k: [] for k in self.keys}
        self.info: dict[str, Any] = {}

    def add(self, obs: dict[str, np.ndarray], action: np.ndarray) -> None:
        for key in self.keys:
            value = action if key == ACTION_KEY else obs[key] if key in obs else [self.info.get(key, 0)]
            self.rows[key].append(np.asarray(value))

    def after(self, info: dict[str, Any]) -> None:
        self.info = info

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.stack(v).astype(np.uint8 if k == IMAGE_KEY else np.float32) for k, v in self.rows.items()}


def _film_frames(task: Task, env: Any, plan: Plan, i: int, j: int, size: int) -> list[np.ndarray]:
    """Video frames before action ``j`` of episode ``i``: the scene with the planned chunk drawn, and at the
    decision (``j = 0``) the predicted futures held for half a second: overlaid on the scene where the task draws
    state futures (Push-T), else the chosen candidate's and the two best others' last predicted steps as pictures."""
    frame = env.frame(size)
    out = []
    if plan.futures is not None and j == 0 and plan.scores is not None:
        assert plan.chosen is not None
        futures, scores, chosen = plan.futures[i], plan.scores[i], int(plan.chosen[i])
        if task.draw_futures is not None and futures.ndim == 3:  # state futures the task overlays on the scene
            out += [task.draw_futures(frame.copy(), futures, scores, chosen)] * 5
        else:  # the chosen candidate and the two best others, each its predicted last step as a picture
            shown = [chosen] + [int(k) for k in np.argsort(-scores) if k != chosen][:2]
            goal = task.observe(env, False, False).get(GOAL_KEY)
            pictures = last_step_pictures(futures[shown], lambda s, g: task.render_state(s, g, size), goal)
            out += [futures_panel(frame, pictures, [float(scores[k]) for k in shown], 0)] * 5
    out.append(task.draw_plan(frame, plan.chunk[i][j:], len(plan.actions[i]) - j) if task.draw_plan is not None else frame)
    return out


def _counts(after: dict[str, Any], before: dict[str, Any]) -> dict[str, Any]:
    """Numeric counters accrued between two ``stats()`` readings (nested dicts too)."""
    out: dict[str, Any] = {}
    for key, value in after.items():
        if isinstance(value, dict):
            out[key] = _counts(value, before.get(key, {}))
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out[key] = value - before.get(key, 0)
    return out


def _add_counts(total: dict[str, Any], more: dict[str, Any]) -> dict[str, Any]:
    for key, value in more.items():
        total[key] = _add_counts(total.get(key, {}), value) if isinstance(value, dict) else total.get(key, 0) + value
    return total


# ---------------------------------------------------------------------- processes
_WORKER: dict[str, Any] = {}


def _init_worker(factory: Callable[[], Controller], threads: int, worker: bool = False, tasks: Sequence[Task] = ()) -> None:
    if worker:
        interrupts.ignore_in_worker()
        keep_freed_memory()  # a spawned process starts with glibc's defaults again
    for task in tasks:  # tasks the parent registered by hand
        register_task(task)
    torch.set_num_threads(threads)
    try:
        _WORKER["controller"] = factory()
    except Exception as exc:  # raised by the first job instead: a failing initializer makes a Pool respawn forever
        _WORKER["error"] = exc


def _work(args: tuple[tuple[int, ...], EvalConfig]) -> dict[str, Any]:
    seeds, config = args
    if "error" in _WORKER:
        raise _WORKER["error"]
    with torch.no_grad():  # not inference_mode: gradient planners re-enable autograd inside
        return run_group(_WORKER["controller"], seeds, config)


def evaluate(factory: Callable[[], Controller], config: EvalConfig,
             on_group: Callable[[dict[str, Any]], None] | None = None,
             finished: Sequence[dict[str, Any]] = ()) -> dict[str, Any]:
    """Run every seed; ``factory`` (picklable) builds the controller inside each process.

    ``finished``: groups an earlier, stopped run of the same evaluation completed (``gpc.harness.results``);
    their seeds are not run again. A stop (``Interrupted``) comes between two groups' decisions.
    """
    t0 = time.perf_counter()
    have = {tuple(r["seed"] for r in g["episodes"]) for g in finished}
    jobs = [(g, config) for g in config.groups() if tuple(int(s) for s in g) not in have]
    groups: list[dict[str, Any]] = list(finished)
    if jobs:
        with closing(map_groups(factory, jobs, config)) as done:  # a stop between groups ends the workers now
            for group in done:
                groups.append(group)
                if on_group:
                    on_group(group)
                interrupts.check()
    result = summarize(groups, time.perf_counter() - t0, config)
    summary = getattr(factory, "summary", None)  # a PlannerRecipe says what it built
    if callable(summary):
        result["controller"] = summary()
    return result


def map_groups(factory: Callable[[], Controller], jobs: list, config: EvalConfig) -> Generator[dict[str, Any], None, None]:
    """Each ``(seeds, config)`` job run as one lockstep group (``run_group``), in order, in ``config.workers`` processes
    (Ray actors with ``config.backend``)."""
    if config.backend is not None:
        from gpc.harness import ray_backend

        yield from ray_backend.map_groups(factory, jobs, config)
        return
    if config.workers == 1 or len(jobs) == 1:
        previous = torch.get_num_threads()
        _init_worker(factory, config.threads)
        try:
            yield from map(_work, jobs)
        finally:
            torch.set_num_threads(previous)
        return
    ctx = mp.get_context("spawn")
    with ctx.Pool(min(config.workers, len(jobs)), initializer=_init_worker, initargs=(factory, config.threads, True, user_tasks())) as pool:
        yield from interrupts.polled(pool, pool.imap(_work, jobs, chunksize=1))


def summarize(groups: list[dict[str, Any]], wall: float, config: EvalConfig) -> dict[str, Any]:
    """Mean score, success rate and decision latency (per batched call and per episode decision)."""
    rows = sorted((r for g in groups for r in g["episodes"]), key=lambda r: r["seed"])
    calls = [c for g in groups for c in g["calls"]]
    # Groups saved before finished episodes were dropped from the calls (a resumed run reads them) planned for all.
    per_episode = [c / n for g in groups for c, n in zip(g["calls"], g.get("call_sizes", [g["group_size"]] * len(g["calls"])))]
    parts: dict[str, float] = {}
    for g in groups:
        for name, sec in g["parts"].items():
            parts[name] = parts.get(name, 0.0) + sec
    total = sum(parts.values()) or 1.0
    stats: dict[str, Any] = {}
    for g in groups:
        _add_counts(stats, g.get("stats", {}))
    return {
        "config": asdict(config),
        "n_action_steps": next((g["n_action_steps"] for g in groups if g.get("n_action_steps") is not None), None),
        "episodes": rows,
        "mean_score": float(np.mean([r["score"] for r in rows])),
        "success_rate": float(np.mean([r["success"] for r in rows])),
        "call_latency_s": _latency(calls),
        "decision_latency_s": _latency(per_episode),
        "time_share": {k: v / total for k, v in parts.items()},
        **({"controller_stats": stats} if stats else {}),
        "wall_s": wall,
    }


def _latency(values: list[float]) -> dict[str, float]:
    if not values:
        return {"mean": float("nan"), "p50": float("nan"), "p95": float("nan")}
    return {"mean": float(statistics.fmean(values)), "p50": float(np.percentile(values, 50)),
            "p95": float(np.percentile(values, 95))}


def write_results(result: dict[str, Any], out: Path, title: str) -> None:
    """``episodes.json`` (per seed), ``summary.json`` and ``summary.md`` in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "episodes.json", json.dumps(result["episodes"], indent=1))
    write_atomic(out / "summary.json", json.dumps({k: v for k, v in result.items() if k != "episodes"}, indent=2))
    c, d = result["call_latency_s"], result["decision_latency_s"]
    seeds = result["config"]["seeds"]
    md = (
        f"# {title}\n\n| seeds | mean score | success rate | s/decision (per episode) mean / p50 / p95 "
        f"| s/batched call mean / p50 / p95 | wall s |\n|---|---|---|---|---|---|\n"
        f"| {seeds[0]}..{seeds[-1]} ({len(seeds)}) | {result['mean_score']:.3f} | {result['success_rate']:.2f} | "
        f"{d['mean']:.4f} / {d['p50']:.4f} / {d['p95']:.4f} | {c['mean']:.3f} / {c['p50']:.3f} / {c['p95']:.3f} | "
        f"{result['wall_s']:.0f} |\n"
    )
    stats = result.get("controller_stats", {})
    if "fell_back" in stats:
        md += (f"\nReward queries: {stats.get('queries', 0)} ({stats.get('cache_hits', 0)} answered from the cache); "
               f"decisions that fell back: {stats['fell_back']} of {stats.get('decisions', 0)} "
               f"({', '.join(f'{k} {v}' for k, v in stats.get('fallbacks', {}).items() if v) or 'none'}).\n")
    write_atomic(out / "summary.md", md)


def write_spread(results: list[dict[str, Any]], out: Path, title: str, run: Any = None) -> dict[str, Any]:
    """Mean and spread of the score over several sampling seeds (same env seeds): ``summary.md/json``;
    ``run``: the spread's identity, recorded so a later command knows what the folder holds."""
    scores = np.array([r["mean_score"] for r in results])
    success = np.array([r["success_rate"] for r in results])
    agg = {
        "sampling_seeds": [r["config"]["sampling_seed"] for r in results],
        "mean_scores": scores.tolist(), "success_rates": success.tolist(),
        "mean_score": float(scores.mean()), "score_std": float(scores.std(ddof=1)) if len(scores) > 1 else 0.0,
        "score_range": [float(scores.min()), float(scores.max())],
        "success_rate": float(success.mean()),
        "decision_latency_s_p50": float(np.median([r["decision_latency_s"]["p50"] for r in results])),
        **({"run": run} if run is not None else {}),
    }
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "summary.json", json.dumps(agg, indent=2))
    seeds = results[0]["config"]["seeds"]
    rows = "".join(f"| {s} | {m:.3f} | {r:.2f} |\n" for s, m, r in zip(agg["sampling_seeds"], scores, success))
    write_atomic(out / "summary.md",
        f"# {title}\n\nEnv seeds {seeds[0]}..{seeds[-1]} ({len(seeds)}), one row per sampling seed.\n\n"
        f"| sampling seed | mean score | success rate |\n|---|---|---|\n{rows}"
        f"| **all** | **{agg['mean_score']:.3f} +- {agg['score_std']:.3f}** (range {agg['score_range'][0]:.3f}-"
        f"{agg['score_range'][1]:.3f}) | {agg['success_rate']:.2f} |\n\nMedian seconds per decision (per episode): "
        f"{agg['decision_latency_s_p50']:.4f}\n"
    )
    return agg
