"""Block Stacking: the paper's third vision task, in 3-D on MuJoCo (the paper publishes no simulator).

A table, a red and a blue 4 cm cube and a floating parallel-jaw gripper (``scene``); the goal is the red cube resting
centred on the blue one, the gripper open and clear. ``gymnasium.make("gpc/Stack-v0", obs_type=...)`` builds the
environment.
"""

from __future__ import annotations

import gymnasium as gym

from gpc.tasks.stack.env import MAX_EPISODE_STEPS, StackEnv

ENV_ID = "gpc/Stack-v0"

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="gpc.tasks.stack.env:StackEnv", max_episode_steps=MAX_EPISODE_STEPS)

__all__ = ["ENV_ID", "MAX_EPISODE_STEPS", "StackEnv"]
