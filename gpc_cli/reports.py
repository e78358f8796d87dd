"""What `gpc data`, `gpc check-sim` and `gpc eval-expert` compute and print."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from datasets.errors import DataError
from datasets.store import EpisodeStore
from gpc_cli.video import write_mp4
from tasks import get_task

_console = Console()


def parse_seeds(text: str, option: str = "--seeds") -> list[int]:
    """``START:STOP`` (stop excluded) or a comma-separated list."""
    try:
        if ":" in text:
            start, stop = (int(v) for v in text.split(":"))
            seeds = list(range(start, stop))
        else:
            seeds = [int(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"{option} {text!r}: use START:STOP or a comma-separated list of integers") from None
    if not seeds or min(seeds) < 0:
        raise ValueError(f"{option} {text!r}: needs at least one non-negative seed")
    return seeds


def _task_of(store: EpisodeStore) -> str:
    """Our stores name their task; Diffusion Policy's Push-T stores are recognised by their keys."""
    return store.attrs.get("task", "pusht" if "state" in store.keys else "")


def describe_store(path: Path) -> dict:
    store = EpisodeStore.open(path)
    store.check_finite([k for k in store.keys if k != "img"])
    lengths = np.diff(np.concatenate([[0], store.episode_ends]))
    info: dict = {
        "path": str(path), "episodes": store.n_episodes, "steps": store.n_steps,
        "keys": {k: {"shape": list(store.shape(k)), "dtype": str(store.array(k).dtype)} for k in store.keys},
        "episode_length": _stats(lengths) if store.n_episodes else {},
        "attrs": store.attrs,
    }
    if "n_contacts" in store.keys and store.n_steps:
        info["contact_fraction"] = float((store.read("n_contacts")[:, 0] > 0).mean())
    scores = store.episode_scores()
    task_name = _task_of(store)
    if (scores is None or not np.all(np.isfinite(scores))) and task_name and "state" in store.keys and store.n_episodes:
        scores = get_task(task_name).episode_scores(store.read("state"), store.episode_ends)
    if scores is not None and store.n_episodes:
        info["score"] = {**_stats(scores), "success_rate": float(np.mean(scores >= 1.0))}
    if task_name and "state" in store.keys and store.n_steps:
        info["block_pose_coverage"] = float(get_task(task_name).pose_coverage(store.read("state")))
    return info


def _stats(values: np.ndarray) -> dict:
    v = np.asarray(values, dtype=np.float64)
    return {"mean": float(v.mean()), "min": float(v.min()), "p50": float(np.median(v)), "max": float(v.max())}


def print_description(info: dict) -> None:
    table = Table(title=f"{info['path']}: {info['episodes']} episodes, {info['steps']} steps")
    table.add_column("key")
    table.add_column("shape")
    table.add_column("dtype")
    for key, meta in info["keys"].items():
        table.add_row(key, str(tuple(meta["shape"])), meta["dtype"])
    _console.print(table)
    for name in ("episode_length", "score"):
        if info.get(name):
            _console.print(f"{name}: " + ", ".join(f"{k} {v:.3f}" for k, v in info[name].items()))
    for name in ("contact_fraction", "block_pose_coverage"):
        if name in info:
            _console.print(f"{name}: {info[name]:.3f}")
    if info["attrs"]:
        _console.print("provenance: " + json.dumps(info["attrs"]))


def episode_video(path: Path, episode: int, out: Path | None) -> Path:
    store = EpisodeStore.open(path)
    ep = store.episode(episode, [k for k in ("img", "state") if k in store.keys] or None)
    out = out or path.with_name(f"{path.name.removesuffix('.zarr')}_ep{episode}.mp4")
    if "img" in ep:
        frames = np.clip(np.rint(ep["img"]), 0, 255).astype(np.uint8)
        write_mp4(frames, out, scale=4)
    elif "state" in ep and _task_of(store):
        task = get_task(_task_of(store))
        write_mp4((task.render_state(s, size=384) for s in ep["state"]), out)
    else:
        raise DataError(f"{path}: episode {episode} has neither img nor state to draw")
    return out


