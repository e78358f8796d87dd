"""Files written whole: a reader, or a crash, sees the old content or the new, never half of one."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from gpc.datasets.errors import DataError


def write_atomic(path: Path, text: str) -> None:
    """Write beside ``path``, then rename over it."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_json(path: Path) -> Any:
    """JSON from ``path``; a missing or damaged file is named in one line."""
    try:
        return json.loads(Path(path).read_text())
    except OSError as exc:
        raise DataError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise DataError(f"{path}: not valid JSON ({str(exc).splitlines()[0][:120]})") from None


def check_out(out: Path) -> None:
    """``out`` is (or can become) a folder this process may write, before any work is done."""
    probe = out
    while not probe.exists():
        probe = probe.parent
    if probe == out and not out.is_dir():
        raise DataError(f"{out}: is a file; --out names a folder for results")
    if not probe.is_dir():
        raise DataError(f"{out}: cannot be written here ({probe} is a file, not a folder)")
    if os.statvfs(probe).f_flag & os.ST_RDONLY:
        raise DataError(f"{out}: cannot be written here ({probe} is on a read-only file system)")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise DataError(f"{out}: cannot be written here ({probe} is not a writable folder)")
