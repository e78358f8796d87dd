"""One training run: Zarr stores -> DataModule -> LightningModule -> checkpoints in a run directory.

``train_policy`` trains the policy; ``fit_module`` is the loop any of our LightningModules
runs in (the world model's ``train_world_model`` uses it too).

Run directory layout::

    RUN_DIR/run.json                 what was trained on what (written by rank 0)
    RUN_DIR/checkpoints/last.ckpt    refreshed every ``checkpoint_every`` steps and at the end
    RUN_DIR/checkpoints/best.ckpt    lowest validation loss (EMA weights) so far
    RUN_DIR/tensorboard/             TensorBoard events

``resume=True`` continues from ``last.ckpt`` (weights, EMA, optimiser, schedule, step
count); the checkpoint's own policy config wins over the one passed in. A non-finite loss
skips that update, stops training and raises ``TrainingDiverged`` after ``last.ckpt`` has
been written with the last good weights.
"""

from __future__ import annotations

import json
import logging
import os
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback, LearningRateMonitor, ModelCheckpoint, RichProgressBar
from lightning.pytorch.loggers import TensorBoardLogger
from lightning.pytorch.utilities import rank_zero_only

from datasets.datamodule import DataConfig, EpisodeDataModule
from datasets.errors import DataError
from models.checkpoint import read_checkpoint
from models.policy import KIND, PolicyModule
from models.policy_config import PolicyConfig

LAST, BEST = "last.ckpt", "best.ckpt"


