"""What `gpc data`, `gpc check-sim` and `gpc eval-expert` print (the figures come from ``gpc.harness``)."""

from __future__ import annotations

import json
from pathlib import Path

from rich.console import Console
from rich.table import Table

_console = Console()


def parse_seeds(text: str, option: str = "--seeds") -> list[int]:
    """``START:STOP`` (stop excluded) or a comma-separated list."""
    from gpc.tasks.base import check_seeds

    try:
        if ":" in text:
            start, stop = (int(v) for v in text.split(":"))
            bounds = (start, stop - 1)
        else:
            seeds = [int(v) for v in text.split(",")]
            bounds = (min(seeds), max(seeds))
    except ValueError:
        raise ValueError(f"{option} {text!r}: use START:STOP or a comma-separated list of integers") from None
    if bounds[1] < bounds[0]:
        raise ValueError(f"{option} {text!r}: needs at least one seed (STOP is excluded)")
    check_seeds(*bounds, f"{option} {text}")  # before a range of 10**23 seeds is made
    return list(range(start, stop)) if ":" in text else seeds


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
    for name in ("contact_fraction", "pose_coverage"):
        if name in info:
            _console.print(f"{name}: {info[name]:.3f}")
    for note in ("task_note", "score_note"):
        if note in info:
            _console.print(info[note])
    if info["attrs"]:
        _console.print("provenance: " + json.dumps(info["attrs"]))


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


def collector_report(task: str, kind: str, seeds: list[int], goal: str, out: Path | None) -> str:
    """A scripted collector's closed-loop score as a Markdown row (and JSON + Markdown files in ``out``)."""
    from rich.progress import Progress

    from gpc.harness.collection import evaluate_collector

    with Progress(transient=True) as bar:
        tid = bar.add_task(f"{kind} episodes", total=len(seeds))
        res = evaluate_collector(task, kind, seeds, goal=goal, on_episode=lambda _: bar.advance(tid), out=out)
    return str(res["markdown"])


def print_policy(info: dict) -> None:
    """``gpc inspect``: one table of the policy's settings, one of its observations and normaliser ranges."""
    head = Table(title=f"{info['path']} ({info['format']}{', ' + info['generation'] if info.get('generation') else ''})")
    head.add_column("setting")
    head.add_column("value")
    rows = [("task", info["task"]), ("observation type", info["obs_type"]), ("action dim", info["action_dim"]),
            ("horizon / obs steps / action steps", f"{info['horizon']} / {info['n_obs_steps']} / {info['n_action_steps']}"),
            ("executed", info["executed"]),
            ("noise", ", ".join(f"{k} {v}" for k, v in info["noise"].items())),
            ("sampler", f"{info['sampler']['method']} {info['sampler']['steps']} steps ({info['sampler']['spacing']})"),
            ("parameters", f"{info['parameters']:,}")]
    for name in ("policy_class", "weights"):
        if name in info:
            rows.append((name.replace("_", " "), info[name]))
    for name, value in rows:
        head.add_row(name, str(value))
    _console.print(head)
    if info.get("features"):
        feats = Table(title="features as the checkpoint names them")
        for col in ("feature", "shape", "normalisation", "from"):
            feats.add_column(col)
        for name, f in info["features"].items():
            feats.add_row(name, str(tuple(f.get("shape", []))), str(f.get("normalization", "")), str(f.get("from", "")))
        _console.print(feats)
    obs = Table(title="what it reads and writes (gpc keys), with the normaliser's [-1, 1] in raw units")
    for col in ("key", "shape", "low", "high"):
        obs.add_column(col)
    for key, r in info["normalizer_ranges"].items():
        shape = info["observations"].get(key, [info["action_dim"]] if key == "action" else [r["size"]])
        more = " ..." if r["size"] > len(r["low"]) else ""
        obs.add_row(key, str(tuple(shape)), ", ".join(f"{v:g}" for v in r["low"]) + more,
                    ", ".join(f"{v:g}" for v in r["high"]) + more)
    _console.print(obs)
