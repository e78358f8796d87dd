"""World-model configs (the network each is, how it learns); their named sizes are in ``profiles``.

Two kinds share one training recipe (``_TrainingConfig``) and one checkpoint kind
(``world_model``), told apart by ``obs_type``:

- ``WorldModelConfig`` (``obs_type="state"``): an MLP single-step state predictor
  (``DynamicsConfig``);
- ``VisualWorldModelConfig`` (``obs_type="image"``): an EDM single-step frame predictor
  (``VisualDynamicsConfig``: U-Net, EDM process, Euler sampler, resolution, frameskip).

``config_from_dict`` rebuilds either from a checkpoint's plain dict.

Two-phase training is one implementation with two settings of ``unroll``:

- phase 1 (``unroll = 1``): every window supplies its predictions one step at a time, each
  from the true history (teacher forcing);
- phase 2 (``unroll`` = all predicted steps by default): the predictor is applied recursively
  from the window's true history and every prediction is supervised. Phase 2 starts from
  phase-1 weights and keeps phase 1's network and normaliser.

State: phase 1 measures errors in one-step-delta standard deviations, phase 2 in state ranges
(``loss_units``): on the human Push-T data, delta units in phase 2 let the agent's
rollout error grow from 0.6 to 5 px while the block improved, state units held it near 1.5 px.

Timeline of one state training window (history H = 2, horizon T = 4), index 0 = oldest state::

    states   | s0 s1 | s2 s3 s4 s5 |      s0, s1: history; s2..s5: supervised futures
    actions  |    a1 | a2 a3 a4    |      a_i moves s_i to s_{i+1} (Diffusion Policy's layout)

A visual window (H = 2 frames, frameskip 2, T = 4 actions) reads every ``frameskip``-th frame::

    frames   | o0 .  o2 | .  o4 .  o6 |   o0, o2: context; o4, o6: supervised predictions
    actions  |       a2 | a3 a4 a5    |   o4 follows (a2, a3), o6 follows (a4, a5)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from gpc.datasets.layout import TaskLayout
from gpc.models.networks.edm import EDMConfig, EulerConfig
from gpc.models.networks.mlp import ACTIVATIONS
from gpc.models.networks.unet2d import UNet2DConfig
from gpc.models.training.config import OptimConfig
from gpc.models.training.config_io import PlainConfig

KIND = "world_model"
OBS_TYPES = ("state", "image")
PROFILES = ("cpu", "tiny", "paper")
LOSS_UNITS = ("delta", "state")
FEEDBACK = ("denoised", "sampled")
FRAMES = ("object", "world")  # state models: contact features in the block's frame, or world coordinates only
IMAGE_KEY = "img"


@dataclass(frozen=True)
class DynamicsConfig:
    """What the single-step predictor reads and its size (fixed once phase 1 has trained it).

    The state layout comes from the task (``for_layout``); the rest is the network's size.
    """

    state_dim: int  # entries of one state vector
    action_dim: int  # entries of one action
    history: int = 2  # H: states the predictor reads (the last one is the current state)
    angle_dims: tuple[int, ...] = ()  # state entries that are angles (fed as cos, sin; predicted as wrapped deltas)
    action_target_dims: tuple[int, ...] = ()  # state entries the action is a target for (fed as action - state); () for none
    width: int = 256  # hidden units per layer
    depth: int = 4  # hidden layers
    activation: str = "silu"  # silu, gelu, mish or relu
    layer_norm: bool = False  # LayerNorm after each hidden Linear
    # (x, y, angle) entries of a rigid object: contact features and its motion in its own frame; () for none
    object_frame: tuple[int, ...] = ()
    object_length: float = 1.0  # object-frame offsets are divided by this (state units: about the object's size)

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
        if self.object_frame:
            frame = self.object_frame
            if len(frame) != 3 or len(set(frame)) != 3 or not all(0 <= d < self.state_dim for d in frame):
                raise ValueError(f"object_frame {frame}: need three distinct state entries (x, y, angle)")
            if frame[2] not in self.angle_dims or {frame[0], frame[1]} & set(self.angle_dims):
                raise ValueError(f"object_frame {frame}: its third entry must be an angle and the first two positions")
            if len(self.action_target_dims) not in (0, 2):
                raise ValueError("object_frame needs planar (2-entry) action targets, or none")
            if self.object_length <= 0:
                raise ValueError(f"object_length {self.object_length}: must be > 0")

    @classmethod
    def for_layout(cls, layout: TaskLayout, frame: str | None = None, **sizes: Any) -> DynamicsConfig:
        """The task's state layout with the given network sizes; ``frame="object"`` (the default when the
        first object has an angle) adds its object-frame features."""
        s = layout.state
        obj = layout.primary if layout.objects else None
        if frame == "object" and (obj is None or not obj.frame):
            what = f"task {layout.name}'s {obj.name} has none" if obj is not None else f"task {layout.name} has no object"
            raise ValueError(f"--frame object needs an object with an angle; {what} (use world)")
        use_object = obj is not None and (bool(obj.frame) if frame is None else frame == "object")
        return cls(state_dim=s.dim, action_dim=layout.action.dim, angle_dims=s.angle_dims, action_target_dims=s.action_targets,
                   object_frame=obj.frame if obj is not None and use_object else (), object_length=obj.size if obj is not None else 1.0,
                   **sizes)

    @property
    def object_points(self) -> int:
        """Planar points seen from the object's current frame: the action targets' positions at each
        history step and the action, and the object's own earlier positions."""
        if not self.object_frame:
            return 0
        return (self.history + 1 if self.action_target_dims else 0) + self.history - 1

    @property
    def linear_dims(self) -> tuple[int, ...]:
        """State entries that are not angles (fed normalised, predicted as deltas)."""
        return tuple(i for i in range(self.state_dim) if i not in self.angle_dims)

    @property
    def in_dim(self) -> int:
        """Input width: per history state the linear entries and cos, sin of the angles; the H - 1
        consecutive differences; the action; the action relative to its target entries; the
        object-frame points."""
        per_state = len(self.linear_dims) + 2 * len(self.angle_dims)
        return (self.history * per_state + (self.history - 1) * self.state_dim + self.action_dim
                + len(self.action_target_dims) + 2 * self.object_points)


