"""The state world model's config (the network it is, how it learns) and its named profiles.

Two-phase training is one implementation with two settings of ``unroll``:

- phase 1 (``unroll = 1``): every window supplies ``horizon`` one-step predictions, each from
  the true history (teacher forcing);
- phase 2 (``unroll = horizon`` by default): the predictor is applied recursively from the
  window's true history over ``unroll`` actions and every predicted state is supervised.
  Phase 2 starts from phase-1 weights and keeps phase 1's network and normaliser.

Phase 1 measures errors in one-step-delta standard deviations, phase 2 in state ranges
(``loss_units``): on the human Push-T data, delta units in phase 2 let the agent's
rollout error grow from 0.6 to 5 px while the block improved, state units held it near 1.5 px.

Timeline of one training window (history H = 2, horizon T = 4), index 0 = oldest state::

    states   | s0 s1 | s2 s3 s4 s5 |      s0, s1: history; s2..s5: supervised futures
    actions  |    a1 | a2 a3 a4    |      a_i moves s_i to s_{i+1} (Diffusion Policy's layout)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from models.config_io import PlainConfig
from models.mlp import ACTIVATIONS
from models.policy_config import OptimConfig

KIND = "world_model"
OBS_TYPES = ("state",)
PROFILES = ("cpu", "tiny")
LOSS_UNITS = ("delta", "state")


@dataclass(frozen=True)
class DynamicsConfig:
    """What the single-step predictor reads and its size (fixed once phase 1 has trained it).

    The defaults describe Push-T's state ``[agent x, y, block x, y, block angle]`` and its
    position-target actions; another task passes its own layout.
    """

    state_dim: int = 5  # entries of one state vector
    action_dim: int = 2  # entries of one action
    history: int = 2  # H: states the predictor reads (the last one is the current state)
    angle_dims: tuple[int, ...] = (4,)  # state entries that are angles (fed as cos, sin; predicted as wrapped deltas)
    action_target_dims: tuple[int, ...] = (0, 1)  # state entries the action is a target for (fed as action - state); () for none
    width: int = 256  # hidden units per layer
    depth: int = 4  # hidden layers
    activation: str = "silu"  # silu, gelu, mish or relu
    layer_norm: bool = False  # LayerNorm after each hidden Linear

    def __post_init__(self) -> None:
        for name in ("state_dim", "action_dim", "history", "width", "depth"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} {getattr(self, name)}: must be at least 1")
        for name in ("angle_dims", "action_target_dims"):
            dims = getattr(self, name)
            if len(set(dims)) != len(dims) or not all(0 <= d < self.state_dim for d in dims):
                raise ValueError(f"{name} {dims}: need distinct indices in [0, {self.state_dim})")
        if self.action_target_dims and len(self.action_target_dims) != self.action_dim:
            raise ValueError(f"action_target_dims {self.action_target_dims}: need one per action entry ({self.action_dim})")
        if set(self.angle_dims) & set(self.action_target_dims):
            raise ValueError("an angle cannot be an action target")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation {self.activation!r}: use one of {', '.join(ACTIVATIONS)}")

    @property
    def linear_dims(self) -> tuple[int, ...]:
        """State entries that are not angles (fed normalised, predicted as deltas)."""
        return tuple(i for i in range(self.state_dim) if i not in self.angle_dims)

    @property
    def in_dim(self) -> int:
        """Input width: per history state the linear entries and cos, sin of the angles; the H - 1
        consecutive differences; the action; the action relative to its target entries."""
        per_state = len(self.linear_dims) + 2 * len(self.angle_dims)
        return self.history * per_state + (self.history - 1) * self.state_dim + self.action_dim + len(self.action_target_dims)


@dataclass(frozen=True)
class WorldModelConfig(PlainConfig):
    """A state world model: the single-step predictor, its training windows and its phase."""

    task: str = "pusht"  # task the model is trained for; checked when a checkpoint is loaded
    obs_type: str = "state"  # observations predicted (the visual world model comes later)
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)  # the network
    horizon: int = 16  # T: actions (and supervised future states) per training window
    phase: int = 1  # 1: one-step loss; 2: unrolled loss from phase-1 weights
    unroll: int | None = None  # predicted steps per unrolled segment (default: 1 in phase 1, horizon in phase 2)
    detach_feedback: bool = False  # phase 2: stop gradients through the fed-back predictions
    loss_units: str | None = None  # error scale per state entry: delta (one-step delta std) or state (data range); default by phase
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=1e-3, betas=(0.9, 0.999), warmup_steps=200))

    def __post_init__(self) -> None:
        if not self.task:
            raise ValueError("task must be named")
        if self.obs_type not in OBS_TYPES:
            raise ValueError(f"world model obs {self.obs_type!r}: use one of {', '.join(OBS_TYPES)}")
        if self.horizon < 1:
            raise ValueError(f"horizon {self.horizon}: must be at least 1")
        if self.phase not in (1, 2):
            raise ValueError(f"phase {self.phase}: use 1 (one-step loss) or 2 (unrolled loss)")
        if self.phase == 1 and self.unroll not in (None, 1):
            raise ValueError(f"phase 1 supervises single steps; unroll {self.unroll} needs phase 2")
        if self.phase == 2 and self.unroll is not None and self.unroll < 2:
            raise ValueError(f"phase 2 unroll {self.unroll}: must be at least 2 (unroll 1 is phase 1)")
        if self.loss_units not in (None,) + LOSS_UNITS:
            raise ValueError(f"loss_units {self.loss_units!r}: use one of {', '.join(LOSS_UNITS)}")
        if self.horizon % self.unroll_steps:
            raise ValueError(f"unroll {self.unroll_steps} must divide the horizon {self.horizon}")

    @property
    def unroll_steps(self) -> int:
        if self.unroll is not None:
            return self.unroll
        return 1 if self.phase == 1 else self.horizon

    @property
    def loss_scale(self) -> str:
        """Units of the training error: one-step-delta standard deviations in phase 1 (each entry's
        next-step change predicted equally well), state ranges in phase 2 (a pixel of drift
        costs the same for the agent and the block, whose one-step changes are ten times smaller)."""
        if self.loss_units is not None:
            return self.loss_units
        return "delta" if self.phase == 1 else "state"

    @property
    def window(self) -> int:
        """States per training window: H history states and T futures."""
        return self.dynamics.history + self.horizon


@dataclass(frozen=True)
class WorldModelProfile:
    """A named size: the config plus the batch size and step budget it is meant for."""

    config: WorldModelConfig
    batch_size: int
    max_steps: int


def world_model_profile(name: str, phase: int = 1, task: str = "pusht") -> WorldModelProfile:
    """``cpu``: 256x4 MLP, T = 16, trains on 2 cores; ``tiny``: seconds-long runs for tests."""
    if name == "cpu":
        dynamics, horizon, batch = DynamicsConfig(width=256, depth=4), 16, 256
        steps = 6000 if phase == 1 else 2000
        optim = OptimConfig(lr=1e-3 if phase == 1 else 3e-4, betas=(0.9, 0.999), warmup_steps=200 if phase == 1 else 50)
    elif name == "tiny":
        dynamics, horizon, batch, steps = DynamicsConfig(width=32, depth=2), 8, 32, 30
        optim = OptimConfig(lr=3e-3, betas=(0.9, 0.999), warmup_steps=2)
    else:
        raise ValueError(f"profile {name!r}: use one of {', '.join(PROFILES)}")
    config = WorldModelConfig(task=task, dynamics=dynamics, horizon=horizon, phase=phase, optim=optim)
    return WorldModelProfile(config, batch, steps)


def with_network_of(config: WorldModelConfig, source: WorldModelConfig) -> WorldModelConfig:
    """``config``'s training settings on ``source``'s network (phase 2 keeps phase 1's network)."""
    if source.task != config.task or source.obs_type != config.obs_type:
        raise ValueError(
            f"the initial model is for task {source.task!r} / obs {source.obs_type!r}, "
            f"not {config.task!r} / {config.obs_type!r}"
        )
    return dataclasses.replace(config, dynamics=source.dynamics)
