"""Named world-model sizes per observation type (``cpu``, ``tiny``, ``paper``), laid out for a task.

Kept apart from the config classes: these are the choices a user picks by name (and the measured settings
behind them), while ``config`` is the schema every checkpoint carries.
"""

from __future__ import annotations

import dataclasses

from gpc.datasets.layout import TaskLayout
from gpc.models.networks.unet2d import UNet2DConfig
from gpc.models.training.config import OptimConfig, Profile
from gpc.models.world_models.config import (
    FEEDBACK,
    FRAMES,
    OBS_TYPES,
    PROFILES,
    AnyWorldModelConfig,
    DynamicsConfig,
    VisualDynamicsConfig,
    VisualWorldModelConfig,
    WorldModelConfig,
)


def world_model_profile(name: str, phase: int, layout: TaskLayout, obs: str = "state", frame: str | None = None,
                        unroll: int | None = None, feedback: str | None = None) -> Profile[AnyWorldModelConfig]:
    """Named sizes per observation type, laid out for the task.

    State: ``cpu`` (256x4 MLP, T = 16, trains on 2 cores), ``tiny`` (seconds-long test runs).
    Image: ``cpu`` (48 px, U-Net (16, 32, 64), frameskip 4: a 16-action chunk is 4 predictions,
    0.9M parameters, bf16 rollouts where the hardware has them; train it with ``--precision bf16-auto``), ``tiny`` (16 px,
    tests), ``paper`` (96 px, U-Net 4 x 96 with two blocks per level and middle attention,
    conditioning 256, frameskip 1: the paper's model, GPU only).
    ``frame`` (state): ``object`` adds the object-frame features of ``DynamicsConfig.object_frame``
    (the default when the task's object has an angle), ``world`` keeps world coordinates only.
    ``unroll`` (phase 2): predictions per unrolled segment; ``feedback`` (image, phase 2): the frames fed back.
    """
    profile = _profile(name, phase, layout, obs, frame)
    if unroll is not None and phase != 2:
        raise ValueError("--unroll applies to phase 2")
    if feedback is not None:
        if not isinstance(profile.config, VisualWorldModelConfig) or phase != 2:
            raise ValueError(f"--feedback applies to --obs image --phase 2 and is one of {', '.join(FEEDBACK)}")
        profile = dataclasses.replace(profile, config=dataclasses.replace(profile.config, feedback=feedback))
    if unroll is not None:
        profile = dataclasses.replace(profile, config=dataclasses.replace(profile.config, unroll=unroll))
    return profile


def _profile(name: str, phase: int, layout: TaskLayout, obs: str, frame: str | None) -> Profile[AnyWorldModelConfig]:
    if obs not in OBS_TYPES:
        raise ValueError(f"world model obs {obs!r}: use one of {', '.join(OBS_TYPES)}")
    if frame is not None and frame not in FRAMES:
        raise ValueError(f"world model frame {frame!r}: use one of {', '.join(FRAMES)}")
    if obs == "image":
        return _visual_profile(name, phase, layout)
    if name == "cpu":
        width, depth, horizon, batch = 256, 4, 16, 256
        steps = 6000 if phase == 1 else 2000
        optim = OptimConfig(lr=1e-3 if phase == 1 else 3e-4, betas=(0.9, 0.999), warmup_steps=200 if phase == 1 else 50)
    elif name == "tiny":
        width, depth, horizon, batch, steps = 32, 2, 8, 32, 30
        optim = OptimConfig(lr=3e-3, betas=(0.9, 0.999), warmup_steps=2)
    else:
        raise ValueError(f"state world model profile {name!r}: use cpu or tiny")
    config = WorldModelConfig(task=layout.name, dynamics=DynamicsConfig.for_layout(layout, frame, width=width, depth=depth),
                              horizon=horizon, phase=phase, optim=optim)
    return Profile(config, batch, steps)


