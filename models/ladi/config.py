"""A LaDi-WM-style latent diffusion world model: config and profiles (``gpc train latent-world-model --kind ladi``).

LaDi-WM (Huang et al. 2025) predicts the future latents of a frozen pretrained visual encoder with a
diffusion model and scores them with a reward on latents. Its foundation encoders (DINOv2, SigLIP)
cannot be downloaded here, so the frozen encoder is the policy's own observation encoder (its
averaged weights; for keypoint and state policies a normalisation without weights), copied into the
checkpoint. A 1-D U-Net denoises the ``future`` latents after each of the chunk's first ``future``
actions, conditioned on the history's latents and those actions; a reward head reads a latent.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from gpc.datasets.layout import TaskLayout
from gpc.models.networks.ddpm import NoiseConfig, SamplerConfig
from gpc.models.networks.encoders import EncoderConfig, ReadsObservations
from gpc.models.networks.unet1d import UNetConfig
from gpc.models.rewards.stored import TASK_REWARD
from gpc.models.training.config import OptimConfig, Profile
from gpc.models.training.config_io import PlainConfig
from gpc.models.training.ema import EMAConfig
from gpc.models.values.config import PROFILES

AGGREGATES = ("final", "sum")
TARGETS = ("change", "latent")


@dataclass(frozen=True)
class LadiConfig(PlainConfig, ReadsObservations):
    """The latent diffusion model, its reward head, and how a chunk is scored."""

    task: str = ""  # task the model is trained for; checked when a checkpoint is loaded
    policy: str = ""  # the policy checkpoint whose frozen encoder it reads (its weights are copied in)
    action_dim: int = 2
    n_obs_steps: int = 2  # the policy's history
    future: int = 8  # latents predicted, one after each of the chunk's first `future` actions
    encoder: EncoderConfig = field(default_factory=EncoderConfig)  # the policy's encoder (shapes included)
    unet: UNetConfig = field(default_factory=lambda: UNetConfig(down_dims=(64, 128, 256), step_embed_dim=128))
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    sampler: SamplerConfig = field(default_factory=SamplerConfig)  # DDIM-10, as the policy samples
    reward_width: int = 256
    reward: str = TASK_REWARD  # where the reward head's targets come from (module:function of the task name)
    reward_goal: bool = False  # the reward reads each episode's goal (the stores' ``goal``)
    reward_scale: float = 1.0  # rewards are divided by this (filled in from the data)
    aggregate: str = "final"  # a chunk's score: the reward of its last predicted latent, or the sum over them
    target: str = "change"  # what is denoised: each future latent's change since now (scaled by its reach), or the latent
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=1e-3))
    ema: EMAConfig = field(default_factory=EMAConfig)

    def __post_init__(self) -> None:
        if not self.task:
            raise ValueError("task must be named")
        for name in ("action_dim", "n_obs_steps", "future", "reward_width"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} {getattr(self, name)}: must be at least 1")
        self.unet.check_horizon(self.future)
        if self.aggregate not in AGGREGATES:
            raise ValueError(f"aggregate {self.aggregate!r}: use one of {', '.join(AGGREGATES)}")
        if self.target not in TARGETS:
            raise ValueError(f"target {self.target!r}: use one of {', '.join(TARGETS)}")
        if not self.reward_scale > 0:
            raise ValueError(f"reward_scale {self.reward_scale}: must be > 0")


def ladi_profile(name: str, layout: TaskLayout, policy: str, encoder: EncoderConfig, timeline: tuple[int, int],
                 lr: float | None = None) -> Profile[LadiConfig]:
    """``cpu``: the policy's CPU U-Net widths, 8 future latents, 8,000 steps (GPC's state world model's two phases; about
    60 minutes alone on 2 cores at 0.45 s per step; at 1,500 its held-out denoising loss was still falling);
    ``paper``: Diffusion Policy's widths;
    ``tiny``: tests. ``encoder`` and ``timeline`` are the policy's (its frozen encoder, history and executed chunk)."""
    base = LadiConfig(task=layout.name, policy=policy, action_dim=layout.action.dim, encoder=encoder,
                      n_obs_steps=timeline[0], future=timeline[1], reward_goal=encoder.goal)
    if name == "cpu":
        config, batch, steps = base, 256, 8000
    elif name == "paper":
        config, batch, steps = dataclasses.replace(base, unet=UNetConfig(), reward_width=512), 256, 100000
    elif name == "tiny":
        optim = OptimConfig(lr=3e-3, warmup_steps=5)
        config = dataclasses.replace(base, unet=UNetConfig(down_dims=(16, 32), step_embed_dim=16), reward_width=32,
                                     sampler=SamplerConfig("ddim", 4), optim=optim)
        batch, steps = 32, 30
    else:
        raise ValueError(f"profile {name!r}: use one of {', '.join(PROFILES)}")
    if lr is not None:
        config = dataclasses.replace(config, optim=dataclasses.replace(config.optim, lr=lr))
    return Profile(config, batch, steps)
