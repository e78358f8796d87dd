"""Honest stops: Ctrl-C (SIGINT) and SIGTERM end a command at its next safe point, with what was kept.

Inside ``deferred_signals()`` (the ``gpc`` command runs in one) a first signal only sets a flag;
the long loops poll it (``check()``: between collected episodes, closed-loop decisions and
training steps) and raise ``Interrupted`` there, so no signal lands inside a C callback (pymunk's
collision handlers print and swallow exceptions) or halfway through an optimiser step. A second
signal stops at once. Worker processes ignore Ctrl-C (``ignore_in_worker``); their parent stops them.
Library code run without ``deferred_signals`` sees Python's ordinary ``KeyboardInterrupt``.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Callback

SIGNALS = (signal.SIGINT, signal.SIGTERM)
_requested: list[int] = []


class Interrupted(BaseException):
    """A stop asked for by a signal; ``kept`` says what was saved and how to go on (set by whoever knows)."""

    def __init__(self, signum: int, kept: str = "") -> None:
        super().__init__(signum, kept)
        self.signum, self.kept = signum, kept

    @property
    def exit_code(self) -> int:
        """130 for SIGINT, 143 for SIGTERM (128 + the signal's number, as shells report it)."""
        return 128 + self.signum

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name


def requested() -> int | None:
    """The signal that asked to stop, if one did."""
    return _requested[0] if _requested else None


def check() -> None:
    """Raise ``Interrupted`` if a stop was asked for (call it where stopping leaves nothing half done)."""
    if _requested:
        raise Interrupted(_requested[0])


def _handler(signum: int, frame: FrameType | None) -> None:
    if _requested:  # the second signal: stop now
        raise Interrupted(signum)
    _requested.append(signum)


@contextmanager
def deferred_signals() -> Iterator[None]:
    """SIGINT and SIGTERM set the stop flag for the block (main thread only; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _handler) for s in SIGNALS}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _requested.clear()


def ignore_in_worker() -> None:
    """Worker processes leave Ctrl-C (sent to the whole process group) to their parent, which polls its flag and
    ends them; SIGTERM keeps its default, since that is how the parent's pool ends its workers."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class StopOnSignal(Callback):
    """Ends training after the current step when a stop was asked for; ``last.ckpt`` is then written as at the end."""

    def __init__(self) -> None:
        self.stopped_at: int | None = None

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        if requested() is not None and self.stopped_at is None:
            self.stopped_at = trainer.global_step
            trainer.should_stop = True
