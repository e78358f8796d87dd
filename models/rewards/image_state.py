"""The learned image reward of a task scored by its own state reward: read a frame's state, score it as a state.

Registration compares objects' poses; Triangle Drawing's reward reads ink and Block Stacking's a height, so their
image reward reads the whole state from each predicted frame (``learned.StatePredictor``) and scores it with the
task's differentiable state reward (``Task.state_reward``, the one planners rank predicted states with): frames and
states are then ranked by one function. ``learned_image_reward`` loads either kind from a ``gpc train reward``
checkpoint.
"""

from __future__ import annotations

import os
from typing import Any

import torch
from torch import nn

from gpc.models.rewards.learned import ImageReward, PosePredictor, RewardPredictorModule
from gpc.models.rewards.registration import RewardConfig


class StateImageReward(nn.Module):
    """``(K, T, 3, S, S)`` frames in [0, 1] -> ``(K,)`` scores: ``reward`` (a state reward taking ``(K, T, D)`` states
    and optional goals) on the states ``predictor`` reads from them; differentiable w.r.t. the frames."""

    def __init__(self, predictor: PosePredictor, reward: nn.Module, config: RewardConfig = RewardConfig()) -> None:
        super().__init__()
        if not predictor.config.state_reward:
            raise ValueError("this predictor reads poses, not states: use ImageReward")
        self.predictor, self.reward, self.config = predictor, reward, config

    @property
    def input_size(self) -> int:
        """The frame size the predictor was trained at (other sizes are resized to it)."""
        return self.predictor.config.input_size

    def states(self, frames: torch.Tensor) -> torch.Tensor:
        """``(K, T, 3, S, S)`` -> ``(K, T, D)`` states read from every frame."""
        if frames.dim() != 5 or frames.shape[2] != 3:
            raise ValueError(f"frames: expected (K, T, 3, S, S), got {tuple(frames.shape)}")
        k, t = frames.shape[:2]
        return self.predictor(frames.flatten(0, 1)).reshape(k, t, -1)

    def forward(self, frames: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
        # Where only the last state scores, read no other frame (each read is a network pass); a state reward whose
        # final score is made from the whole predicted path (``reads_path``: Triangle Drawing's ink) reads them all.
        if self.config.aggregate == "final" and not getattr(self.reward, "reads_path", False):
            frames = frames[:, -1:]
        return self.reward(self.states(frames), goal)


def learned_image_reward(path: str | os.PathLike, state_reward: nn.Module, goal: Any = None,
                         config: RewardConfig = RewardConfig(), map_location: Any = "cpu", task: str | None = None) -> nn.Module:
    """The frozen reward of a ``gpc train reward`` checkpoint: registration of the poses it reads (``ImageReward``), or,
    for a state reader, ``state_reward`` (the task's, built with ``config``) on the states it reads."""
    predictor = RewardPredictorModule.load_from_checkpoint(path, map_location=map_location, task=task).predictor
    predictor = predictor.requires_grad_(False).eval()
    if predictor.config.state_reward:
        return StateImageReward(predictor, state_reward, config)
    return ImageReward(predictor, goal, config)
