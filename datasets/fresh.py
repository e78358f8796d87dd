"""A failed start leaves nothing behind: what one command made is removed again if it fails before its first result.

Only what this process made is ever removed (known in memory, from what was absent when it began); a path that was
there before, the user's or another run's, is left as it was. A stop (SIGINT, SIGTERM: not an ``Exception``) keeps
what it made, since it says what it kept and the same command goes on from it.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def missing_folders(path: str | os.PathLike) -> list[Path]:
    """The folders from ``path`` up that do not exist yet, deepest first (those a ``mkdir -p path`` would make)."""
    found, probe = [], Path(path)
    while not (probe.exists() or probe.is_symlink()) and probe != probe.parent:
        found.append(probe)
        probe = probe.parent
    return found


def remove_folders(folders: list[Path]) -> None:
    """Remove each folder (deepest first) that is still empty; one that now holds anything is left alone."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return  # not empty (another process put something there), or gone: nothing above it is ours to remove


class Fresh:
    """``path`` as this command found it; ``keep()`` once it holds a first result (nothing is removed after that)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.made = missing_folders(self.path)  # the path itself first, when it is absent
        self.kept = False

    @property
    def new(self) -> bool:
        """Whether the path was absent when the command began (so anything there now is this command's)."""
        return bool(self.made) and self.made[0] == self.path

    def keep(self) -> None:
        self.kept = True

    def undo(self) -> None:
        """Remove what this command made at and above the path (nothing, when the path was there before)."""
        if not self.made:
            return
        if self.new and self.path.is_dir() and not self.path.is_symlink():
            shutil.rmtree(self.path, ignore_errors=True)
        elif self.new and (self.path.exists() or self.path.is_symlink()):
            self.path.unlink(missing_ok=True)
        remove_folders(self.made[1:] if self.new else self.made)


@contextmanager
def fresh(path: str | os.PathLike) -> Iterator[Fresh]:
    """The block may make ``path`` (and folders above it); if it fails before ``keep()``, they are removed again."""
    made = Fresh(path)
    try:
        yield made
    except Exception:
        if not made.kept:
            made.undo()
        raise
