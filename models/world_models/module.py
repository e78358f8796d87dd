"""The world-model LightningModule: either dynamics (state MLP or visual EDM) under the one training contract.

``WorldModelModule`` wraps ``StateDynamics`` (``state``) or ``VisualDynamics`` (``visual``),
chosen by ``config.obs_type``, for training (batch in, loss and logs out, through
``TrainableModule``) and checkpoints (``kind="world_model"``, task, obs, phase);
``WorldModelModule.load_from_checkpoint(path)`` alone rebuilds it, normaliser included.

Training on stores (``gpc.models.training.trainer.train``): windows of the history and T
futures (histories padded at episode starts, futures never). Phase 2 starts from a phase-1
checkpoint (``init``): its network config, held-out episodes, normaliser and weights are
taken as they are, with a fresh optimiser and phase 2's own schedule; ``find_phase_one``
finds that checkpoint beside a phase-2 run directory. A visual model records the frame size
of its training stores (``source_size``); a store of another size is resized with a warning.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from gpc.datasets.datamodule import DataConfig, EpisodeDataModule
from gpc.datasets.errors import DataError
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.datasets.windows import EpisodeArrays
from gpc.models.networks.precision import check_rollout_precision
from gpc.models.training.config import RunConfig
from gpc.models.training.module import TrainableModule
from gpc.models.world_models.config import (
    KIND,
    AnyWorldModelConfig,
    VisualWorldModelConfig,
    config_from_dict,
    with_network_of,
)
from gpc.models.world_models.state import ACTION_KEY, DELTA_KEY, STATE_KEY, StateDynamics, delta_statistics
from gpc.models.world_models.visual import VisualDynamics

LAST = "last.ckpt"
_PHASE_TAGS = (("phase2", "phase1"), ("phase-2", "phase-1"), ("phase_2", "phase_1"))


class WorldModelModule(TrainableModule):
    """A world model (state or image) for one task: batch in, loss and logs out; ``rollout`` for planners."""

    KIND, WHAT = KIND, "world model"

    def __init__(self, config: AnyWorldModelConfig | Mapping[str, Any], normalizer: MinMaxNormalizer | None = None,
                 data: Mapping[str, Any] | None = None) -> None:
        config = config_from_dict(config)
        super().__init__(config, data)
        self.config: AnyWorldModelConfig = config
        visual = isinstance(config, VisualWorldModelConfig)
        self.dynamics: StateDynamics | VisualDynamics = (VisualDynamics if visual else StateDynamics)(config.dynamics, normalizer)  # type: ignore[arg-type]
        self._teacher: tuple[VisualDynamics] | None = None  # in a tuple: not a submodule, not in the checkpoint
        self.track_ema()

    @property
    def n_obs_steps(self) -> int:
        return self.dynamics.n_obs_steps

    @property
    def obs_key(self) -> str:
        """The observation a planner feeds this model's history from (``img`` frames or ``state``)."""
        return self.config.obs_key

    def rollout(self, history: torch.Tensor | np.ndarray, actions: torch.Tensor | np.ndarray, **options: Any) -> torch.Tensor:
        """See ``WorldModel.rollout`` and the dynamics' ``rollout`` (the visual one takes ``noise`` and
        ``generator``); arrays are moved to the module's device as float32."""
        history = torch.as_tensor(history, dtype=torch.float32, device=self.device)
        actions = torch.as_tensor(actions, dtype=torch.float32, device=self.device)
        return self.dynamics.rollout(history, actions, **options)

    def set_rollout_precision(self, precision: str) -> str:
        """Rollouts at ``precision`` (``gpc.models.networks.precision.ROLLOUT_PRECISIONS``) from now on.

        Returns the dtype they run in on this device, ``bfloat16`` or ``float32``: it changes the numbers, so
        results record it. A state model always rolls out in float32.
        """
        check_rollout_precision(precision)
        if isinstance(self.dynamics, VisualDynamics):
            self.dynamics.precision = precision
            return "bfloat16" if self.dynamics.bf16(self.device.type) else "float32"
        return "float32"

    # ------------------------------------------------------------------ the training contract
    @property
    def network(self) -> nn.Module:
        return self.dynamics

    def loss(self, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        if isinstance(self.config, VisualWorldModelConfig) and self.config.distill_from:
            assert isinstance(self.dynamics, VisualDynamics)  # a visual config builds visual dynamics
            return self.dynamics.window_loss(batch, self.config, self.teacher())
        return self.dynamics.window_loss(batch, self.config)  # type: ignore[arg-type]

    def teacher(self) -> VisualDynamics:
        """The distillation teacher's dynamics, frozen, loaded once from ``config.distill_from`` (kept out of the
        checkpoint: a student plans alone)."""
        if self._teacher is None:
            assert isinstance(self.config, VisualWorldModelConfig) and self.config.distill_from
            loaded = load_world_model(self.config.distill_from, self.config.task).dynamics
            if not isinstance(loaded, VisualDynamics):
                raise ValueError(f"{self.config.distill_from}: a state world model cannot teach a visual one")
            self._teacher = (loaded.to(self.device).eval().requires_grad_(False),)
        return self._teacher[0]

    def check_ready(self) -> None:
        self.dynamics.check_normalizer()

    def record(self) -> dict[str, Any]:
        return {"obs": self.config.obs_type, "phase": self.config.phase}

    @classmethod
    def config_from_dict(cls, data: Any) -> AnyWorldModelConfig:
        return config_from_dict(data)

    @classmethod
    def data_config(cls, config: AnyWorldModelConfig, datasets: tuple[str, ...], run: RunConfig,
                    split: tuple[int, float]) -> DataConfig:
        """Windows of the history and T futures (observations and actions)."""
        return DataConfig(
            paths=datasets, obs_keys=(config.obs_key,), action_key=ACTION_KEY, horizon=config.window,
            n_obs_steps=config.n_obs_steps, n_action_steps=1, obs_steps_override=config.window, val_ratio=split[1],
            seed=split[0], batch_size=run.batch_size, num_workers=run.num_workers,
        )

    @classmethod
    def fit_to_data(cls, config: AnyWorldModelConfig, arrays: EpisodeArrays, source: str, resumed: bool) -> AnyWorldModelConfig:
        return check_observations(config, arrays, source)

    @classmethod
    def from_data(cls, config: AnyWorldModelConfig, data: EpisodeDataModule, record: dict[str, Any]) -> WorldModelModule:
        """State models z-score their one-step deltas by statistics of the training episodes."""
        normalizer = data.normalizer
        if not isinstance(config, VisualWorldModelConfig):
            lo, hi = delta_statistics(data.arrays.data[STATE_KEY], data.arrays.episode_ends, data.train_episodes,
                                      config.dynamics.angle_dims)
            normalizer.add(DELTA_KEY, lo, hi)
        return cls(config, normalizer=normalizer, data=record)

    @classmethod
    def check_resume(cls, stored: AnyWorldModelConfig, given: AnyWorldModelConfig, path: str) -> None:
        super().check_resume(stored, given, path)
        if stored.phase != given.phase:
            raise DataError(f"{path}: the run is phase {stored.phase}, not phase {given.phase}")

    @classmethod
    def check_start(cls, config: AnyWorldModelConfig) -> None:
        if config.phase == 2:
            raise DataError("phase 2 starts from phase-1 weights: pass init (--init PHASE1_RUN/checkpoints/last.ckpt)")

    @classmethod
    def continue_from(cls, config: AnyWorldModelConfig, stored: AnyWorldModelConfig, path: str) -> AnyWorldModelConfig:
        """Phase 2 (or a restart) keeps the initial model's network."""
        try:
            return with_network_of(config, stored)
        except ValueError as exc:
            raise DataError(f"{path}: {exc}") from None


def check_observations(config: AnyWorldModelConfig, arrays: EpisodeArrays, source: str | os.PathLike) -> AnyWorldModelConfig:
    """Refuse stores whose observations or actions do not fit ``config``; a visual config gets the
    stores' frame size as ``source_size`` (a size other than a recorded one is resized, with a warning)."""
    dyn = config.dynamics
    actions = tuple(arrays.data[ACTION_KEY].shape[1:])
    if actions != (dyn.action_dim,):
        raise DataError(f"{source}: data/{ACTION_KEY} rows are {actions}, the world model needs ({dyn.action_dim},)")
    shape = tuple(arrays.data[config.obs_key].shape[1:])
    if not isinstance(config, VisualWorldModelConfig):
        if shape != (config.dynamics.state_dim,):
            raise DataError(f"{source}: data/{config.obs_key} rows are {shape}, the world model needs "
                            f"({config.dynamics.state_dim},)")
        return config
    vis = config.dynamics
    if len(shape) != 3 or shape[0] != shape[1] or shape[2] != vis.img_channels:
        raise DataError(f"{source}: data/{config.obs_key} frames are {shape}; the visual world model needs square "
                        f"(S, S, {vis.img_channels}) RGB frames")
    if vis.source_size is not None and vis.source_size != shape[0]:
        warnings.warn(f"{source}: frames are {shape[0]} px, the model's earlier training used {vis.source_size} px; "
                      f"resizing {shape[0]} -> {vis.resolution} px", stacklevel=2)
        return config
    return dataclasses.replace(config, dynamics=dataclasses.replace(vis, source_size=shape[0]))


def find_phase_one(out: str | os.PathLike) -> Path:
    """``last.ckpt`` of the phase-1 run beside the phase-2 run directory ``out``.

    ``runs/wm-phase2`` looks in ``runs/wm-phase1`` (also ``phase-2``/``phase_2``); any other
    name ``NAME`` looks in ``NAME-phase1``.
    """
    out = Path(out)
    names = [out.name.replace(a, b) for a, b in _PHASE_TAGS if a in out.name] + [f"{out.name}-phase1"]
    candidates = [out.with_name(n) / "checkpoints" / LAST for n in dict.fromkeys(names)]
    for path in candidates:
        if path.is_file():
            return path
    raise DataError(
        f"phase 2 starts from phase-1 weights and found none (looked for {', '.join(map(str, candidates))}); "
        "pass --init PHASE1_RUN/checkpoints/last.ckpt"
    )


def load_world_model(path: str | os.PathLike, task: str | None = None) -> WorldModelModule:
    """A world-model checkpoint of either kind (state MLP or visual EDM), from its record alone."""
    return WorldModelModule.load_from_checkpoint(path, task=task)
