"""The task's reward on stored states, for components that learn a value from episodes (V-GPS, latent models).

``gpc.models`` knows no task, so such a component names where its reward comes from, ``module:function``
of the task's name (``TASK_REWARD``: the harness's, the task's own state reward, the one GPC's planners
score predicted futures with); its scale (the standard deviation over the stored steps) makes the
learned values comparable across tasks.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import torch

from gpc.models.named import load_named

TASK_REWARD = "gpc.harness.values:task_reward"
CHUNK = 4096  # states scored per call when measuring the scale


@functools.lru_cache(maxsize=8)
def stored_reward(spec: str, task: str) -> Any:
    """The reward ``spec`` names for ``task``: ``(N, T, D)`` raw states, ``(N, G)`` goals or None -> ``(N,)``, the last step scored."""
    return load_named(spec, "the training reward")(task)


def reward_scale(spec: str, task: str, states: np.ndarray, goals: np.ndarray | None) -> float:
    """The reward's standard deviation over every stored state (1 where it barely varies)."""
    reward = stored_reward(spec, task)
    with torch.no_grad():
        values = torch.cat([reward(torch.as_tensor(states[i : i + CHUNK], dtype=torch.float32)[:, None],
                                   None if goals is None else torch.as_tensor(goals[i : i + CHUNK], dtype=torch.float32))
                            for i in range(0, len(states), CHUNK)])
    std = float(values.std()) if len(values) > 1 else 0.0
    return std if std > 1e-6 else 1.0