@dataclass(frozen=True)
class VisualDynamicsConfig:
    """The visual single-step predictor: frame size, context, action conditioning and its diffusion stack.

    Frames are RGB ``resolution`` px squares scaled to [-1, 1]. A prediction reads ``history``
    frames spaced ``frameskip`` steps apart (the last is the current frame) and the
    ``frameskip`` actions that follow it, and predicts the frame ``frameskip`` steps later.
    """

    resolution: int = 48  # S: the model's frame size (stores are resized to it)
    history: int = 4  # H: context frames per prediction
    frameskip: int = 4  # actions consumed per predicted frame (and the spacing of context frames)
    action_dim: int = 2  # entries of one action
    img_channels: int = 3  # colour channels
    unet: UNet2DConfig = field(default_factory=UNet2DConfig)  # the inner network
    edm: EDMConfig = field(default_factory=EDMConfig)  # the training noise process
    sampler: EulerConfig = field(default_factory=EulerConfig)  # inference: Euler steps, frozen or sampled noise
    action_maps: bool = True  # also draw each action of the step as a Gaussian blob channel beside the context
    action_extent: tuple[float, float] = (0.0, 1.0)  # action coordinates at the frame's first and last pixel edge (the task's frame)
    action_map_sigma: float = 0.03  # blob standard deviation, in action units (the task's drawn agent size)
    motion_weight: float = 0.0  # training: pixels weigh 1 + this x their change since the previous frame (mean |diff| in [-1, 1] units)
    source_size: int | None = None  # frame size of the training stores (filled from the data; others are resized with a warning)
    bf16: bool = False  # rollouts under bfloat16 autocast where the hardware has it (networks.precision); float32 elsewhere
    channels_last: bool = False  # keep the U-Net's weights channels-last (about 9% off a planning decision on CPU)

    def __post_init__(self) -> None:
        for name in ("resolution", "history", "frameskip", "action_dim", "img_channels"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} {getattr(self, name)}: must be at least 1")
        if self.resolution < self.unet.downsampling:
            raise ValueError(f"resolution {self.resolution} is smaller than the U-Net's downsampling {self.unet.downsampling}")
        lo, hi = self.action_extent
        if not hi > lo or self.action_map_sigma <= 0:
            raise ValueError(f"action_extent {self.action_extent} must increase and action_map_sigma be > 0")
        if self.motion_weight < 0:
            raise ValueError(f"motion_weight {self.motion_weight}: must be >= 0")
        if self.source_size is not None and self.source_size < 1:
            raise ValueError(f"source_size {self.source_size}: must be at least 1")

    @property
    def n_obs_steps(self) -> int:
        """Observation steps a rollout reads: H frames spaced ``frameskip`` apart."""
        return (self.history - 1) * self.frameskip + 1

    @property
    def context_channels(self) -> int:
        """Channels beside the noisy frame: the H context frames and, with ``action_maps``, one map per action."""
        return self.history * self.img_channels + (self.frameskip if self.action_maps else 0)

    @property
    def cond_dim(self) -> int:
        """Entries of the action conditioning vector: the step's ``frameskip`` normalised actions."""
        return self.frameskip * self.action_dim


