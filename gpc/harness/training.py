"""What `gpc train ...` runs: the stores checked against the task first, and an honest stop on a signal.

``models.training.trainer.train`` is the training itself; this adds what only the harness knows
(the task's step shapes) and turns a SIGINT or SIGTERM into ``Interrupted`` once the last
checkpoint holds the step training stopped at.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.utilities import rank_zero_only

from gpc.datasets.locks import check_free
from gpc.harness.files import check_out
from gpc.harness.interrupts import Interrupted, reclaim_sigterm, requested
from gpc.harness.stores import check_stores
from gpc.models.training.config import RunConfig
from gpc.models.training.module import TrainableModule
from gpc.models.training.trainer import TrainResult, check_run_dir, train
from gpc.tasks import get_task


def train_component(cls: type[TrainableModule], config: Any, datasets: Sequence[str | os.PathLike], run: RunConfig,
                    init: str | os.PathLike | None = None) -> TrainResult:
    """Train ``cls`` with ``config`` (see ``train``) after checking every store holds the keys and shapes it reads."""
    if getattr(rank_zero_only, "rank", 0) == 0:  # (a DDP worker Lightning launched finds rank 0's run there)
        check_out(Path(run.run_dir))  # the output first: a wrong --out costs nothing
        check_free(run.run_dir, "run directory")
        check_run_dir(run)
    paths = tuple(str(p) for p in datasets)
    windows = cls.data_config(config, paths, run, (run.seed, run.val_ratio))
    check_stores(get_task(config.task), paths, tuple(dict.fromkeys(windows.obs_keys + (windows.action_key,))))
    stop = StopOnSignal()
    result = train(cls, config, paths, run, init=init, callbacks=[stop])
    signum = requested()
    if stop.stopped_at is not None and signum is not None:
        raise Interrupted(signum, f"training stopped at step {result.global_step}; {result.last} holds it "
                                  "(run the same command with --resume to go on)")
    return result


class StopOnSignal(Callback):
    """Ends training after the current step when a stop was asked for; ``last.ckpt`` is then written as at the end.

    Lightning puts its own SIGTERM handler in place for the fit (it exits 0 without a checkpoint);
    ours is put back when training starts, so SIGTERM stops like Ctrl-C.
    """

    def __init__(self) -> None:
        self.stopped_at: int | None = None

    def on_train_start(self, trainer: L.Trainer, *args: Any) -> None:
        reclaim_sigterm()

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        if requested() is not None and self.stopped_at is None:
            self.stopped_at = trainer.global_step
            trainer.should_stop = True
            # Lightning runs a whole validation pass before honouring should_stop: on an image world model that
            # held a SIGTERM for minutes (20 beside another job). A stop keeps the step's weights, not a score.
            trainer.fit_loop.epoch_loop._skip_next_val = True
