"""The one training contract every trainable component follows, as a LightningModule base.

A component (policy, world model, reward predictor) supplies its config, its network and
``loss(batch) -> (loss, logs)``; ``TrainableModule`` owns the rest, once: the AdamW + cosine
optimiser, the EMA copy (when the config asks for one), the stop on a non-finite loss, the
checkpoint record and rebuilding a module from a checkpoint alone. What a component needs to
be trained on stores (its data windows, how its config adapts to the data, how it is built
from the data) are the classmethods below; ``gpc.models.training.trainer.train`` calls them.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar

import lightning as L
import torch
from torch import nn

from gpc.datasets.errors import DataError
from gpc.models.training.checkpoint import checkpoint_meta, read_checkpoint, rebuild
from gpc.models.training.ema import EMAWeights
from gpc.models.training.optim import adamw_cosine

if TYPE_CHECKING:
    from gpc.datasets.datamodule import DataConfig, EpisodeDataModule
    from gpc.datasets.windows import EpisodeArrays
    from gpc.models.training.config import RunConfig

Batch = Mapping[str, torch.Tensor]
Logs = dict[str, torch.Tensor]


class TrainableModule(L.LightningModule):
    """Base of every trainable component: batch in, loss and logs out; checkpoints that rebuild it alone.

    Subclasses set ``KIND`` (the checkpoint kind) and ``WHAT`` (how messages name it), build
    their network in ``__init__`` and then call ``self.track_ema()``.
    """

    KIND: ClassVar[str]
    WHAT: ClassVar[str]

    def __init__(self, config: Any, data: Mapping[str, Any] | None = None) -> None:
        super().__init__()
        self.config = config
        # ``data``: where the weights came from (stores, split seed and ratio, init checkpoint).
        self.save_hyperparameters({"config": config.to_dict(), "data": dict(data or {})})
        self.ema: EMAWeights | None = None
        self.diverged_at: int | None = None  # global step of a non-finite loss; training stops there

    # ------------------------------------------------------------------ what a component supplies
    @property
    def network(self) -> nn.Module:
        """The module whose parameters are optimised (and averaged into the EMA copy)."""
        raise NotImplementedError

    def loss(self, batch: Batch) -> tuple[torch.Tensor, Logs]:
        """A training batch -> (scalar loss, detached figures to log)."""
        raise NotImplementedError

    def validation_loss(self, batch: Batch, batch_idx: int) -> tuple[torch.Tensor, Logs]:
        """The held-out loss (default: the training loss)."""
        return self.loss(batch)

    def check_ready(self) -> None:
        """Raise when the module cannot train (e.g. its normaliser lacks a key)."""

    def record(self) -> dict[str, Any]:
        """Fields of the checkpoint record beside kind and task (checked when a checkpoint is loaded)."""
        return {}

    @classmethod
    def expected_record(cls, obs_type: str | None) -> dict[str, Any]:
        """Record fields a caller may require on loading."""
        return {"obs": obs_type}

    @classmethod
    def config_from_dict(cls, data: Any) -> Any:
        raise NotImplementedError

    # ------------------------------------------------------------------ how a component trains on stores
    @classmethod
    def data_config(cls, config: Any, datasets: tuple[str, ...], run: RunConfig, split: tuple[int, float]) -> DataConfig:
        """The windows this component trains on; ``split`` is the (seed, ratio) of its held-out episodes."""
        raise NotImplementedError

    @classmethod
    def fit_to_data(cls, config: Any, arrays: EpisodeArrays, source: str, resumed: bool) -> Any:
        """The config that fits the stores (shapes filled in), or a ``DataError`` naming ``source``."""
        return config

    @classmethod
    def from_data(cls, config: Any, data: EpisodeDataModule, record: dict[str, Any]) -> TrainableModule:
        """A fresh module whose normaliser is fitted on the training episodes."""
        return cls(config, normalizer=data.normalizer, data=record)  # type: ignore[call-arg]

    def prepare(self, data: EpisodeDataModule, progress: bool = False) -> None:
        """Called once before fitting, fresh or resumed: where a module derives what its windows read from the loaded
        stores (LaDi's frozen encoder reads each frame once here, not once per window)."""

    @classmethod
    def check_resume(cls, stored: Any, given: Any, path: str) -> None:
        """Refuse to resume a run whose stored config is of another kind than the one asked for."""
        if getattr(stored, "obs_type", None) != getattr(given, "obs_type", None):
            raise DataError(f"{path}: run was trained on obs {getattr(stored, 'obs_type', None)!r}, "
                            f"not {getattr(given, 'obs_type', None)!r}")

    @classmethod
    def check_start(cls, config: Any) -> None:
        """Refuse a fresh run (neither resumed nor started from a checkpoint) that cannot start from nothing."""

    @classmethod
    def continue_from(cls, config: Any, stored: Any, path: str) -> Any:
        """``config``'s training settings for a run that starts from the weights of a checkpoint of ``stored``."""
        raise DataError(f"{path}: a {cls.WHAT} cannot start from another checkpoint's weights (use --resume)")

    # ------------------------------------------------------------------ owned here
    def track_ema(self) -> None:
        """Keep an averaged copy of ``network`` when the config has ``ema`` settings."""
        ema = getattr(self.config, "ema", None)
        if ema is not None:
            self.ema = EMAWeights(self.network, ema)

    @property
    def data_record(self) -> dict[str, Any]:
        return dict(self.hparams.get("data", {}))

    def on_fit_start(self) -> None:
        self.check_ready()

    def training_step(self, batch: Batch, batch_idx: int) -> torch.Tensor | None:
        loss, logs = self.loss(batch)
        bad = not bool(torch.isfinite(loss))
        if self.trainer.strategy.reduce_boolean_decision(bad, all=False):
            # Skip this update (the weights stay the last good ones) and stop; the trainer reports it.
            self.diverged_at = self.global_step
            self.trainer.should_stop = True
            return None
        self.log_dict({f"train/{k}": v for k, v in logs.items()}, prog_bar=True, batch_size=_batch_size(batch))
        return loss

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        if self.ema is not None and self.diverged_at is None:
            self.log("train/ema_decay", self.ema.update(self.network), batch_size=1)

    def validation_step(self, batch: Batch, batch_idx: int) -> torch.Tensor:
        loss, logs = self.validation_loss(batch, batch_idx)
        n = _batch_size(batch)
        self.log("val/loss", loss, prog_bar=True, sync_dist=True, batch_size=n)
        for name, value in logs.items():
            if name != "loss":
                self.log(f"val/{name}", value, sync_dist=True, batch_size=n)
        return loss

    def configure_optimizers(self) -> Any:  # Lightning's optimiser-and-scheduler dict
        return adamw_cosine(self.network.parameters(), self.config.optim, self.trainer)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["gpc"] = checkpoint_meta(self.KIND, self.config.task, **self.record())

    @classmethod
    def load_from_checkpoint(  # type: ignore[override]
        cls, checkpoint_path: str | os.PathLike, map_location: Any = "cpu", task: str | None = None,
        obs_type: str | None = None, **_: Any,
    ) -> Any:
        """Rebuild the module (config, normaliser, weights, EMA) from a checkpoint alone, in eval mode.

        ``task`` / ``obs_type``, when given, must match the checkpoint's record (``DataError`` otherwise).
        """
        ckpt = read_checkpoint(checkpoint_path, cls.KIND, task=task, map_location=map_location,
                               **cls.expected_record(obs_type))
        return rebuild(cls, ckpt, checkpoint_path, cls.WHAT)


def _batch_size(batch: Batch) -> int:
    return int(next(iter(batch.values())).shape[0])
