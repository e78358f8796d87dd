"""What a value function trains on that only the harness knows: the task's own reward on stored states."""

from __future__ import annotations

from typing import Any

from gpc.tasks import get_task


def task_reward(task: str) -> Any:
    """The task's state reward (the one GPC's planners score predicted futures with), ``(N, T, D)`` states and
    ``(N, G)`` goals or None -> ``(N,)``, its final step scored; ``gpc.models.rewards.stored.TASK_REWARD`` names it."""
    from gpc.harness.recipes import RewardSpec, build_reward

    return build_reward(RewardSpec(), get_task(task))