@dataclass(frozen=True)
class _TrainingConfig(PlainConfig):
    """What every world model shares: its task, training windows and phase, and the optimiser."""

    task: str = ""  # task the model is trained for (required); checked when a checkpoint is loaded
    horizon: int = 16  # T: actions per training window
    phase: int = 1  # 1: one-step loss; 2: unrolled loss from phase-1 weights
    unroll: int | None = None  # predictions per unrolled segment (default: 1 in phase 1, all of the window's in phase 2)
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=1e-3, betas=(0.9, 0.999), warmup_steps=200))

    def __post_init__(self) -> None:
        if not self.task:
            raise ValueError("task must be named")
        if getattr(self, "obs_type", None) not in OBS_TYPES:
            raise ValueError(f"world model obs {getattr(self, 'obs_type', None)!r}: use one of {', '.join(OBS_TYPES)}")
        if self.horizon < 1:
            raise ValueError(f"horizon {self.horizon}: must be at least 1")
        if self.phase not in (1, 2):
            raise ValueError(f"phase {self.phase}: use 1 (one-step loss) or 2 (unrolled loss)")
        if self.phase == 1 and self.unroll not in (None, 1):
            raise ValueError(f"phase 1 supervises single steps; unroll {self.unroll} needs phase 2")
        if self.phase == 2 and self.unroll is not None and self.unroll < 2:
            raise ValueError(f"phase 2 unroll {self.unroll}: must be at least 2 (unroll 1 is phase 1)")
        if self.predicted_steps % self.unroll_steps:
            raise ValueError(f"unroll {self.unroll_steps} must divide the {self.predicted_steps} predictions per window")

    @property
    def predicted_steps(self) -> int:
        """Predictions per training window."""
        return self.horizon

    @property
    def n_obs_steps(self) -> int:
        """Observation steps before the window's first action (the history a rollout reads)."""
        raise NotImplementedError

    @property
    def unroll_steps(self) -> int:
        if self.unroll is not None:
            return self.unroll
        return 1 if self.phase == 1 else self.predicted_steps

    @property
    def window(self) -> int:
        """Steps per training window: the history and T futures."""
        return self.n_obs_steps + self.horizon


@dataclass(frozen=True)
class WorldModelConfig(_TrainingConfig):
    """A state world model: the single-step MLP predictor, its training windows and its phase."""

    obs_type: str = "state"  # observations predicted
    dynamics: DynamicsConfig = field(kw_only=True)  # the network (its state layout is the task's: DynamicsConfig.for_layout)
    detach_feedback: bool = False  # phase 2: stop gradients through the fed-back predictions
    loss_units: str | None = None  # error scale per state entry: delta (one-step delta std) or state (data range); default by phase

    def __post_init__(self) -> None:
        if self.obs_type != "state":
            raise ValueError(f"WorldModelConfig predicts states, not {self.obs_type!r} (see VisualWorldModelConfig)")
        super().__post_init__()
        if self.loss_units not in (None,) + LOSS_UNITS:
            raise ValueError(f"loss_units {self.loss_units!r}: use one of {', '.join(LOSS_UNITS)}")

    @property
    def n_obs_steps(self) -> int:
        return self.dynamics.history

    @property
    def obs_key(self) -> str:
        return "state"

    @property
    def loss_scale(self) -> str:
        """Units of the training error: one-step-delta standard deviations in phase 1 (each entry's
        next-step change predicted equally well), state ranges in phase 2 (a pixel of drift
        costs the same for the agent and the block, whose one-step changes are ten times smaller)."""
        if self.loss_units is not None:
            return self.loss_units
        return "delta" if self.phase == 1 else "state"


