"""A DreamerV3-style latent world model: its config and profiles (``gpc train latent-world-model``).

DreamerV3 (Hafner et al. 2023) learns a recurrent state-space model (RSSM): a deterministic GRU
state, a discrete stochastic latent (groups of categoricals, 1% uniform mix), an observation
decoder and a reward head, with symlog targets, KL balancing (dynamics 0.5, representation 0.1)
and free bits (1 nat). Here it is trained on the same stores as GPC's world model, the reward
head on the task's own state reward, and used as DreamerV3 plans in imagination: each of the
policy's K proposals is rolled out in latent space from the current observation and ranked by the
reward it imagines along the chunk. The decoder reconstructs the task's state vector (for state
observations, the observation itself; image observations are encoded, and their decoder also
targets the state, not the pixels).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from gpc.datasets.layout import TaskLayout
from gpc.models.networks.encoders import EncoderConfig, ReadsObservations
from gpc.models.rewards.stored import TASK_REWARD
from gpc.models.training.config import OptimConfig, Profile
from gpc.models.training.config_io import PlainConfig
from gpc.models.values.config import OBS_TYPES, PROFILES, task_encoder

AGGREGATES = ("sum", "final")


@dataclass(frozen=True)
class LatentConfig(PlainConfig, ReadsObservations):
    """The RSSM's sizes, its losses' weights, and how imagined rewards rank a chunk."""

    task: str = ""  # task the model is trained for; checked when a checkpoint is loaded
    action_dim: int = 2
    state_dim: int = 0  # width of the task's state, the decoder's target (filled in from the data)
    encoder: EncoderConfig = field(default_factory=EncoderConfig)  # observation type (the policy's) and sizes
    sequence: int = 32  # steps per training sequence
    # Observations each posterior reads: 1, the current one (DreamerV3); 2, it and the one before, stacked, as the policy
    # reads its history (a decision starts from one posterior, which then sees velocities a single frame cannot show).
    history: int = 1
    deter: int = 256  # GRU state width
    groups: int = 16  # categorical latents
    classes: int = 16  # classes per categorical
    hidden: int = 256  # MLP width (embedding, prior, posterior, heads)
    unimix: float = 0.01  # uniform share mixed into every categorical
    free_nats: float = 1.0  # KL terms below this are not pushed further (free bits)
    dyn_scale: float = 0.5  # KL balancing: the prior towards the (stopped) posterior
    rep_scale: float = 0.1  # ... and the posterior towards the (stopped) prior
    # The heads' losses are negative log-likelihoods of a Gaussian of this precision (1 / (2 sigma^2)): the decoder's
    # summed over the normalised state's entries, the reward head's on symlog(reward / scale). Against the KL's price
    # per nat, they decide how much of each observation the posterior keeps (at 1, a 2-d state was not worth 1 nat).
    recon_weight: float = 100.0
    reward_weight: float = 10.0
    reward: str = TASK_REWARD  # where the reward head's targets come from (module:function of the task name)
    reward_goal: bool = False  # the reward reads each episode's goal (the stores' ``goal``)
    reward_scale: float = 1.0  # rewards are divided by this before symlog (filled in from the data)
    aggregate: str = "sum"  # ranking: sum (discounted) of the imagined rewards along the chunk, or the final one
    discount: float = 0.99
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=4e-4, betas=(0.9, 0.999), warmup_steps=200))

    def __post_init__(self) -> None:
        if not self.task:
            raise ValueError("task must be named")
        for name in ("action_dim", "deter", "groups", "classes", "hidden"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} {getattr(self, name)}: must be at least 1")
        if self.history < 1:
            raise ValueError(f"history {self.history}: must be at least 1")
        if self.sequence < 2:
            raise ValueError(f"sequence {self.sequence}: must be at least 2 (a step and what follows it)")
        if not 0.0 <= self.unimix < 1.0 or self.free_nats < 0 or self.dyn_scale < 0 or self.rep_scale < 0:
            raise ValueError("unimix must lie in [0, 1), free_nats and the KL scales must be >= 0")
        if self.aggregate not in AGGREGATES:
            raise ValueError(f"aggregate {self.aggregate!r}: use one of {', '.join(AGGREGATES)}")
        if not 0.0 <= self.discount <= 1.0 or not self.reward_scale > 0:
            raise ValueError("discount must lie in [0, 1] and reward_scale be > 0")

    @property
    def stoch(self) -> int:
        return self.groups * self.classes


def latent_profile(name: str, obs_type: str, layout: TaskLayout, goal: str = "fixed",
                   lr: float | None = None) -> Profile[LatentConfig]:
    """``cpu``: 256-wide, 16x16 latents, 3,000 sequences of 32 steps in batches of 16 (about 9 minutes on 2 cores,
    more than GPC's state world model takes); ``paper``: DreamerV3's medium sizes; ``tiny``: tests."""
    if obs_type not in OBS_TYPES:
        raise ValueError(f"--obs {obs_type!r}: use one of {', '.join(OBS_TYPES)}")
    image = obs_type == "image"
    if name == "cpu":
        encoder = EncoderConfig(obs_type, resnet_width=32 if image else 64)
        config, batch, steps = LatentConfig(task=layout.name, encoder=encoder), 16, 3000
    elif name == "paper":
        config = LatentConfig(task=layout.name, encoder=EncoderConfig(obs_type), sequence=64, deter=1024, groups=32,
                              classes=32, hidden=512)
        batch, steps = 16, 100000
    elif name == "tiny":
        encoder = EncoderConfig(obs_type, crop_size=24, resnet_width=8, spatial_keypoints=4, image_feature_dim=8)
        optim = OptimConfig(lr=2e-3, betas=(0.9, 0.999), warmup_steps=2)
        config = LatentConfig(task=layout.name, encoder=encoder, sequence=8, deter=64, groups=8, classes=8, hidden=64,
                              optim=optim)
        batch, steps = 16, 30
    else:
        raise ValueError(f"profile {name!r}: use one of {', '.join(PROFILES)}")
    encoder, varies = task_encoder(config.encoder, layout, goal)
    config = dataclasses.replace(config, encoder=encoder, reward_goal=varies, action_dim=layout.action.dim)
    if lr is not None:
        config = dataclasses.replace(config, optim=dataclasses.replace(config.optim, lr=lr))
    return Profile(config, batch, steps)
