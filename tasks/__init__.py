"""Tasks: environments, experts, exploration and task geometry. Nothing else knows their constants.

``get_task(name)`` returns a ``Task`` (``gpc.tasks.base``), the one interface collection,
training, planning and evaluation use. Push-T, Cube & Sphere Swapping and Triangle Drawing ship built in. Your own task becomes known by
name, to the library and to every ``gpc`` command, in one of three ways:

- ``register_task(task)`` in your process (worker processes get it from their parent);
- ``GPC_TASKS=my_package.my_module:TASK`` (comma-separated for several) in the environment;
- an entry point in the group ``gpc.tasks`` of an installed package (``name = "module:TASK"``).

A task's callables must be defined at module level, so that worker processes can receive it.
Checkpoints record the task's name; it must be known before they are loaded.
"""

from __future__ import annotations

import importlib
import os
from importlib.metadata import entry_points

from gpc.tasks.base import Task

# name -> module exposing TASK (imported on first use)
BUILT_IN = {"pusht": "gpc.tasks.pusht", "swap": "gpc.tasks.swap", "stack": "gpc.tasks.stack", "draw": "gpc.tasks.draw"}
DEFAULT_TASK = "pusht"  # what commands act on when no --task is given
ENV_VAR, ENTRY_POINTS = "GPC_TASKS", "gpc.tasks"
_REGISTRY: dict[str, Task] = {}
_USER: dict[str, Task] = {}  # registered in this process: handed to worker processes
_discovered: list[bool] = []


def register_task(task: Task) -> Task:
    """Make ``task`` known by its name (replacing an earlier registration of that name)."""
    _REGISTRY[task.name] = task
    if task.name not in BUILT_IN:
        _USER[task.name] = task
    return task


def user_tasks() -> list[Task]:
    """Tasks registered in this process by hand (a worker process registers them again)."""
    return list(_USER.values())


def _load(spec: str, source: str) -> None:
    module, _, attr = spec.strip().partition(":")
    try:
        task = getattr(importlib.import_module(module), attr or "TASK")
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"{source}: cannot load task {spec!r} ({exc})") from None
    if not isinstance(task, Task):
        raise ValueError(f"{source}: {spec!r} is a {type(task).__name__}, not a gpc.tasks.base.Task")
    _REGISTRY.setdefault(task.name, task)


def _discover() -> None:
    """Tasks named in $GPC_TASKS and by installed packages' entry points, once per process."""
    if _discovered:
        return
    _discovered.append(True)
    for spec in filter(None, os.environ.get(ENV_VAR, "").split(",")):
        _load(spec, f"${ENV_VAR}")
    for point in entry_points(group=ENTRY_POINTS):
        _load(point.value, f"entry point {point.name}")


def task_names() -> tuple[str, ...]:
    _discover()
    return tuple(dict.fromkeys([*BUILT_IN, *_REGISTRY]))


def get_task(name: str) -> Task:
    if name not in _REGISTRY and name in BUILT_IN:
        register_task(importlib.import_module(BUILT_IN[name]).TASK)
    if name not in _REGISTRY:
        _discover()
    if name not in _REGISTRY:
        raise ValueError(f"unknown task {name!r}: available tasks are {', '.join(task_names())} "
                         f"(name your own in ${ENV_VAR}=module:TASK or register it with gpc.tasks.register_task)")
    return _REGISTRY[name]
