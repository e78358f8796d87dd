"""One training run for any component: Zarr stores -> DataModule -> module -> checkpoints in a run directory.

``train(ModuleClass, config, datasets, run)`` trains a policy, a world model or a reward
predictor alike (``gpc.models.training.module.TrainableModule`` says what each supplies);
``fit_module`` is the Lightning loop inside it.

Run directory layout::

    RUN_DIR/run.json                 what was trained on what (written by rank 0)
    RUN_DIR/checkpoints/last.ckpt    refreshed every ``checkpoint_every`` steps, ``checkpoint_minutes`` and at the end
    RUN_DIR/checkpoints/best.ckpt    lowest validation loss so far
    RUN_DIR/tensorboard/             TensorBoard events

``resume=True`` continues from ``last.ckpt`` (weights, EMA, optimiser, schedule, step count,
held-out episodes), and only the same run: other data (by content) or settings are refused (``check_same_run``). ``init``
starts a new run from another checkpoint's weights (world-model phase 2 from phase 1),
keeping the episodes it held out. A non-finite loss skips that update, stops training and
raises ``TrainingDiverged`` after ``last.ckpt`` has been written with the last good weights.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
import time
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import Callback, LearningRateMonitor, ModelCheckpoint, RichProgressBar
from lightning.pytorch.loggers import TensorBoardLogger
from lightning.pytorch.utilities import rank_zero_only

from gpc.datasets.datamodule import EpisodeDataModule
from gpc.datasets.errors import DataError
from gpc.datasets.locks import exclusive
from gpc.datasets.sequence import identities, recorded_held_out, recorded_split
from gpc.datasets.store import EpisodeStore
from gpc.datasets.windows import EpisodeArrays
from gpc.models.networks.precision import native_bf16
from gpc.models.training.checkpoint import module_state, read_checkpoint
from gpc.models.training.config import RunConfig
from gpc.models.training.config_io import first_difference
from gpc.models.training.module import TrainableModule

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
class TrainResult:
    run_dir: Path
    last: Path
    best: Path | None
    global_step: int
    best_val_loss: float | None
    module: L.LightningModule  # the trained module as training left it (weights equal last.ckpt's)
    rank: int = 0  # this process's global rank (DDP runs return in every process)


class LastCheckpoint(Callback):
    """Writes ``last.ckpt`` every ``every`` steps, every ``minutes`` and at the end, via a temporary file and a
    rename. The clock bounds what a killed run loses when steps are slow (a CPU job beside another)."""

    def __init__(self, path: Path, every: int, minutes: float | None = None) -> None:
        self.path, self.every, self.seconds = path, every, None if minutes is None else 60.0 * minutes
        self._saved_at, self._saved_time = -1, time.monotonic()

    def _save(self, trainer: L.Trainer) -> None:
        tmp = self.path.with_name(self.path.name + ".tmp")
        try:
            trainer.save_checkpoint(tmp, weights_only=False)
        except BaseException:  # a full disk or a stop mid-write: the previous last.ckpt stays as it was
            tmp.unlink(missing_ok=True)
            raise
        if trainer.is_global_zero:
            os.replace(tmp, self.path)
        trainer.strategy.barrier("gpc-last-checkpoint")
        self._saved_at, self._saved_time = trainer.global_step, time.monotonic()

    def on_train_batch_end(self, trainer: L.Trainer, *args: object) -> None:
        due = trainer.global_step % self.every == 0
        if self.seconds is not None:  # rank 0's clock decides for all ranks, so the collective save stays in step
            due = bool(trainer.strategy.broadcast(due or time.monotonic() - self._saved_time >= self.seconds, src=0))
        if due and trainer.global_step != self._saved_at:
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


def check_run_dir(run: RunConfig) -> Path:
    """``RUN_DIR/checkpoints/last.ckpt``, after refusing to resume nothing or to overwrite a run."""
    run_dir = Path(run.run_dir)
    last = run_dir / "checkpoints" / LAST
    if run_dir.exists() and not run_dir.is_dir():
        raise DataError(f"{run_dir}: is a file; --out names the run's folder")
    if run.resume:
        if not last.is_file():
            held = " (it holds a run stopped before its first checkpoint: remove it to start again)" if _holds_run(run_dir) else ""
            raise DataError(f"{run_dir}: nothing to resume (no checkpoints/{LAST}){held}; drop --resume to start a run")
    elif _holds_run(run_dir):
        raise DataError(f"{run_dir}: already holds a training run; pass --resume to continue it or pick another --out")
    return last


def _holds_run(run_dir: Path) -> bool:
    """Whether anything a training run writes is there (a run killed before ``last.ckpt`` counts: never mix two)."""
    return (run_dir / "run.json").exists() or (run_dir / "tensorboard").exists() or any((run_dir / "checkpoints").glob("*.ckpt"))


@rank_zero_only
def _write_run_record(run_dir: Path, kind: str, config: Any, record: dict[str, Any], run: RunConfig) -> None:
    out = {"kind": kind, "config": config.to_dict(), **record,
           "run": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(run).items()}}
    tmp = run_dir / ".run.json.tmp"  # written whole: a reader never sees half of it
    tmp.write_text(json.dumps(out, indent=2))
    tmp.replace(run_dir / "run.json")


def store_digests(arrays: EpisodeArrays) -> list[str]:
    """SHA-256 of each store's steps as training reads them (its keys' rows and episode ends): a store whose content
    changed is other data, whatever its path."""
    out, first, row = [], 0, 0
    for count in arrays.counts:
        ends = np.asarray(arrays.episode_ends[first : first + count], dtype=np.int64)
        h = hashlib.sha256((ends - row).tobytes())
        stop = int(ends[-1])
        for key in sorted(arrays.data):
            part = np.ascontiguousarray(arrays.data[key][row:stop])
            h.update(f"{key} {part.dtype.str} {part.shape}".encode())
            h.update(part.data)  # C-contiguous: hashed in place
        out.append(h.hexdigest())
        first, row = first + count, stop
    return out


def check_same_run(earlier: dict[str, Any], record: dict[str, Any], stored: Any, given: Any, last: Path) -> None:
    """``--resume`` continues only the same run: the same data (each store's steps, in order; by real path where the
    checkpoint predates their digests), seed, batch size and component settings; the first difference is named.
    A store moved or copied elsewhere is the same data."""
    then, now, digests = earlier.get("datasets", []), record["datasets"], earlier.get("data_digests")
    same_stores = ([os.path.realpath(p) for p in then] == [os.path.realpath(p) for p in now] if digests is None
                   else len(digests) == len(now))
    if not same_stores:
        raise DataError(f"{last}: the run trained on --dataset {' '.join(map(str, then))}, not {' '.join(map(str, now))}; "
                        "--resume continues only the same run (train into another --out)")
    for old, path, held, here in zip(then, now, digests or [], record["data_digests"]):
        if held != here:
            raise DataError(f"{last}: --dataset {path} is not the data the run trained on ({old} then: the SHA-256 of its "
                            "steps differs); --resume continues only the same run (train into another --out)")
    keys = [key for key in ("seed", "batch_size") if key in earlier]
    held_settings: dict[str, Any] = {"config": stored.to_dict(), **{key: earlier[key] for key in keys}}
    given_settings: dict[str, Any] = {"config": given.to_dict(), **{key: record[key] for key in keys}}
    if held_settings != given_settings:
        raise DataError(f"{last}: --resume continues only the same run, and this one's settings differ "
                        f"({first_difference(held_settings, given_settings)}); train into another --out")


def _stored_config(cls: type[TrainableModule], ckpt: dict[str, Any], path: Path) -> Any:
    try:
        return cls.config_from_dict(ckpt["hyper_parameters"]["config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{path}: {cls.WHAT} checkpoint with an unreadable config ({exc})") from None


def train(cls: type[TrainableModule], config: Any, datasets: Sequence[str | os.PathLike], run: RunConfig,
          init: str | os.PathLike | None = None, callbacks: Sequence[Callback] = ()) -> TrainResult:
    """Train (or resume) the component ``cls`` with ``config`` on the given stores; returns where the checkpoints are.

    ``init``: a checkpoint of the same kind whose weights (and held-out episodes) a new run starts from;
    ``callbacks``: more Lightning callbacks. Lightning's settings and the stores are checked before the run
    directory is made; the run directory is locked while written (one writer), and one this call made is
    removed again if training fails before its first checkpoint.
    """
    run = resolve_precision(run)
    check_lightning(run)
    run_dir = Path(run.run_dir)
    if getattr(rank_zero_only, "rank", 0) != 0:  # a DDP worker Lightning launched: rank 0 holds the lock and owns the directory
        return _train(cls, config, datasets, run, init, callbacks)
    with exclusive(run_dir, "run directory"):
        made = not run_dir.exists()
        try:
            return _train(cls, config, datasets, run, init, callbacks)
        except BaseException:
            if made and not (run_dir / "checkpoints" / LAST).exists():
                shutil.rmtree(run_dir, ignore_errors=True)
            raise


def _train(cls: type[TrainableModule], config: Any, datasets: Sequence[str | os.PathLike], run: RunConfig,
           init: str | os.PathLike | None, callbacks: Sequence[Callback]) -> TrainResult:
    run_dir = Path(run.run_dir)
    rank_zero = getattr(rank_zero_only, "rank", 0) == 0  # a DDP worker finds rank 0's run.json there already
    last = check_run_dir(run) if rank_zero else run_dir / "checkpoints" / LAST
    paths = tuple(str(p) for p in datasets)
    start_step, ckpt, init_state = 0, None, None
    if run.resume:
        ckpt = read_checkpoint(last, cls.KIND, task=config.task)
        if "optimizer_states" not in ckpt:
            raise DataError(f"{last}: holds no optimiser state (a `gpc export` for planning): "
                            "training cannot resume it")
        stored = _stored_config(cls, ckpt, last)
        cls.check_resume(stored, config, str(last))
        given_config, config, start_step = config, stored, int(ckpt.get("global_step", 0))
        init = ckpt["hyper_parameters"].get("data", {}).get("init")
    elif init is not None:
        ckpt = read_checkpoint(init, cls.KIND, task=config.task, obs=getattr(config, "obs_type", None))
        config = cls.continue_from(config, _stored_config(cls, ckpt, Path(init)), str(init))
        init_state = module_state(ckpt)
    else:
        cls.check_start(config)

    # A run started from a checkpoint holds out the episodes it held out, whatever its own seed:
    # otherwise its "held-out" episodes would have been trained on.
    earlier = ckpt["hyper_parameters"].get("data", {}) if ckpt else {}
    split = recorded_split(earlier) or (run.seed, run.val_ratio)
    windows = cls.data_config(config, paths, run, split)
    if earlier.get("held_out") is not None:  # the same episodes, found by identity whatever the stores' order
        counts = [EpisodeStore.open(p).n_episodes for p in paths]
        kept = recorded_held_out(earlier, paths, counts, strict=False)
        if len(kept):  # (none when the run trains on other stores: then its own split holds out theirs)
            windows = dataclasses.replace(windows, val_episodes=tuple(int(i) for i in kept))
    data = EpisodeDataModule(windows)
    config = cls.fit_to_data(config, data.arrays, paths[0], resumed=run.resume)
    record = {"datasets": list(paths), "val_ratio": split[1], "seed": run.seed, "split_seed": split[0],
              "init": None if init is None else str(init),
              "held_out": identities(data.arrays.sources, data.arrays.counts, data.val_episodes.tolist()),
              "data_digests": store_digests(data.arrays), "batch_size": run.batch_size}
    if ckpt is not None and run.resume:  # before run.json is rewritten: a refused resume changes nothing
        expected = cls.continue_from(given_config, config, str(last)) if init is not None else given_config
        check_same_run(earlier, record, config, cls.fit_to_data(expected, data.arrays, paths[0], resumed=False), last)
    (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    _write_run_record(run_dir, cls.KIND, config, record, run)

    L.seed_everything((run.seed + start_step) % 2**32, workers=True, verbose=False)  # a 32-bit seed, --seed near 2**32 too
    if init_state is None:
        module = cls.from_data(config, data, record)
    else:
        module = cls(config, data=record)
        try:
            module.load_state_dict(init_state)
        except RuntimeError as exc:
            raise DataError(f"{init}: weights do not fit the {cls.WHAT} ({str(exc).splitlines()[0][:200]})") from None
    module.prepare(data, progress=run.progress)
    return fit_module(module, data, run, validate=len(data.val_episodes) > 0, extra=callbacks)


ACCELERATORS = ("auto", "cpu", "gpu", "cuda", "mps", "tpu")
PRECISIONS = ("32-true", "32", "16-mixed", "bf16-mixed")
BF16_AUTO = "bf16-auto"  # bf16-mixed where the hardware computes bf16 natively, 32-true elsewhere


def resolve_precision(run: RunConfig) -> RunConfig:
    """``bf16-auto`` made concrete for the device the run trains on (emulated bf16 is slower than float32)."""
    if run.precision != BF16_AUTO:
        return run
    gpu = run.accelerator in ("gpu", "cuda") or (run.accelerator == "auto" and torch.cuda.is_available())
    return dataclasses.replace(run, precision="bf16-mixed" if native_bf16("cuda" if gpu else "cpu") else "32-true")


def check_lightning(run: RunConfig) -> None:
    """Refuse, in one line naming the option, settings Lightning cannot run here (before anything is written)."""
    if run.accelerator not in ACCELERATORS:
        raise ValueError(f"--accelerator {run.accelerator!r}: use one of {', '.join(ACCELERATORS)}")
    if run.accelerator in ("gpu", "cuda") and not torch.cuda.is_available():
        raise ValueError(f"--accelerator {run.accelerator}: no GPU is visible to torch on this machine; use cpu or auto")
    if run.precision not in PRECISIONS:
        raise ValueError(f"--precision {run.precision}: use one of {', '.join((*PRECISIONS, BF16_AUTO))} "
                         "(the models keep 32-bit weights)")
    devices = run.devices
    if not (devices == "auto" or (isinstance(devices, int) and devices >= 1)
            or (isinstance(devices, str) and devices.isdigit() and int(devices) >= 1)):
        raise ValueError(f"--devices {devices!r}: use a number of devices (at least 1) or auto")
    quiet = [logging.getLogger(n) for n in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero")]
    levels = [q.level for q in quiet]
    try:
        for q in quiet:  # the trial Trainer would announce the hardware a second time
            q.setLevel(logging.WARNING)
        L.Trainer(accelerator=run.accelerator, devices=_devices(run), strategy=run.strategy, num_nodes=run.num_nodes,
                  precision=run.precision, logger=False, enable_checkpointing=False,  # type: ignore[arg-type]
                  enable_progress_bar=False, enable_model_summary=False)
    except Exception as exc:  # Lightning raises several types for settings it cannot serve
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"--accelerator {run.accelerator} --devices {run.devices} --strategy {run.strategy} "
                         f"--precision {run.precision}: Lightning cannot run this here ({first[:200]})") from None
    finally:
        for q, level in zip(quiet, levels):
            q.setLevel(level)


def _devices(run: RunConfig) -> int | str:
    return int(run.devices) if isinstance(run.devices, str) and run.devices.isdigit() else run.devices


def fit_module(module: TrainableModule, data: L.LightningDataModule, run: RunConfig, validate: bool,
               extra: Sequence[Callback] = ()) -> TrainResult:
    """Run Lightning on any of our modules: last/best checkpoints, TensorBoard, resume, NaN stop.

    The module logs ``val/loss`` (when ``validate``) and sets ``diverged_at`` (a step, or
    ``None``) when its loss turns non-finite; ``last.ckpt`` is resumed when ``run.resume``.
    """
    run_dir = Path(run.run_dir)
    ckpt_dir = run_dir / "checkpoints"
    last = ckpt_dir / LAST
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    callbacks: list[Callback] = [LastCheckpoint(last, run.checkpoint_every, run.checkpoint_minutes), LearningRateMonitor("step"), *extra]
    best_cb = None
    if validate:
        best_cb = ModelCheckpoint(dirpath=ckpt_dir, filename=BEST[:-5], monitor="val/loss", mode="min", save_top_k=1,
                                  auto_insert_metric_name=False, enable_version_counter=False,
                                  save_on_train_epoch_end=False)
        callbacks.append(best_cb)
    if run.progress:
        callbacks.append(StepProgressBar())
    devices = _devices(run)
    trainer = L.Trainer(
        default_root_dir=run_dir, max_steps=run.max_steps or -1, max_epochs=run.max_epochs or (-1 if run.max_steps else None),
        accelerator=run.accelerator, devices=devices, strategy=run.strategy, num_nodes=run.num_nodes,
        precision=run.precision,  # type: ignore[arg-type]  # RunConfig names Lightning's precision strings
        logger=TensorBoardLogger(save_dir=run_dir, name="", version="tensorboard"),
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
