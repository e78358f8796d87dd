"""Tasks: environments, experts, exploration and task rewards. Nothing else knows their constants.

A task is a module exposing the small interface collection and inspection need
(``record``, ``env_params``, ``collector_params``, ``record_keys``, ``episode_scores``).
"""

from __future__ import annotations

import importlib
from types import ModuleType

TASKS = ("pusht",)


def get_task(name: str) -> ModuleType:
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}: available tasks are {', '.join(TASKS)}")
    return importlib.import_module(f"tasks.{name}")