class _DropTips(logging.Filter):
    """Lightning advertises a cloud logger on every run; keep the console to what matters."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "Tip:" not in record.getMessage()


_LIGHTNING_LOG = logging.getLogger("lightning.pytorch.utilities.rank_zero")
if not any(isinstance(f, _DropTips) for f in _LIGHTNING_LOG.filters):
    _LIGHTNING_LOG.addFilter(_DropTips())


class TrainingDiverged(ValueError):
    """The loss became NaN or infinite; the message names the step and the last good checkpoint."""


@dataclass(frozen=True)
class RunConfig:
    """Where one run writes and how Lightning runs it (the network's own settings are in PolicyConfig)."""

    run_dir: Path  # output directory (checkpoints/, tensorboard/, run.json)
    max_steps: int | None = None  # optimiser steps in total, counted from the run's start (resume included)
    max_epochs: int | None = None  # alternatively (or also) a number of passes over the training windows
    batch_size: int = 256  # windows per optimiser step (per device under DDP)
    accelerator: str = "auto"  # Lightning accelerator: cpu, gpu, auto
    devices: int | str = 1  # devices per node (an int, or "auto")
    strategy: str = "auto"  # Lightning strategy: auto, ddp, ddp_spawn, ...
    num_nodes: int = 1  # machines
    precision: str = "32-true"  # Lightning precision: 32-true, bf16-mixed, 16-mixed
    seed: int = 0  # seeds weights, shuffling and noise (shifted by the step count on resume)
    resume: bool = False  # continue from run_dir/checkpoints/last.ckpt
    progress: bool = True  # rich progress bar
    checkpoint_every: int = 500  # optimiser steps between refreshes of last.ckpt
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
        if self.max_steps is None and self.max_epochs is None:
            raise ValueError("give max_steps or max_epochs")


@dataclass(frozen=True)
class TrainResult:
    run_dir: Path
    last: Path
    best: Path | None
    global_step: int
    best_val_loss: float | None
    module: L.LightningModule  # the trained module as training left it (weights equal last.ckpt's)
    rank: int = 0  # this process's global rank (DDP runs return in every process)


class LastCheckpoint(Callback):
    """Writes ``last.ckpt`` every ``every`` steps and at the end, via a temporary file and a rename."""

    def __init__(self, path: Path, every: int) -> None:
        self.path, self.every = path, every
        self._saved_at = -1

    def _save(self, trainer: L.Trainer) -> None:
        tmp = self.path.with_name(self.path.name + ".tmp")
        trainer.save_checkpoint(tmp, weights_only=False)
        if trainer.is_global_zero:
            os.replace(tmp, self.path)
        trainer.strategy.barrier("gpc-last-checkpoint")
        self._saved_at = trainer.global_step

    def on_train_batch_end(self, trainer: L.Trainer, *args: object) -> None:
        if trainer.global_step % self.every == 0 and trainer.global_step != self._saved_at:
            self._save(trainer)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.global_step != self._saved_at:
            self._save(trainer)

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        # Ctrl-C in a single process: keep the progress (a collective save could hang under DDP).
        if isinstance(exception, KeyboardInterrupt) and trainer.world_size == 1 and trainer.global_step != self._saved_at:
            self._save(trainer)


class StepProgressBar(RichProgressBar):
    """Rich bar that shows the global step instead of the logger's version and an epoch bound of -1."""

    def get_metrics(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict:
        items = super().get_metrics(trainer, pl_module)
        items.pop("v_num", None)
        limit = trainer.max_steps
        items["step"] = f"{trainer.global_step}/{limit}" if limit > 0 else str(trainer.global_step)
        return items

    def _get_train_description(self, current_epoch: int) -> str:
        return f"epoch {current_epoch}"


def data_config(policy: PolicyConfig, datasets: Sequence[str | os.PathLike], run: RunConfig) -> DataConfig:
    return DataConfig(
        paths=tuple(str(p) for p in datasets), obs_keys=policy.obs_keys, horizon=policy.horizon,
        n_obs_steps=policy.n_obs_steps, n_action_steps=policy.n_action_steps, val_ratio=run.val_ratio,
        seed=run.seed, batch_size=run.batch_size, num_workers=run.num_workers,
    )


def _resumed_config(last: Path, policy: PolicyConfig) -> tuple[PolicyConfig, int]:
    ckpt = read_checkpoint(last, KIND, task=policy.task)
    stored = PolicyConfig.from_dict(ckpt["hyper_parameters"]["config"])
    if stored.obs_type != policy.obs_type:
        raise DataError(f"{last}: run was trained on obs {stored.obs_type!r}, not {policy.obs_type!r}")
    return stored, int(ckpt.get("global_step", 0))


@rank_zero_only
def _write_run_record(run_dir: Path, policy: PolicyConfig, datasets: Sequence[str], run: RunConfig) -> None:
    record = {"kind": KIND, "policy": policy.to_dict(), "datasets": list(datasets),
              "run": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(run).items()}}
    (run_dir / "run.json").write_text(json.dumps(record, indent=2))


def check_run_dir(run: RunConfig) -> Path:
    """``RUN_DIR/checkpoints/last.ckpt``, after refusing to resume nothing or to overwrite a run."""
    last = Path(run.run_dir) / "checkpoints" / LAST
    if run.resume:
        if not last.is_file():
            raise DataError(f"{run.run_dir}: nothing to resume (no checkpoints/{LAST}); drop --resume to start a run")
    elif last.exists():
        raise DataError(f"{run.run_dir}: already holds a training run; pass --resume to continue it or pick another --out")
    return last


def train_policy(policy: PolicyConfig, datasets: Sequence[str | os.PathLike], run: RunConfig) -> TrainResult:
    """Train (or resume) a policy on the given stores; returns where the checkpoints are."""
    run_dir = Path(run.run_dir)
    ckpt_dir = run_dir / "checkpoints"
    last = check_run_dir(run)
    start_step = 0
    if run.resume:
        policy, start_step = _resumed_config(last, policy)

    data = EpisodeDataModule(data_config(policy, datasets, run))
    shapes = {k: tuple(data.arrays.data[k].shape[1:]) for k in policy.obs_keys}
    if run.resume:
        stored = {k: tuple(v) for k, v in policy.encoder.obs_shapes}
        if stored != shapes:
            raise DataError(f"{last}: trained on observation shapes {stored}, the datasets have {shapes}")
    else:
        policy = policy.with_obs_shapes(shapes)
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    _write_run_record(run_dir, policy, [str(p) for p in datasets], run)

    L.seed_everything(run.seed + start_step, workers=True, verbose=False)
    module = PolicyModule(policy, normalizer=data.normalizer)
    return fit_module(module, data, run, validate=len(data.val_episodes) > 0)


def fit_module(module: L.LightningModule, data: L.LightningDataModule, run: RunConfig, validate: bool) -> TrainResult:
    """Run Lightning on any of our modules: last/best checkpoints, TensorBoard, resume, NaN stop.

    The module logs ``val/loss`` (when ``validate``) and sets ``diverged_at`` (a step, or
    ``None``) when its loss turns non-finite; ``last.ckpt`` is resumed when ``run.resume``.
    """
    run_dir = Path(run.run_dir)
    ckpt_dir = run_dir / "checkpoints"
    last = ckpt_dir / LAST
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    callbacks: list[Callback] = [LastCheckpoint(last, run.checkpoint_every), LearningRateMonitor("step")]
    best_cb = None
    if validate:
        best_cb = ModelCheckpoint(dirpath=ckpt_dir, filename=BEST[:-5], monitor="val/loss", mode="min", save_top_k=1,
                                  auto_insert_metric_name=False, enable_version_counter=False,
                                  save_on_train_epoch_end=False)
        callbacks.append(best_cb)
    if run.progress:
        callbacks.append(StepProgressBar())
    devices = int(run.devices) if isinstance(run.devices, str) and run.devices.isdigit() else run.devices
    trainer = L.Trainer(
        default_root_dir=run_dir, max_steps=run.max_steps or -1, max_epochs=run.max_epochs or (-1 if run.max_steps else None),
        accelerator=run.accelerator, devices=devices, strategy=run.strategy, num_nodes=run.num_nodes,
        precision=run.precision, logger=TensorBoardLogger(save_dir=run_dir, name="", version="tensorboard"),
        callbacks=callbacks, enable_progress_bar=run.progress, log_every_n_steps=run.log_every,
        val_check_interval=run.val_every, check_val_every_n_epoch=None if run.val_every else 1,
        num_sanity_val_steps=0, enable_model_summary=run.progress,
    )
    with warnings.catch_warnings():
        # The EMA copy is meant to stay in eval mode; Lightning would warn about it on every run.
        warnings.filterwarnings("ignore", message=r".*module\(s\) in eval mode.*")
        warnings.filterwarnings("ignore", message=r".*smaller than the logging interval.*")
        trainer.fit(module, datamodule=data, ckpt_path=last if run.resume else None, weights_only=True)
    diverged_at = getattr(module, "diverged_at", None)
    if diverged_at is not None:
        raise TrainingDiverged(
            f"loss became non-finite at step {diverged_at}; training stopped and {last} holds the last "
            "good weights (check the data, lower the learning rate or use 32-bit precision, then --resume)"
        )
    best = Path(best_cb.best_model_path) if best_cb is not None and best_cb.best_model_path else None
    score = best_cb.best_model_score if best_cb is not None else None
    return TrainResult(run_dir, last, best, trainer.global_step,
                       float(score) if isinstance(score, torch.Tensor) else None, module, trainer.global_rank)
