"""What every training run shares: the optimiser recipe, the run's own settings, and named profiles.

A component's config (policy, world model, reward predictor) says what the network is and how
it learns (``optim``, optionally ``ema``); ``RunConfig`` says where a run writes and how
Lightning runs it; a ``Profile`` pairs a config with the batch size and step budget it is
meant for.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

C = TypeVar("C")


@dataclass(frozen=True)
class OptimConfig:
    """AdamW with a cosine learning-rate schedule after a linear warm-up (Diffusion Policy's)."""

    lr: float = 1e-4  # peak learning rate
    betas: tuple[float, float] = (0.95, 0.999)  # AdamW moment decay rates
    weight_decay: float = 1e-6  # AdamW decoupled weight decay
    warmup_steps: int = 500  # linear warm-up from 0 to lr, then cosine decay to 0 at the last step

    def __post_init__(self) -> None:
        if self.lr <= 0 or self.weight_decay < 0 or self.warmup_steps < 0:
            raise ValueError(f"optimiser: lr {self.lr} must be > 0, weight_decay and warmup_steps >= 0")
        if len(self.betas) != 2 or not all(0 <= b < 1 for b in self.betas):
            raise ValueError(f"AdamW betas {self.betas}: need two values in [0, 1)")


@dataclass(frozen=True)
class RunConfig:
    """Where one run writes and how Lightning runs it (the network's own settings are in its config)."""

    run_dir: Path  # output directory (checkpoints/, tensorboard/, run.json)
    max_steps: int | None = None  # optimiser steps in total, counted from the run's start (resume included)
    max_epochs: int | None = None  # alternatively (or also) a number of passes over the training windows
    batch_size: int = 256  # windows per optimiser step (per device under DDP)
    accelerator: str = "auto"  # Lightning accelerator: cpu, gpu, auto
    devices: int | str = 1  # devices per node (an int, or "auto")
    strategy: str = "auto"  # Lightning strategy: auto, ddp, ddp_spawn, ...
    num_nodes: int = 1  # machines
    precision: str = "32-true"  # Lightning precision: 32-true, bf16-mixed, 16-mixed, or bf16-auto (trainer.resolve_precision)
    seed: int = 0  # seeds weights, shuffling and noise (shifted by the step count on resume)
    resume: bool = False  # continue from run_dir/checkpoints/last.ckpt
    progress: bool = True  # rich progress bar
    checkpoint_every: int = 500  # optimiser steps between refreshes of last.ckpt
    checkpoint_minutes: float | None = 10.0  # also refresh it once this long has passed (slow steps lose little)
    val_every: int | None = None  # optimiser steps between validations (None: once per epoch)
    val_ratio: float = 0.05  # fraction of episodes held out for validation
    num_workers: int = 0  # DataLoader worker processes
    log_every: int = 50  # optimiser steps between logged training metrics

    def __post_init__(self) -> None:
        for name in ("max_steps", "max_epochs", "val_every"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"{name} {value}: must be at least 1")
        for name in ("batch_size", "num_nodes", "checkpoint_every", "log_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} {getattr(self, name)}: must be at least 1")
        if self.checkpoint_minutes is not None and not self.checkpoint_minutes > 0:
            raise ValueError(f"checkpoint_minutes {self.checkpoint_minutes}: must be above 0")
        if self.max_steps is None and self.max_epochs is None:
            raise ValueError("give max_steps or max_epochs")


@dataclass(frozen=True)
class Profile(Generic[C]):
    """A named size: a component's config plus the batch size and step budget it is meant for."""

    config: C
    batch_size: int
    max_steps: int

    def run(self, run_dir: Path, max_steps: int | None = None, max_epochs: int | None = None, batch_size: int | None = None,
            **lightning: Any) -> RunConfig:
        """A run of this profile: its step budget and batch size unless given (``max_epochs`` alone replaces the budget)."""
        steps = max_steps if max_steps or max_epochs else self.max_steps
        return RunConfig(run_dir=Path(run_dir), max_steps=steps, max_epochs=max_epochs, batch_size=batch_size or self.batch_size,
                         **lightning)
