"""Cube & Sphere Swapping: the paper's second vision task, on our own planar simulator (the paper publishes none).

Push-T's workspace, agent and physics (``gpc.tasks.planar``), a square cube and a round sphere; the goal is to swap
their places. This package gives the pieces a task is made of (environment, observation, recording, scripted
expert and explorer, the simulator as a world model); ``gymnasium.make("gpc/Swap-v0", obs_type=...)`` builds the env.
"""

from __future__ import annotations

import gymnasium as gym

from gpc.tasks.swap.env import MAX_EPISODE_STEPS, SwapEnv

ENV_ID = "gpc/Swap-v0"

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="gpc.tasks.swap.env:SwapEnv", max_episode_steps=MAX_EPISODE_STEPS)

__all__ = ["ENV_ID", "MAX_EPISODE_STEPS", "SwapEnv"]
