"""The largest value each numeric option takes, declared once: Click refuses a value past it while parsing, in one
line naming the option, before any file is made (``-n 10**23`` once reached ``range`` as an OverflowError, and a
seed past 32 bits failed inside the first episode, after the store was made)."""

from __future__ import annotations

from gpc.tasks.base import MAX_SEED

__all__ = ["MAX_COUNT", "MAX_PROCESSES", "MAX_SEED"]

MAX_COUNT = 2**31 - 1  # episodes, steps, batches, windows, sizes: past any run, inside every index type
MAX_PROCESSES = 1024  # worker processes, threads, nodes: past any machine's cores (each one is started)