@dataclass(frozen=True)
class VisualWorldModelConfig(_TrainingConfig):
    """A visual world model: the EDM frame predictor applied every ``frameskip`` actions.

    Phase 1 denoises each of the window's ``horizon / frameskip`` frames from the true
    context; phase 2 unrolls: each step's context holds the previous steps' ``feedback``
    frames (detached), ``denoised`` being the one-step estimate at the training noise level
    (the official GPC code), ``sampled`` the sampler's frame (what a rollout feeds back).
    With ``distill_from``, a student started from that teacher learns to give, in its own
    sampler's steps, the frame the teacher's sampler gives from the same context and
    (perturbed) actions: planning pays per sampler step, in every rollout and gradient.
    """

    obs_type: str = "image"  # observations predicted
    dynamics: VisualDynamicsConfig = field(default_factory=VisualDynamicsConfig)  # the network
    feedback: str = "denoised"  # phase 2: frame fed back as context (denoised or sampled)
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=3e-4, betas=(0.9, 0.999), weight_decay=1e-2, warmup_steps=200))
    distill_from: str | None = None  # a teacher checkpoint: learn to give its sampler's frames in this model's fewer steps
    distill_action_noise: float = 0.05  # distillation: actions moved by up to this share of the action extent (planners' chunks)

    def __post_init__(self) -> None:
        if self.obs_type != "image":
            raise ValueError(f"VisualWorldModelConfig predicts images, not {self.obs_type!r}")
        if self.horizon % self.dynamics.frameskip:
            raise ValueError(f"horizon {self.horizon} must be a multiple of frameskip {self.dynamics.frameskip}")
        if self.feedback not in FEEDBACK:
            raise ValueError(f"feedback {self.feedback!r}: use one of {', '.join(FEEDBACK)}")
        if not 0 <= self.distill_action_noise <= 1:
            raise ValueError(f"distill_action_noise {self.distill_action_noise}: a share of the action extent in [0, 1]")
        super().__post_init__()

    @property
    def predicted_steps(self) -> int:
        return self.horizon // self.dynamics.frameskip

    @property
    def n_obs_steps(self) -> int:
        return self.dynamics.n_obs_steps

    @property
    def obs_key(self) -> str:
        return IMAGE_KEY


AnyWorldModelConfig = WorldModelConfig | VisualWorldModelConfig


def config_from_dict(data: Mapping[str, Any] | AnyWorldModelConfig) -> AnyWorldModelConfig:
    """A state or visual world-model config from its plain dict (``obs_type`` decides), or as given."""
    if isinstance(data, (WorldModelConfig, VisualWorldModelConfig)):
        return data
    if not isinstance(data, Mapping):
        raise ValueError(f"world model config: expected a mapping, got {type(data).__name__}")
    cls = VisualWorldModelConfig if data.get("obs_type") == "image" else WorldModelConfig
    return cls.from_dict(data)


def with_network_of(config: AnyWorldModelConfig, source: AnyWorldModelConfig) -> AnyWorldModelConfig:
    """``config``'s training settings on ``source``'s network (phase 2 keeps phase 1's network)."""
    if source.task != config.task or source.obs_type != config.obs_type:
        raise ValueError(
            f"the initial model is for task {source.task!r} / obs {source.obs_type!r}, "
            f"not {config.task!r} / {config.obs_type!r}"
        )
    if isinstance(config, WorldModelConfig) and isinstance(source, WorldModelConfig):
        return dataclasses.replace(config, dynamics=source.dynamics)
    assert isinstance(config, VisualWorldModelConfig) and isinstance(source, VisualWorldModelConfig)  # same obs_type
    # the sampler and the memory layout are not the network: a distillation student keeps its own
    dynamics = dataclasses.replace(source.dynamics, sampler=config.dynamics.sampler, channels_last=config.dynamics.channels_last)
    return dataclasses.replace(config, dynamics=dynamics)
