"""Timing and reporting shared by the benchmarks: medians of repeats, tables, the latest rows in docs/benchmarks.md."""

from __future__ import annotations

import platform
import statistics
import time
from collections.abc import Callable
from datetime import date
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table


def median_seconds(fn: Callable[[], object], number: int, repeat: int = 5) -> float:
    """Median over ``repeat`` runs of the mean time of ``number`` calls."""
    from gpc.harness.memory import keep_freed_memory

    keep_freed_memory()  # time what a gpc process runs: gpc keeps freed memory (gpc.harness.memory, bench_memory)
    fn()  # warm-up
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        runs.append((time.perf_counter() - t0) / number)
    return statistics.median(runs)


def machine() -> str:
    """The machine as far as the figures depend on it: vector units and bf16 (emulated bf16 is 4-6x slower)."""
    import os

    import torch

    from gpc.models.networks.precision import native_bf16

    bf16 = "" if native_bf16("cpu") else ", bf16 emulated"
    return (f"{platform.machine()} {torch.backends.cpu.get_cpu_capability()}{bf16}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}")


def show(title: str, header: list[str], rows: list[list[str]]) -> None:
    table = Table(*header, title=title)
    for row in rows:
        table.add_row(*row)
    Console().print(table)


def write_rows(doc: Path, name: str, header: list[str], rows: list[list[str]], key: int) -> None:
    """Put rows (dated) in the benchmark's table in ``doc`` (between the ``bench:NAME`` markers): a row replaces the
    earlier row of the same setting (its first ``key`` columns) on the same kind of machine, so the table holds each
    setting's latest figures per kind."""
    begin, end = f"<!-- bench:{name}:begin -->", f"<!-- bench:{name}:end -->"
    text = doc.read_text() if doc.exists() else "# Benchmarks\n"
    head = ["date", "machine", *header]
    here = machine()
    new = {(here, *r[:key]): [date.today().isoformat(), here, *r] for r in rows}
    kept: list[list[str]] = []
    if begin in text:
        old = text[text.index(begin) + len(begin) : text.index(end)].strip().splitlines()[2:]
        for line in old:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if tuple(cells[1 : 2 + key]) not in new:
                kept.append(cells)
    table = "\n".join([begin, "| " + " | ".join(head) + " |", "|" + "---|" * len(head),
                        *["| " + " | ".join(r) + " |" for r in kept + list(new.values())], end])
    if begin in text:
        text = text[: text.index(begin)] + table + text[text.index(end) + len(end) :]
    else:
        text = f"{text.rstrip()}\n\n## {name}\n\n{table}\n"
    doc.write_text(text)


def publish(title: str, name: str, header: list[str], rows: list[list[str]], doc: Path | None, key: int = 2) -> None:
    """Print the table and, given a doc, write its rows there (``write_rows``)."""
    show(title, header, rows)
    if doc:
        write_rows(doc, name, header, rows, key)


def time_decisions(planner: Any, obs: dict, repeat: int) -> tuple[float, str]:
    """Median seconds of ``planner``'s decision on ``obs`` (one history) and where the time went."""
    import torch

    gen, parts = torch.Generator().manual_seed(0), dict[str, float]()

    def decide() -> None:
        with torch.no_grad():
            plan = planner.plan(obs, [gen])
        for k, v in plan.seconds.items():
            parts[k] = parts.get(k, 0.0) + v

    t = median_seconds(decide, number=1, repeat=repeat)
    total = sum(parts.values()) or 1.0
    return t, ", ".join(f"{k} {v / total:.0%}" for k, v in sorted(parts.items(), key=lambda kv: -kv[1]))
