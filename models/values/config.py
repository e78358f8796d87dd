"""V-GPS's value function: its config and profiles (``gpc train value``).

V-GPS (Nakamoto et al. 2024, "Steering Your Generalists") re-ranks a frozen generalist policy's
sampled actions by a Q-function trained offline. Ours is trained with IQL (Kostrikov et al. 2022)
rather than Cal-QL: IQL never queries actions outside the data, so it needs no policy to sample
them, and V-GPS reports both. The "action" is the chunk a decision executes (``n_action_steps``
actions from the current step), the transition is one decision (a semi-MDP step of that many
environment steps), and the reward is the task's own state reward (the one GPC's planners score
predicted futures with) on the state the chunk reaches.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from gpc.datasets.layout import TaskLayout
from gpc.models.networks.encoders import EncoderConfig, ReadsObservations
from gpc.models.rewards.stored import TASK_REWARD
from gpc.models.training.config import OptimConfig, Profile
from gpc.models.training.config_io import PlainConfig
from gpc.models.training.ema import EMAConfig

PROFILES = ("cpu", "paper", "tiny")
OBS_TYPES = ("state", "keypoints", "image")


@dataclass(frozen=True)
class ValueConfig(PlainConfig, ReadsObservations):
    """A Q-function of (observation history, executed chunk) and a state value V, trained by IQL."""

    task: str = ""  # task the value function is trained for; checked when a checkpoint is loaded
    action_dim: int = 2
    n_obs_steps: int = 2  # observation history length (the policy's)
    n_action_steps: int = 8  # actions per decision: the chunk Q reads and one transition's length
    encoder: EncoderConfig = field(default_factory=EncoderConfig)  # observation type (the policy's) and sizes
    width: int = 256  # hidden units of the Q and V networks
    depth: int = 2  # hidden layers
    discount: float = 0.99  # per environment step; a transition of n actions discounts by discount ** n
    expectile: float = 0.7  # IQL's tau: V fits this expectile of Q over the data's actions (0.5: SARSA's mean)
    target_decay: float = 0.995  # the target Q-networks: an exponential average of the trained ones
    reward: str = TASK_REWARD  # where the training reward comes from (module:function of the task name)
    reward_goal: bool = False  # the reward reads each episode's goal (the stores' ``goal``)
    reward_scale: float = 1.0  # rewards are divided by this (the training data's standard deviation; filled in)
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=3e-4, betas=(0.9, 0.999), warmup_steps=200))

    def __post_init__(self) -> None:
        if not self.task:
            raise ValueError("task must be named")
        for name in ("action_dim", "n_obs_steps", "n_action_steps", "width", "depth"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} {getattr(self, name)}: must be at least 1")
        if not 0.0 <= self.discount < 1.0:
            raise ValueError(f"discount {self.discount}: must lie in [0, 1)")
        if not 0.0 < self.expectile < 1.0:
            raise ValueError(f"expectile {self.expectile}: must lie in (0, 1)")
        if not 0.0 <= self.target_decay < 1.0:
            raise ValueError(f"target_decay {self.target_decay}: must lie in [0, 1)")
        if not self.reward_scale > 0:
            raise ValueError(f"reward_scale {self.reward_scale}: must be > 0")

    @property
    def ema(self) -> EMAConfig:
        """The target networks' average (``TrainableModule``'s EMA copy), at a constant decay."""
        return EMAConfig(power=1.0, min_decay=self.target_decay, max_decay=self.target_decay)

    @property
    def chunk_discount(self) -> float:
        return float(self.discount**self.n_action_steps)


def value_profile(name: str, obs_type: str, layout: TaskLayout, timeline: tuple[int, int], goal: str = "fixed",
                  lr: float | None = None) -> Profile[ValueConfig]:
    """``cpu``: two 256-wide layers, 10,000 steps (about 8 minutes on 2 cores, what GPC's state world model takes);
    ``paper``: 512-wide, 100,000; ``tiny``: tests. ``timeline``: the
    policy's (n_obs_steps, n_action_steps), so that the Q-function reads what the policy reads and scores what it executes."""
    if obs_type not in OBS_TYPES:
        raise ValueError(f"--obs {obs_type!r}: use one of {', '.join(OBS_TYPES)}")
    image = obs_type == "image"
    if name == "cpu":
        encoder = EncoderConfig(obs_type, resnet_width=32 if image else 64)
        config, batch, steps = ValueConfig(task=layout.name, encoder=encoder), 64 if image else 256, 10000
    elif name == "paper":
        config = ValueConfig(task=layout.name, encoder=EncoderConfig(obs_type), width=512)
        batch, steps = 256, 100000
    elif name == "tiny":
        encoder = EncoderConfig(obs_type, crop_size=24, resnet_width=8, spatial_keypoints=4, image_feature_dim=8)
        optim = OptimConfig(lr=1e-3, betas=(0.9, 0.999), warmup_steps=2)
        config, batch, steps = ValueConfig(task=layout.name, encoder=encoder, width=32, optim=optim), 32, 30
    else:
        raise ValueError(f"profile {name!r}: use one of {', '.join(PROFILES)}")
    encoder, varies = task_encoder(config.encoder, layout, goal)
    config = dataclasses.replace(config, encoder=encoder, reward_goal=varies, action_dim=layout.action.dim,
                                 n_obs_steps=timeline[0], n_action_steps=timeline[1])
    if lr is not None:
        config = dataclasses.replace(config, optim=dataclasses.replace(config.optim, lr=lr))
    return Profile(config, batch, steps)


def task_encoder(encoder: EncoderConfig, layout: TaskLayout, goal: str) -> tuple[EncoderConfig, bool]:
    """The encoder for the task's observations (where the agent sits in its state; whether a goal drawn per episode
    is read) and whether the goal varies, so the training reward must read it too."""
    if encoder.obs_type != "state":
        if not layout.state.agent_xy:
            raise ValueError(f"obs {encoder.obs_type!r} reads the agent's position; task {layout.name} has none in its state")
        encoder = dataclasses.replace(encoder, agent_dims=len(layout.state.agent_xy))
    varies = goal == "random" or layout.goal is None
    return dataclasses.replace(encoder, goal=varies), varies
