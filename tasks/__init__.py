"""Tasks: environments, experts, exploration and task geometry. Nothing else knows their constants.

``get_task(name)`` returns a ``Task`` (``gpc.tasks.base``), the one interface collection,
training, planning and evaluation use. Push-T ships built in; ``register_task`` adds your own
(checkpoints record the task's name, so register it before loading them).
"""

from __future__ import annotations

import importlib

from gpc.tasks.base import Task

BUILT_IN = {"pusht": "gpc.tasks.pusht"}  # name -> module exposing TASK (imported on first use)
DEFAULT_TASK = "pusht"  # what commands act on when no --task is given
_REGISTRY: dict[str, Task] = {}


def register_task(task: Task) -> Task:
    """Make ``task`` known by its name (replacing an earlier registration of that name)."""
    _REGISTRY[task.name] = task
    return task


def task_names() -> tuple[str, ...]:
    return tuple(dict.fromkeys([*BUILT_IN, *_REGISTRY]))


def get_task(name: str) -> Task:
    if name not in _REGISTRY and name in BUILT_IN:
        register_task(importlib.import_module(BUILT_IN[name]).TASK)
    if name not in _REGISTRY:
        raise ValueError(f"unknown task {name!r}: available tasks are {', '.join(task_names())}")
    return _REGISTRY[name]
