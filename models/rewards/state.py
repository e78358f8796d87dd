"""Rewards on predicted states, chosen by name: a task names the one its planners score with.

A task (``gpc.tasks.base.Task.state_reward``) names its reward instead of building it, since tasks
never import ``gpc.models``; the name maps here to a factory of the task's layout and a
``RewardConfig``. ``registration`` (the mean over the task's objects of their registration loss
against the goal) is built in; a task of your own can register another differentiable reward
(batched futures ``(K, T, D)`` and optional goals ``(K, G)`` in, ``(K,)`` scores out, higher is better),
or name its factory ``package.module:function``, imported and registered on first use: a task's reward
then lives beside the task, which imports no ``gpc.models``. A reward whose final score is computed from every
predicted step, not the last alone, says so with a true ``reads_path`` attribute, so that the learned image reward
reads a state from every predicted frame for it (``gpc.models.rewards.image_state``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from gpc.datasets.layout import TaskLayout
from gpc.models.named import load_named
from gpc.models.rewards.registration import RegistrationReward, RewardConfig

StateRewardFactory = Callable[[TaskLayout, RewardConfig], Any]
_FACTORIES: dict[str, StateRewardFactory] = {"registration": RegistrationReward.from_layout}


def register_state_reward(name: str, factory: StateRewardFactory) -> None:
    """Make ``factory(layout, config)`` the state reward a task names ``name``."""
    _FACTORIES[name] = factory


def state_reward(name: str, layout: TaskLayout, config: RewardConfig = RewardConfig()) -> Any:
    """The reward a task names, for its layout (a ``module:function`` name is imported and registered)."""
    if name not in _FACTORIES and ":" in name:
        register_state_reward(name, load_named(name, f"task {layout.name}'s state reward"))
    if name not in _FACTORIES:
        raise ValueError(f"task {layout.name}: unknown state reward {name!r} (registered: {', '.join(sorted(_FACTORIES))}; "
                         "add yours with gpc.models.rewards.state.register_state_reward)")
    return _FACTORIES[name](layout, config)