def check_simulator(path: Path, episodes: int = 0, frame_stride: int = 10) -> dict:
    from tasks.pusht import fidelity

    store = EpisodeStore.open(path)
    for key in ("state", "action"):
        store.array(key)
    n_eps = store.n_episodes if episodes == 0 else min(episodes, store.n_episodes)
    stop = int(store.episode_ends[n_eps - 1])
    states, actions = store.read("state", 0, stop), store.read("action", 0, stop)
    store.check_finite(["state", "action"])
    rep = fidelity.replay(states, actions, store.episode_ends[:n_eps])
    gaps = fidelity.restore_divergence(states, actions, store.episode_ends[:n_eps])
    out = {"data": str(path), "replay": rep.summary(),
           "restore": {"samples": int(gaps.size), "horizon": 16, "exact_fraction": float(np.mean(gaps == 0)),
                       "gap_px_p50": float(np.median(gaps)), "gap_px_p95": float(np.percentile(gaps, 95)),
                       "gap_px_max": float(gaps.max())}}
    if "img" in store.keys:
        idx = np.arange(0, stop, frame_stride)
        imgs = np.asarray(store.array("img").oindex[idx])  # each chunk decompressed once
        mad = fidelity.render_errors(states[idx], imgs)
        out["render"] = {"frames": int(idx.size), "mad_mean": float(mad.mean()),
                         "mad_p99": float(np.percentile(mad, 99)), "mad_max": float(mad.max())}
    return out


def print_check(report: dict) -> None:
    r = report["replay"]
    _console.print(f"[bold]replay[/] {r['episodes']} episodes of {report['data']}: "
                   f"{100 * r['fraction_within']:.1f}% within {r['tolerance']['px']} px and "
                   f"{r['tolerance']['deg']} deg over the whole episode")
    table = Table("percentile", "max block position error (px)", "max block angle error (deg)")
    for q in r["pos_err_px_percentiles"]:
        table.add_row(q, f"{r['pos_err_px_percentiles'][q]:.2e}", f"{r['ang_err_deg_percentiles'][q]:.2e}")
    _console.print(table)
    if r["episodes_outside"]:
        _console.print(f"episodes outside tolerance: {r['episodes_outside']}")
    g = report["restore"]
    _console.print(f"[bold]restore[/] {g['samples']} snapshots, {g['horizon']} steps on: {100 * g['exact_fraction']:.0f}% "
                   f"bit-exact; block gap p50 {g['gap_px_p50']:.1e}, p95 {g['gap_px_p95']:.1e}, max {g['gap_px_max']:.1e} px")
    if "render" in report:
        m = report["render"]
        _console.print(f"[bold]render[/] {m['frames']} frames: mean abs difference {m['mad_mean']:.3f} "
                       f"(p99 {m['mad_p99']:.3f}, max {m['mad_max']:.3f}) of 255")


def expert_report(seeds: list[int], goal: str, out: Path | None) -> str:
    from tasks.pusht.expert import evaluate_expert

    from rich.progress import Progress

    with Progress(transient=True) as bar:
        tid = bar.add_task("expert episodes", total=len(seeds))
        res = evaluate_expert(seeds, goal=goal, on_episode=lambda _: bar.advance(tid))
    md = (
        f"| seeds | goal | mean score | success rate | s/episode p50 | s/episode max |\n|---|---|---|---|---|---|\n"
        f"| {seeds[0]}..{seeds[-1]} ({len(seeds)}) | {goal} | {res['mean_score']:.3f} | {res['success_rate']:.2f} | "
        f"{np.median(res['seconds']):.2f} | {np.max(res['seconds']):.2f} |"
    )
    if out:
        out.mkdir(parents=True, exist_ok=True)
        (out / "expert.json").write_text(json.dumps(res, indent=2, default=float))
        (out / "expert.md").write_text(md + "\n")
    return md
