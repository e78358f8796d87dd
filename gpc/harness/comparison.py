"""Paired comparisons of closed-loop results: each planner against BC on the same seeds.

Every planner draws its policy proposals from the same per-episode random stream as BC,
so the per-seed difference isolates planning. The table reports the mean difference with
a paired 95% confidence interval (Student t over seeds) and, given the ground-truth
simulator's result, the share of the BC-to-ceiling gap a planner closes.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from gpc.datasets.errors import DataError
from gpc.harness.files import check_file_out, read_json, write_atomic, write_bytes_atomic
from gpc.harness.identity import EPISODE_SETTINGS, controller_of, episode_settings, first_difference
from gpc.harness.ownership import adopt
from gpc.tasks import DEFAULT_TASK, get_task

COMPARISON = "gpc compare"  # the kind its JSON records: what --out may replace
COMPARISON_SUFFIXES = (".md", ".json", ".png")  # the files --out names


def t_quantile(p: float, dof: int) -> float:
    """Student t quantile by a Cornish-Fisher expansion of the normal one (error < 1e-3 for dof >= 5)."""
    z = _normal_quantile(p)
    v = float(dof)
    return (z + (z**3 + z) / (4 * v) + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * v**2)
            + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * v**3))


def _normal_quantile(p: float) -> float:
    lo, hi = -10.0, 10.0
    for _ in range(100):  # bisection on the normal CDF
        mid = (lo + hi) / 2
        if 0.5 * (1 + math.erf(mid / math.sqrt(2))) < p:
            lo = mid
        else:
            hi = mid
    return (lo + hi) / 2


def paired_interval(diffs: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """Mean of per-seed differences and its two-sided ``level`` confidence interval."""
    n = len(diffs)
    mean = float(np.mean(diffs))
    if n < 2:
        return mean, float("nan"), float("nan")
    half = t_quantile(0.5 + level / 2, n - 1) * float(np.std(diffs, ddof=1)) / math.sqrt(n)
    return mean, mean - half, mean + half


def load_run(path: Path) -> dict[str, Any]:
    """A `gpc eval` output directory (or its first sampling seed's) as summary + per-seed rows.

    ``A+B``: one controller evaluated on two seed ranges (two ``gpc eval`` runs) counts as one
    run over the union of their seeds, so more seeds can be added without re-running the first;
    its latencies and time shares are the parts' figures weighted by their seeds.
    """
    if not Path(path).exists() and "+" in str(path):
        return _joined([load_run(Path(p)) for p in str(path).split("+")], str(path))
    path = Path(path)
    for d in (path, path / "sampling-seed-0"):
        if (d / "episodes.json").is_file() and (d / "summary.json").is_file():
            summary = _checked_summary(read_json(d / "summary.json"), d / "summary.json")
            rows = _checked_rows(read_json(d / "episodes.json"), d / "episodes.json")
            label = summary.get("controller", {}).get("controller", d.name)
            return {"path": str(path), "label": label, "summary": summary, "rows": rows}
    raise DataError(f"{path}: no gpc eval results here (episodes.json, summary.json); run `gpc eval ... --out {path}` first")


def _checked_summary(summary: Any, path: Path) -> dict[str, Any]:
    """The fields a comparison reads, of the types it reads them as (a damaged file is named, not a traceback)."""
    if not isinstance(summary, dict):
        raise DataError(f"{path}: not a gpc eval summary (not a JSON object)")
    for key in ("config", "decision_latency_s", "call_latency_s"):
        if not isinstance(summary.get(key), dict):
            raise DataError(f"{path}: not a gpc eval summary (no {key!r} object)")
    for key in ("decision_latency_s", "call_latency_s"):
        if not _finite(summary[key].get("p50")):
            raise DataError(f"{path}: {key} has no finite number p50 ({summary[key].get('p50')!r})")
    for key, share in summary.get("time_share", {}).items() if isinstance(summary.get("time_share"), dict) else ():
        if not _finite(share):
            raise DataError(f"{path}: time_share {key!r} is {share!r}, not a finite number")
    if not isinstance(summary.get("controller", {}), dict) or not isinstance(summary.get("time_share", {}), dict):
        raise DataError(f"{path}: controller and time_share must be JSON objects")
    return summary


def _checked_rows(episodes: Any, path: Path) -> dict[int, dict[str, Any]]:
    if not isinstance(episodes, list) or not all(isinstance(r, dict) for r in episodes):
        raise DataError(f"{path}: not gpc eval episodes (a JSON list of objects)")
    for i, r in enumerate(episodes):
        if not (isinstance(r.get("seed"), int) and _number(r.get("score")) and _number(r.get("success"), bool)):
            raise DataError(f"{path}: episode {i} needs an integer seed, a number score and a true/false success")
        if not _finite(r["score"]):  # JSON's NaN / Infinity: no mean, interval or plot can hold it
            raise DataError(f"{path}: episode {i} (seed {r['seed']}) has score {r['score']}; a comparison needs a finite score")
    return {r["seed"]: r for r in episodes}


def _number(x: Any, *also: type) -> bool:
    return isinstance(x, also) or (isinstance(x, (int, float)) and not isinstance(x, bool))


def _finite(x: Any) -> bool:
    return _number(x) and math.isfinite(x)


def settings(summary: dict[str, Any]) -> dict[str, Any]:
    """The settings a run's per-seed scores depend on, besides its controller (``identity.EPISODE_SETTINGS``)."""
    return episode_settings(summary)


def check_comparable(run: dict[str, Any], base: dict[str, Any], what: str = "the baseline") -> None:
    """Refuse to pair runs whose episodes differ (a setting a run predates is not checked); their controllers may differ."""
    mine, theirs = settings(run["summary"]), settings(base["summary"])
    for key, name in EPISODE_SETTINGS:
        if mine[key] is not None and theirs[key] is not None and mine[key] != theirs[key]:
            raise DataError(f"{run['path']}: {name} {mine[key]} differs from {what}'s {theirs[key]} ({base['path']}); "
                            "only runs with the same settings pair seed by seed")


def _joined(parts: list[dict[str, Any]], path: str) -> dict[str, Any]:
    first = parts[0]
    rows: dict[int, Any] = {}
    for part in parts:
        mine, theirs = controller_of(part["summary"]), controller_of(first["summary"])
        mine, theirs = ({k: v for k, v in x.items() if k in mine and k in theirs} for x in (mine, theirs))  # (older parts)
        if mine != theirs:  # its whole identity but the seeds: sampler, reward, checkpoints' contents included
            raise DataError(f"{path}: {part['path']} ran another controller than {first['path']} "
                            f"({first_difference(theirs, mine)}); join runs of one controller")
        check_comparable(part, first, "its first part")
        twice = sorted(set(rows) & set(part["rows"]))
        if twice:
            raise DataError(f"{path}: seed(s) {twice[:5]} appear in more than one part")
        rows.update(part["rows"])
    weights = [len(p["rows"]) / len(rows) for p in parts]

    def mix(get: Any) -> float:
        return float(sum(w * get(p["summary"]) for w, p in zip(weights, parts)))

    shares = {k for p in parts for k in p["summary"].get("time_share", {})}
    summary = {**first["summary"],
               "decision_latency_s": {"p50": mix(lambda s: s["decision_latency_s"]["p50"])},
               "call_latency_s": {"p50": mix(lambda s: s["call_latency_s"]["p50"])},
               "time_share": {k: mix(lambda s, k=k: s.get("time_share", {}).get(k, 0.0)) for k in sorted(shares)}}
    return {"path": path, "label": first["label"], "summary": summary, "rows": rows}


def compare_runs(baseline: Path, runs: list[Path], ceiling: Path | None = None,
                 seeds: list[int] | None = None) -> dict[str, Any]:
    """One row per run: score, success, paired differences to BC, gap closed, seconds per decision.

    ``seeds`` pairs on those seeds alone (every run must hold them): a protocol of fewer seeds (Table III's 50)
    read from runs that hold more, without evaluating them again."""
    base = load_run(baseline)
    if seeds is not None:
        lacking = sorted(set(seeds) - set(base["rows"]))
        if lacking:
            raise DataError(f"{base['path']}: the baseline lacks seed(s) {lacking[:5]} of --seeds")
    seeds = sorted(set(seeds)) if seeds is not None else sorted(base["rows"])
    top = load_run(ceiling) if ceiling else None
    table = []
    for run in [base] + [load_run(r) for r in runs if Path(r) != Path(baseline)] + ([top] if top else []):
        check_comparable(run, base)
    if top is not None and any(s not in top["rows"] for s in seeds):
        missing = [s for s in seeds if s not in top["rows"]]
        raise DataError(f"{top['path']}: the --ceiling lacks seed(s) {missing[:5]} of the baseline; compare runs on the same seeds")
    for run in [base] + [load_run(r) for r in runs if Path(r) != Path(baseline)]:
        missing = [s for s in seeds if s not in run["rows"]]
        if missing:
            raise DataError(f"{run['path']}: lacks seed(s) {missing[:5]} of the baseline; compare runs on the same seeds")
        score = np.array([run["rows"][s]["score"] for s in seeds])
        success = np.array([float(run["rows"][s]["success"]) for s in seeds])
        b_score = np.array([base["rows"][s]["score"] for s in seeds])
        b_success = np.array([float(base["rows"][s]["success"]) for s in seeds])
        d, lo, hi = paired_interval(score - b_score)
        ds, slo, shi = paired_interval(success - b_success)
        row = {
            "label": run["label"], "path": run["path"], "seeds": len(seeds),
            "score": float(score.mean()), "success": float(success.mean()),
            "score_diff": d, "score_ci": [lo, hi], "success_diff": ds, "success_ci": [slo, shi],
            "s_per_decision": run["summary"]["decision_latency_s"]["p50"],
            "s_per_call": run["summary"]["call_latency_s"]["p50"],
            "time_share": run["summary"].get("time_share", {}),
        }
        if top is not None:
            t_score = float(np.mean([top["rows"][s]["score"] for s in seeds]))
            t_success = float(np.mean([float(top["rows"][s]["success"]) for s in seeds]))
            gap, gap_s = t_score - b_score.mean(), t_success - b_success.mean()
            row["gap_closed_score"] = float(d / gap) if gap > 0 else float("nan")
            row["gap_closed_success"] = float(ds / gap_s) if gap_s > 0 else float("nan")
        table.append(row)
    _tell_apart(table)
    return {"baseline": str(baseline), "ceiling": str(ceiling) if ceiling else None, "task": settings(base["summary"])["task"],
            "seeds": [seeds[0], seeds[-1]], "rows": table}


def _tell_apart(rows: list[dict[str, Any]]) -> None:
    """Two runs of one controller (e.g. with two world models) would share a label: name each by its results
    folder, or by its own folder's name where they share the results folder."""
    labels = [r["label"] for r in rows]
    for label in set(labels):
        group = [r for r in rows[1:] if r["label"] == label]  # the baseline keeps its label (the paper's column keys on it)
        if labels.count(label) < 2 or not group:
            continue
        paths = [Path(r["path"].split("+")[0]) for r in group]
        names = [p.parent.name for p in paths]
        if len(set(names)) < len(names):
            names = [p.name for p in paths]
        for r, name in zip(group, names):
            r["label"] = f"{label} ({name})"


def _pct(x: float) -> str:
    return "n/a" if x != x else f"{100 * x:.0f}%"


def check_compare_out(out: Path) -> None:
    """``--out`` names a .md file whose .md, .json and .png are new or gpc's (an earlier comparison's: never an
    evaluation's ``summary.md`` or a file of the user's; ``gpc.harness.ownership``)."""
    check_file_out(out, ".md", beside=COMPARISON_SUFFIXES[1:], proof=_older_comparison)
    for path in (out.with_suffix(s) for s in COMPARISON_SUFFIXES):  # gpc's, and a comparison (not a summary.md)
        if path.is_file() and not _comparison(path):
            raise DataError(f"{path}: exists and is not a comparison gpc wrote; choose another --out")


def adopt_older(out: Path) -> None:
    """Record an older gpc's comparison at ``out`` as gpc's (it kept no ownership record), before it is replaced."""
    adopt([out.with_suffix(s) for s in COMPARISON_SUFFIXES], _older_comparison)


def _older_comparison(path: Path) -> bool:
    """A comparison an older gpc wrote: its ``.json`` says so (``kind``, or the rows and baseline of older ones)."""
    held = json.loads(path.with_suffix(".json").read_text())
    return isinstance(held, dict) and (held.get("kind") == COMPARISON or {"baseline", "rows"} <= set(held))


def _comparison(path: Path) -> bool:
    try:
        return _older_comparison(path)
    except (OSError, ValueError):
        return False


def write_comparison(table: dict[str, Any], out: Path, title: str, paper: str | None = None) -> str:
    """Markdown (and JSON beside it) of a ``compare_runs`` table; returns the Markdown.

    ``paper``: one of the baseline task's reference tables (``Task.references``), shown beside ours.
    """
    figures: Mapping[str, float] = {}
    if paper is not None:
        references = get_task(table["task"] or DEFAULT_TASK).references
        if paper not in references:
            raise ValueError(f"--paper {paper!r}: task {table['task']} has the reference tables {', '.join(references) or 'none'}")
        figures = references[paper]
    head = "| controller | " + ("paper | " if figures else "") + (
        "score | success | score - BC [95% CI] | success - BC [95% CI] | gap closed (score / success) "
        "| s/decision | time share |")
    span = f" ({table['seeds'][0]}-{table['seeds'][1]})" if "seeds" in table else ""
    lines = [f"# {title}", "", f"Paired over {table['rows'][0]['seeds']} seeds{span}; baseline {table['baseline']}"
             + (f"; ceiling {table['ceiling']}" if table["ceiling"] else "") + ".", "", head,
             "|" + "---|" * (head.count("|") - 1)]
    for r in table["rows"]:
        share = ", ".join(f"{k} {v:.0%}" for k, v in sorted(r["time_share"].items(), key=lambda kv: -kv[1]))
        gap = f"{_pct(r.get('gap_closed_score', float('nan')))} / {_pct(r.get('gap_closed_success', float('nan')))}"
        lines.append(
            f"| {r['label']} | " + (f"{figures.get(r['label'], float('nan')):.3f} | ".replace("nan", "-") if figures else "")
            + f"{r['score']:.3f} | {r['success']:.2f} | {r['score_diff']:+.3f} [{r['score_ci'][0]:+.3f}, {r['score_ci'][1]:+.3f}] "
            f"| {r['success_diff']:+.2f} [{r['success_ci'][0]:+.2f}, {r['success_ci'][1]:+.2f}] | {gap} "
            f"| {r['s_per_decision']:.3f} | {share} |"
        )
    md = "\n".join(lines) + "\n\ns/decision: median seconds per decision per episode (a lockstep call divided by its episodes).\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out, md)
    write_atomic(out.with_suffix(".json"), json.dumps({"kind": COMPARISON, **table}, indent=2))
    return md


def plot_comparison(table: dict[str, Any], path: Path, size: tuple[int, int] = (900, 560)) -> Path:
    """PNG: mean score against seconds per decision (log axis), one labelled point per controller."""
    png = render_plot(table, path, size)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(path, png)
    return path


def render_plot(table: dict[str, Any], path: Path, size: tuple[int, int] = (900, 560)) -> bytes:
    """``plot_comparison``'s PNG, in memory (a comparison is made whole before its first file is written)."""
    import cv2

    rows = [r for r in table["rows"] if r["s_per_decision"] > 0]
    if not rows:
        raise DataError(f"{path}: no controller with a positive decision time to plot")
    w, h = size
    left, right, top, bottom = 70, 30, 30, 60
    img = np.full((h, w, 3), 255, np.uint8)
    xs = np.log10([r["s_per_decision"] for r in rows])
    x_lo, x_hi = float(np.floor(xs.min())), float(np.ceil(xs.max() + 1e-9))
    x_hi = max(x_hi, x_lo + 1)
    y_lo = min(0.0, float(np.floor(min(r["score"] for r in rows) * 10) / 10))

    def px(x: float, y: float) -> tuple[int, int]:
        return (int(left + (x - x_lo) / (x_hi - x_lo) * (w - left - right)),
                int(h - bottom - (y - y_lo) / (1.0 - y_lo) * (h - top - bottom)))

    black, grey, font = (0, 0, 0), (200, 200, 200), cv2.FONT_HERSHEY_SIMPLEX
    for e in range(int(x_lo), int(x_hi) + 1):
        cv2.line(img, px(e, y_lo), px(e, 1.0), grey, 1)
        cv2.putText(img, f"{10.0 ** e:g} s", (px(e, y_lo)[0] - 20, h - bottom + 22), font, 0.45, black, 1, cv2.LINE_AA)
    for y in np.arange(y_lo, 1.0001, 0.1):
        cv2.line(img, px(x_lo, y), px(x_hi, y), grey, 1)
        cv2.putText(img, f"{y:.1f}", (20, px(x_lo, y)[1] + 5), font, 0.45, black, 1, cv2.LINE_AA)
    cv2.putText(img, "seconds per decision (per episode, log scale)", (w // 2 - 190, h - 12), font, 0.5, black, 1, cv2.LINE_AA)
    cv2.putText(img, "mean score", (5, 18), font, 0.5, black, 1, cv2.LINE_AA)
    for r, x in zip(rows, xs):
        p = px(float(x), r["score"])
        cv2.circle(img, p, 5, (200, 40, 40) if r["label"] == "bc" else (40, 90, 200), -1, cv2.LINE_AA)
        cv2.putText(img, r["label"], (p[0] + 7, p[1] - 6), font, 0.42, black, 1, cv2.LINE_AA)
    ok, png = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    if not ok:
        raise DataError(f"{path}: OpenCV could not encode the plot")
    return png.tobytes()
