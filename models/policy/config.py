"""The policy's one config (what the network is and how it learns) and its named profiles.

Profiles (``cpu``, ``paper``, ``tiny``) fix the sizes; the observation shapes are filled in
from the training data (``with_obs_shapes``) so a checkpoint alone can rebuild the network.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from gpc.datasets.layout import TaskLayout
from gpc.models.networks.ddpm import NoiseConfig, SamplerConfig
from gpc.models.networks.encoders import EncoderConfig, ReadsObservations
from gpc.models.networks.unet1d import UNetConfig
from gpc.models.training.config import OptimConfig, Profile
from gpc.models.training.config_io import PlainConfig
from gpc.models.training.ema import EMAConfig

PROFILES = ("cpu", "paper", "tiny")
GOALS = ("fixed", "random")
LABELS = ("action", "expert_action")  # what a policy learns its actions from (``PolicyConfig.labels``)


@dataclass(frozen=True)
class PolicyConfig(PlainConfig, ReadsObservations):
    """Diffusion Policy: a chunk of ``horizon`` actions denoised given ``n_obs_steps`` observations.

    Timeline (n_obs_steps 2, horizon 16, n_action_steps 8), index 0 = oldest observation::

        obs      | o0 o1 |
        actions  | a0 a1 a2 ... a15 |          (predicted chunk)
        executed |    a1 ... a8     |          (n_action_steps from index n_obs_steps - 1)
    """

    task: str  # task the policy is trained for; checked when a checkpoint is loaded
    action_dim: int  # width of one action
    horizon: int = 16  # actions per predicted chunk
    n_obs_steps: int = 2  # observation history length
    n_action_steps: int = 8  # actions executed per decision, from index n_obs_steps - 1
    encoder: EncoderConfig = field(default_factory=EncoderConfig)  # observation type and encoder sizes
    unet: UNetConfig = field(default_factory=UNetConfig)  # the noise-prediction network
    noise: NoiseConfig = field(default_factory=NoiseConfig)  # DDPM training process
    sampler: SamplerConfig = field(default_factory=SamplerConfig)  # default inference chain
    optim: OptimConfig = field(default_factory=OptimConfig)  # optimiser and learning-rate schedule
    ema: EMAConfig = field(default_factory=EMAConfig)  # EMA weights used for sampling and validation
    # The array the actions are learned from: ``action`` (what ran) or ``expert_action`` (a DART store's labels:
    # what the expert asked for under noise; a store without them gives its actions, its expert ran clean).
    labels: str = "action"

    def __post_init__(self) -> None:
        if not self.task:
            raise ValueError("task must be named")
        if self.labels not in LABELS:
            raise ValueError(f"--labels {self.labels!r}: use one of {', '.join(LABELS)}")
        for name in ("horizon", "n_obs_steps", "n_action_steps", "action_dim"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} {getattr(self, name)}: must be at least 1")
        if self.n_obs_steps - 1 + self.n_action_steps > self.horizon:
            raise ValueError(
                f"n_obs_steps {self.n_obs_steps} - 1 + n_action_steps {self.n_action_steps} exceeds horizon {self.horizon}"
            )
        self.unet.check_horizon(self.horizon)
        if self.sampler.steps > self.noise.train_steps:
            raise ValueError(f"sampler steps {self.sampler.steps} exceed the {self.noise.train_steps} training steps")


def policy_profile(name: str, obs_type: str, layout: TaskLayout, goal: str = "fixed",
                   lr: float | None = None, mlp: tuple[int, ...] = ()) -> Profile[PolicyConfig]:
    """``cpu``: narrow U-Net, DDIM-10, trains on 2 cores; ``paper``: Diffusion Policy's sizes,
    DDPM-100; ``tiny``: seconds-long runs for tests. The task's layout fills the action width and
    where the agent sits in the state; ``goal="random"``: the policy also reads each episode's goal
    (stores collected with random goals); ``lr``: another peak learning rate than the profile's; ``mlp``: widths of
    an MLP over each step's observation features (``EncoderConfig.mlp``)."""
    if goal not in GOALS:
        raise ValueError(f"--goal {goal!r}: use one of {', '.join(GOALS)}")
    image = obs_type == "image"
    if name == "cpu":
        unet = UNetConfig(down_dims=(64, 128, 256), step_embed_dim=128)
        encoder = EncoderConfig(obs_type, resnet_width=32 if image else 64)
        # lr 1e-3, not Diffusion Policy's 1e-4: over a CPU-sized budget of a few thousand steps the
        # smaller rate underfits (expert data, 50 test seeds, DDIM-10: 0.473 after 6,500 steps at
        # 1e-4 against 0.696 after 3,000 steps at 1e-3; docs/results.md).
        sampler, batch, steps, optim = SamplerConfig("ddim", 10), 64 if image else 256, 6000, OptimConfig(lr=1e-3)
    elif name == "paper":
        # Diffusion Policy: state (256,512,1024) with a 256-wide step embedding, batch 256;
        # image (512,1024,2048) with a 128-wide one, batch 64. Both sample with DDPM-100.
        unet = UNetConfig(down_dims=(512, 1024, 2048), step_embed_dim=128) if image else UNetConfig()
        encoder = EncoderConfig(obs_type)
        sampler, batch, steps, optim = SamplerConfig("ddpm", 100), 64 if image else 256, 500_000, OptimConfig()
    elif name == "tiny":
        unet = UNetConfig(down_dims=(16, 32), step_embed_dim=16)
        encoder = EncoderConfig(obs_type, crop_size=24, resnet_width=8, spatial_keypoints=4, image_feature_dim=8)
        sampler, batch, steps, optim = SamplerConfig("ddim", 4), 32, 50, OptimConfig(lr=3e-3, warmup_steps=5)
    else:
        raise ValueError(f"profile {name!r}: use one of {', '.join(PROFILES)}")
    if obs_type != "state":
        if not layout.state.agent_xy:
            raise ValueError(f"obs {obs_type!r} reads the agent's position; task {layout.name} has none in its state")
        encoder = dataclasses.replace(encoder, agent_dims=len(layout.state.agent_xy))
    encoder = dataclasses.replace(encoder, goal=goal == "random" or layout.goal is None,  # a goal drawn per episode is read
                                  state_spans=layout.state.spans, mlp=tuple(mlp))
    optim = optim if lr is None else dataclasses.replace(optim, lr=lr)
    policy = PolicyConfig(task=layout.name, action_dim=layout.action.dim, encoder=encoder, unet=unet, sampler=sampler,
                          optim=optim)
    return Profile(policy, batch, steps)
