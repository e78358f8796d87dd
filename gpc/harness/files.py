"""Files written whole: a reader, or a crash, sees the old content or the new, never half of one."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from gpc.datasets.errors import DataError
from gpc.datasets.jsonfile import read_json
from gpc.harness.ownership import Proof, claim, write_bytes

__all__ = ["check_file_out", "check_out", "read_json", "write_atomic", "write_bytes_atomic"]


def write_atomic(path: Path, text: str) -> None:
    """Write beside ``path``, then rename over it, recorded as gpc's (``gpc.harness.ownership``: a file there
    that gpc did not write is refused, never replaced); a failure names ``path``, not the temporary file."""
    write_bytes(path, text.encode())


def write_bytes_atomic(path: Path, data: bytes) -> None:
    """``write_atomic`` for bytes (an image, a checkpoint)."""
    write_bytes(path, data)


def check_file_out(path: Path, suffix: str, option: str = "--out", beside: Sequence[str] = (), proof: Proof | None = None) -> None:
    """``path`` can become a ``suffix`` file (a video, a report) in a folder this process may write, before any work;
    it and the files written ``beside`` it (their suffixes) are new or gpc's own (``ownership.claim``)."""
    path = Path(path)
    if path.is_dir():
        raise DataError(f"{path}: is a folder; {option} names the {suffix} file to write")
    if path.suffix.lower() != suffix:
        raise DataError(f"{path}: {option} names a {suffix} file (gpc does not write {suffix} content under another name)")
    check_out(path.parent)
    claim([path, *(path.with_suffix(s) for s in beside)], option, proof)


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
