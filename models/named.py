"""Objects a task or a user names as ``package.module:attribute`` (a state reward, a relabelling, a planner, a training
reward): imported on first use, so a task's code lives beside the task and ``gpc.models`` never imports it."""

from __future__ import annotations

import importlib
from typing import Any


def load_named(spec: str, source: str) -> Any:
    """The attribute ``spec`` names; a bad name is one ``ValueError`` saying where it came from (``source``)."""
    module, _, attr = spec.strip().partition(":")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError, ValueError) as exc:
        raise ValueError(f"{source}: cannot load {spec!r} ({exc})") from None
