"""Honest stops: Ctrl-C (SIGINT) and SIGTERM end a command at its next safe point, with what was kept.

Inside ``deferred_signals()`` (the ``gpc`` command runs in one) a first signal only sets a flag;
the long loops poll it (``check()``: between collected episodes, closed-loop decisions and
training steps) and raise ``Interrupted`` there, so no signal lands inside a C callback (pymunk's
collision handlers print and swallow exceptions) or halfway through an optimiser step. A second
signal ends the process at once (what is on disk is then as after a kill: every store, checkpoint
and results folder is written so that a kill loses at most the unfinished piece). Worker processes
ignore Ctrl-C (``ignore_in_worker``); the parent polls its flag while it waits for them (``polled``).
Library code run without ``deferred_signals`` sees Python's ordinary ``KeyboardInterrupt``.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

SIGNALS = (signal.SIGINT, signal.SIGTERM)
_requested: list[int] = []
_workers: set[int] = set()  # pids of the pool workers this process waits on (``polled``): a second signal ends them
_semaphores: set[str] = set()  # the named semaphores of those pools' queues: a second signal removes them itself


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
    if _requested:  # the second signal: end now, without running Python code that could be anywhere
        for pid in tuple(_workers):  # else they would run on to their group's end, then fail to hand it over
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        _release_semaphores()
        name = signal.Signals(signum).name
        os.write(2, f"gpc: stopped by {name}: a second signal ended gpc at once; whole episodes, groups and "
                    "checkpoints already written are kept (run the same command, or --resume, to go on)\n".encode())
        os._exit(128 + signum)
    _requested.append(signum)


def _release_semaphores() -> None:
    """Unlink the pools' semaphores and tell multiprocessing's resource tracker so: after ``os._exit`` it would
    remove them itself, warning on stderr of "leaked semaphore objects" below gpc's one line. The tracker is told
    through its pipe directly, since its lock may be held by the code the signal interrupted."""
    from multiprocessing import resource_tracker, synchronize

    tracker = getattr(resource_tracker, "_resource_tracker", None)
    fd = getattr(tracker, "_fd", None)
    for name in tuple(_semaphores):
        try:
            synchronize.sem_unlink(name)  # type: ignore[attr-defined]  # _multiprocessing's, on every POSIX system
            if fd is not None:
                os.write(fd, f"UNREGISTER:{name}:semaphore\n".encode("ascii"))
        except (OSError, AttributeError):
            pass  # already gone, or no tracker: nothing would be reported either


def _pool_semaphores(pool: Any) -> set[str]:
    """The names of the semaphores a multiprocessing pool's queues hold (their locks)."""
    names = set()
    for queue in (getattr(pool, attr, None) for attr in ("_inqueue", "_outqueue", "_change_notifier")):
        for lock in (getattr(queue, attr, None) for attr in ("_rlock", "_wlock")):
            name = getattr(getattr(lock, "_semlock", None), "name", None)
            if name:
                names.add(name)
    return names


def active() -> bool:
    """Whether the calling process defers signals (is inside ``deferred_signals``)."""
    return signal.getsignal(signal.SIGINT) is _handler


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


def reclaim_sigterm() -> None:
    """Put the stop flag's handler back for SIGTERM where something replaced it (Lightning does, for a fit);
    a no-op outside ``deferred_signals`` and off the main thread."""
    if active() and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _handler)


def ignore_in_worker() -> None:
    """Worker processes leave Ctrl-C (sent to the whole process group) to their parent, which polls its flag and
    ends them; SIGTERM keeps its default, since that is how the parent's pool ends its workers."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def polled(pool: Any, results: Iterator[Any], every: float = 0.25) -> Iterator[Any]:
    """The results of ``pool.imap(...)``, checking for a stop while waiting for each (not only between them).

    A SIGTERM to the whole process group ends the workers at once; the parent then stops on its own
    flag instead of waiting forever for their lost results. A worker that dies alone (the kernel's
    out-of-memory killer) is reported in one line instead of a hang. A second signal (make passes its
    SIGTERM on to the job, then a user's ``kill`` adds one) ends the parent at once and these workers
    with it, so none plays its group to the end for nobody.
    """
    workers = list(getattr(pool, "_pool", ()))  # multiprocessing keeps its workers there
    pids, names = {w.pid for w in workers}, _pool_semaphores(pool)
    _workers.update(pids)
    _semaphores.update(names)
    try:
        while True:
            try:
                item = results.next(every)  # type: ignore[attr-defined]  # IMapIterator.next takes a timeout
            except mp.TimeoutError:
                check()
                dead = [w for w in workers if w.exitcode is not None]
                if dead:
                    code = dead[0].exitcode
                    how = f"was killed by {signal.Signals(-code).name}" if code < 0 else f"exited with status {code}"
                    raise OSError(f"a worker process (pid {dead[0].pid}) {how}, e.g. by the out-of-memory killer; what "
                                  "was finished is kept (run the same command again, or with fewer --workers)") from None
                continue
            except StopIteration:
                return
            yield item
    finally:
        # Stopping on the flag, the pool is still being torn down when a second signal may come (make's SIGTERM,
        # then the user's): leave its workers and semaphores to that signal (a name already gone is skipped).
        if requested() is None:
            _workers.difference_update(pids)
            _semaphores.difference_update(names)
