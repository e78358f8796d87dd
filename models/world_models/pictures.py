"""Predicted futures as pictures: what a person (a video, `gpc plan`) or a vision-language model is shown of them."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch


def last_step_pictures(futures: torch.Tensor | np.ndarray, render: Callable[..., np.ndarray] | None = None,
                       goal: Any = None) -> list[np.ndarray]:
    """``(K, T, ...)`` futures -> K ``(S, S, 3)`` uint8 pictures of their last predicted step: frames as they are
    (channels first or last, [0, 1] or uint8), states drawn by ``render(state, goal)`` (a goal ``(G,)`` for all or
    ``(K, G)`` one per candidate)."""
    futures = torch.as_tensor(futures)
    last = futures[:, -1].detach().cpu()
    if futures.dim() == 5:  # frames already
        if last.shape[1] == 3:
            last = last.permute(0, 2, 3, 1)
        elif last.shape[-1] != 3:
            raise ValueError(f"frame futures: expected (K, T, 3, H, W) or (K, T, H, W, 3), got {tuple(futures.shape)}")
        array = last.numpy()
        return list(array if array.dtype == np.uint8 else np.round(np.clip(array, 0, 1) * 255).astype(np.uint8))
    if futures.dim() == 3:
        if render is None:
            raise ValueError("state futures (K, T, D) need a render function")
        return [np.asarray(render(s, g)) for s, g in zip(last.numpy(), per_candidate(goal, futures.shape[0]))]
    raise ValueError(f"futures: expected (K, T, D) states or (K, T, 3, H, W) frames, got {tuple(futures.shape)}")


def per_candidate(goal: Any, k: int) -> list[np.ndarray | None]:
    """A goal shared by all candidates ``(G,)`` or one per candidate ``(K, G)`` -> K goals."""
    if goal is None:
        return [None] * k
    goal = goal.detach().cpu().numpy() if isinstance(goal, torch.Tensor) else np.asarray(goal)
    return list(goal) if goal.ndim == 2 else [goal] * k
