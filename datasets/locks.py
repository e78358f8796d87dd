"""One writer at a time: an exclusive OS lock for each store, run directory and results folder being written.

The lock is ``flock`` on a small file beside the target (``.NAME.lock`` in its parent folder), so it
exists before the target does and dies with the process that holds it: a SIGKILL never leaves a
stale lock. A second writer fails at once with one line naming the holder's pid. Readers take no
lock (a store's readers see whole episodes only). The lock file is left in place when released:
removing it would let two processes lock two different files of the same name.
"""

from __future__ import annotations

import errno
import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from gpc.datasets.errors import DataError


def lock_path(target: str | os.PathLike) -> Path:
    """Beside the target itself: every path to it (a symbolic link, ``..``) takes the same lock."""
    target = Path(os.path.realpath(target))
    return target.parent / f".{target.name}.lock"


def _busy(target: str | os.PathLike, what: str, fd: int) -> DataError:
    holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
    return DataError(f"{target}: another gpc process (pid {holder}) is writing this {what}; wait for it to finish or stop it")


def check_free(target: str | os.PathLike, what: str) -> None:
    """Refuse at once, creating nothing, a target another process holds (``exclusive`` checks again when it locks)."""
    try:
        fd = os.open(lock_path(target), os.O_RDONLY)
    except OSError:
        return  # no lock file: nobody has written here
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise _busy(target, what, fd) from None
            raise
        fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


@contextmanager
def exclusive(target: str | os.PathLike, what: str) -> Iterator[None]:
    """Hold the writer's lock on ``target`` (a store, run directory or results folder) for the block.

    ``what`` names the target in the refusal: "store", "run directory", "results folder".
    """
    path = lock_path(target)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise DataError(f"{target}: cannot write here ({exc.strerror or exc})") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise
            raise _busy(target, what, fd) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)