def _visual_profile(name: str, phase: int, layout: TaskLayout) -> Profile[AnyWorldModelConfig]:
    one = phase == 1
    if name == "cpu":
        unet = UNet2DConfig(channels=(16, 32, 64), depths=(1, 1, 1), cond_channels=128)
        dynamics = dict(resolution=48, history=4, frameskip=4, unet=unet, motion_weight=8.0, bf16=True, channels_last=True)
        horizon, batch, steps = 16, 8, 5000 if one else 1000  # batch 8 windows = 32 predictions per step
        optim = OptimConfig(lr=5e-4 if one else 2e-4, betas=(0.9, 0.999), weight_decay=1e-2, warmup_steps=200 if one else 20)
    elif name == "tiny":
        unet = UNet2DConfig(channels=(8, 8), depths=(1, 1), cond_channels=16, group_size=8)
        dynamics = dict(resolution=16, history=2, frameskip=2, unet=unet, motion_weight=4.0)
        horizon, batch, steps = 4, 8, 30
        optim = OptimConfig(lr=3e-3, betas=(0.9, 0.999), weight_decay=0.0, warmup_steps=2)
    elif name == "paper":
        unet = UNet2DConfig(channels=(96, 96, 96, 96), depths=(2, 2, 2, 2), cond_channels=256, mid_attention=True)
        dynamics = dict(resolution=96, history=4, frameskip=1, unet=unet, action_maps=False)
        horizon, batch, steps = 16, 32, 100_000 if one else 20_000
        optim = OptimConfig(lr=1e-4, betas=(0.9, 0.999), weight_decay=1e-2, warmup_steps=100)
    else:
        raise ValueError(f"visual world model profile {name!r}: use one of {', '.join(PROFILES)}")
    if layout.frame is None:
        raise ValueError(f"task {layout.name} renders no frames: it has no visual world model")
    visual = VisualDynamicsConfig(action_dim=layout.action.dim, action_extent=layout.frame.extent,
                                  action_map_sigma=layout.frame.marker_size, **dynamics)  # type: ignore[arg-type]
    config = VisualWorldModelConfig(task=layout.name, dynamics=visual, horizon=horizon, phase=phase, optim=optim)
    return Profile(config, batch, steps)


def distill_profile(name: str, teacher: AnyWorldModelConfig, teacher_path: str, sampler_steps: int = 1) -> Profile[AnyWorldModelConfig]:
    """A student of the visual model at ``teacher_path``: its network and windows, sampling in ``sampler_steps`` Euler
    steps, trained (from the teacher's weights) to give the teacher's frames; ``cpu``: 2,000 steps, ``tiny``: tests."""
    if not isinstance(teacher, VisualWorldModelConfig):
        raise ValueError(f"{teacher_path}: a {teacher.obs_type} world model; distillation shortens a visual model's sampler")
    if sampler_steps >= teacher.dynamics.sampler.steps:
        raise ValueError(f"--sampler-steps {sampler_steps}: the teacher samples in {teacher.dynamics.sampler.steps}; "
                         "a student takes fewer")
    if name == "cpu":
        batch, steps, optim = 8, 2000, OptimConfig(lr=1e-4, betas=(0.9, 0.999), weight_decay=1e-2, warmup_steps=50)
    elif name == "tiny":
        batch, steps, optim = 8, 10, OptimConfig(lr=1e-3, betas=(0.9, 0.999), weight_decay=0.0, warmup_steps=2)
    else:
        raise ValueError(f"distillation profile {name!r}: use cpu or tiny")
    sampler = dataclasses.replace(teacher.dynamics.sampler, steps=sampler_steps)  # a student plans: channels-last
    config = dataclasses.replace(teacher, dynamics=dataclasses.replace(teacher.dynamics, sampler=sampler, channels_last=True),
                                 distill_from=str(teacher_path), optim=optim)
    return Profile(config, batch, steps)
