"""Timing and reporting shared by the benchmarks: medians of repeats, tables, README rows."""

from __future__ import annotations

import platform
import re
import statistics
import time
from datetime import date
from pathlib import Path
from typing import Callable

from rich.console import Console
from rich.table import Table


def median_seconds(fn: Callable[[], object], number: int, repeat: int = 5) -> float:
    """Median over ``repeat`` runs of the mean time of ``number`` calls."""
    fn()  # warm-up
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        runs.append((time.perf_counter() - t0) / number)
    return statistics.median(runs)


def machine() -> str:
    import os

    return f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"


def show(title: str, header: list[str], rows: list[list[str]]) -> None:
    table = Table(*header, title=title)
    for row in rows:
        table.add_row(*row)
    Console().print(table)


def append_rows(readme: Path, name: str, header: list[str], rows: list[list[str]]) -> None:
    """Append rows (dated) to the benchmark's table in the README, creating it if absent."""
    begin, end = f"<!-- bench:{name}:begin -->", f"<!-- bench:{name}:end -->"
    text = readme.read_text() if readme.exists() else ""
    stamped = [[date.today().isoformat(), machine(), *r] for r in rows]
    lines = ["| " + " | ".join(r) + " |" for r in stamped]
    if begin not in text:
        head = ["date", "machine", *header]
        block = "\n".join([begin, "| " + " | ".join(head) + " |", "|" + "---|" * len(head), *lines, end])
        marker = "<!-- bench:insert -->"
        text = text.replace(marker, f"{block}\n\n{marker}") if marker in text else f"{text.rstrip()}\n\n{block}\n"
    else:
        text = re.sub(re.escape(end), lambda _: "\n".join(lines) + "\n" + end, text, count=1)
    readme.write_text(text)


def publish(title: str, name: str, header: list[str], rows: list[list[str]], readme: Path | None) -> None:
    """Print the table and, given a README, append its rows there (between the ``bench:NAME`` markers)."""
    show(title, header, rows)
    if readme:
        append_rows(readme, name, header, rows)
