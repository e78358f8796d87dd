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
from gpc.datasets.fresh import missing_folders, remove_folders


def lock_path(target: str | os.PathLike) -> Path:
    """Beside the target itself: every path to it (a symbolic link, ``..``) takes the same lock."""
    target = Path(os.path.realpath(target))
    return target.parent / f".{target.name}.lock"


def _holder(fd: int) -> str:
    return os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"


def _busy(target: str | os.PathLike, what: str, fd: int) -> DataError:
    holder = _holder(fd)
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
            if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise
            if _holder(fd) != str(os.getpid()):  # this process holding it (a check inside its own lock) is no refusal
                raise _busy(target, what, fd) from None
            return
        fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


@contextmanager
def exclusive(target: str | os.PathLike, what: str) -> Iterator[None]:
    """Hold the writer's lock on ``target`` (a store, run directory or results folder) for the block.

    ``what`` names the target in the refusal: "store", "run directory", "results folder". A lock file this call made
    (and the folders it made for it) is removed again when the block fails, or when it leaves no target behind: a
    failed start leaves nothing. Removing it is safe because every locker checks, once it holds the lock, that the
    file it locked is still the one at the path (``_lock``).
    """
    path = lock_path(target)
    folders = missing_folders(path.parent)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, created = _lock(path, target, what)
    except OSError as exc:
        remove_folders(folders)
        raise DataError(f"{target}: cannot write here ({exc.strerror or exc})") from None
    except BaseException:
        remove_folders(folders)
        raise
    failed = False
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    except Exception:
        failed = True
        raise
    finally:
        if created and (failed or not os.path.lexists(os.path.realpath(target))):
            path.unlink(missing_ok=True)  # still locked: a process that opened it finds it gone and locks anew
            remove_folders(folders)
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def _lock(path: Path, target: str | os.PathLike, what: str) -> tuple[int, bool]:
    """An open, exclusively locked descriptor of the lock file at ``path`` and whether this call created the file."""
    while True:
        try:
            fd, created = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644), True
        except FileExistsError:
            try:
                fd, created = os.open(path, os.O_RDWR), False
            except FileNotFoundError:
                continue  # removed between the two opens: make it anew
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            now, held = os.stat(path), os.fstat(fd)
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                busy = _busy(target, what, fd)
                os.close(fd)
                raise busy from None
            os.close(fd)
            if isinstance(exc, FileNotFoundError):
                continue  # its maker removed it while this process waited to lock it
            raise
        if (now.st_dev, now.st_ino) == (held.st_dev, held.st_ino):
            return fd, created
        os.close(fd)  # the file locked was removed and another made in its place: lock that one
