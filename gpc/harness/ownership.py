"""Which files gpc wrote: the one rule every command's writes obey.

A file or folder gpc did not write is never replaced or deleted, ``--overwrite`` included. To know
its own, gpc keeps a record beside what it writes: ``DIR/.gpc-files.json`` names each file it wrote
in ``DIR`` with the SHA-256 of the content it wrote. A file is gpc's when the record names it with
the content it holds now, so a file of the user's (or one they edited after gpc wrote it) is refused
by name, in one line, before any work. Older gpc wrote no record: where a file's content proves an
older gpc wrote it (a results folder's run record, a comparison's ``kind``, a checkpoint's ``gpc``
record), the caller passes that proof and the file is recorded (``adopt``) once the command goes on.

A record entry is written twice around each replacement: first with the new content ``pending``,
then as the new content alone; a crash between the two leaves a record that accepts either file.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import sys
import tempfile
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from gpc.datasets.errors import DataError

RECORD = ".gpc-files.json"
Proof = Callable[[Path], bool]


def digest_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _entries(folder: Path) -> dict[str, Any]:
    """The folder's record (empty when there is none or it is unreadable: then nothing there is taken as gpc's)."""
    try:
        held = json.loads((folder / RECORD).read_text())
    except (OSError, ValueError):
        return {}
    files = held.get("files") if isinstance(held, dict) else None
    return files if isinstance(files, dict) else {}


def is_ours(path: Path, proof: Proof | None = None) -> bool:
    """``path`` is a file gpc wrote and nobody changed since (or ``proof`` shows an older gpc wrote it)."""
    path = Path(path)
    if not path.is_file():
        return False
    entry = _entries(path.parent).get(path.name)
    if isinstance(entry, dict):  # gpc wrote a file of this name: it is gpc's only as gpc wrote it (not as edited since)
        try:
            return digest_file(path) in {entry.get("sha256"), entry.get("pending")} - {None}
        except OSError:
            return False
    return proof is not None and _proven(proof, path)


def _proven(proof: Proof, path: Path) -> bool:
    try:
        return bool(proof(path))
    except (OSError, ValueError):
        return False


def claim(paths: Iterable[Path], option: str = "--out", proof: Proof | None = None) -> None:
    """Refuse, reading only and before any work, to write where a file is that gpc did not write.

    ``paths``: every file the command will write (or remove); ``proof``: how an older gpc's file of this
    kind is recognised (see the module docstring)."""
    for path in map(Path, paths):
        if path.is_dir() and not path.is_symlink():
            raise DataError(f"{path}: is a folder; {option} would write a file there")
        if (path.exists() or path.is_symlink()) and not is_ours(path, proof):
            raise DataError(f"{path}: exists and was not written by gpc (no record of it in {path.parent / RECORD}); "
                            f"gpc never replaces it: move it away or choose another {option}")


def adopt(paths: Iterable[Path], proof: Proof) -> None:
    """Record the files ``proof`` shows an older gpc wrote (call once the command goes on, inside its lock)."""
    for path in map(Path, paths):
        if path.is_file() and not is_ours(path) and _proven(proof, path):
            with _record(path.parent) as files:
                files[path.name] = _entry(digest_file(path), adopted=True)


def check_replaceable(path: Path) -> None:
    """The last guard, at the moment of writing: a file there that is not gpc's stays."""
    claim([path])


def remove(path: Path) -> None:
    """Delete a file gpc wrote (and its record entry); a file that is not gpc's is refused by name."""
    path = Path(path)
    if not (path.exists() or path.is_symlink()):
        return
    claim([path])
    path.unlink()
    with _record(path.parent) as files:
        files.pop(path.name, None)


def write_bytes(path: Path, data: bytes) -> None:
    """``data`` into ``path`` whole (written beside it, then renamed over it), recorded as gpc's."""
    path = Path(path)
    check_replaceable(path)
    tmp = temporary_beside(path)
    try:
        with open(tmp, "wb") as f:
            f.write(data)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise DataError(f"{path}: cannot be written ({exc.strerror or exc})") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    install(tmp, path)


def install(tmp: Path, path: Path) -> None:
    """A file another writer finished at ``tmp`` (beside ``path``) takes ``path``'s place, recorded as gpc's;
    ``tmp`` is removed whatever happens."""
    try:
        check_replaceable(path)
        new = digest_file(tmp)
        with _record(path.parent) as files:
            files[path.name] = {**files.get(path.name, {}), "pending": new}
        try:
            os.replace(tmp, path)
        except OSError as exc:
            raise DataError(f"{path}: cannot be written ({exc.strerror or exc})") from None
        with _record(path.parent) as files:
            files[path.name] = _entry(new)
    finally:
        tmp.unlink(missing_ok=True)


def temporary_beside(path: Path, suffix: str = ".tmp") -> Path:
    """A new, empty temporary file beside ``path`` (same file system: the rename is atomic), readable as gpc's
    outputs are (mkstemp's 0600 would hide it from the user's group)."""
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
        os.fchmod(fd, 0o666 & ~_umask())
        os.close(fd)
    except OSError as exc:
        raise DataError(f"{path}: cannot be written ({exc.strerror or exc})") from None
    return Path(tmp)


def _entry(sha256: str, adopted: bool = False) -> dict[str, Any]:
    entry: dict[str, Any] = {"sha256": sha256, "by": _command(), "written": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    if adopted:
        entry["adopted"] = True  # written by a gpc that kept no record; its content proved it
    return entry


def _command() -> str:
    """The gpc command writing (``gpc eval``, ``gpc data video``), for a person reading the record."""
    words = []
    for arg in sys.argv[1:3]:
        if not arg.replace("-", "").isalpha() or arg.startswith("-"):
            break
        words.append(arg)
    return " ".join(["gpc", *words])


@contextmanager
def _record(folder: Path) -> Iterator[dict[str, Any]]:
    """The folder's record for read-modify-write, under a lock on the folder (processes write one folder's
    files at once: workers' videos, parallel makes), written whole."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as exc:
        raise DataError(f"{folder}: cannot be written ({exc.strerror or exc})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        files = dict(_entries(folder))
        yield files
        text = json.dumps({"about": "files gpc wrote here (it replaces no other file)", "files": files}, indent=1, sort_keys=True)
        _replace_with(folder / RECORD, text.encode())
    finally:
        os.close(fd)  # closing releases the lock


def _replace_with(path: Path, data: bytes) -> None:
    """The record itself, written beside and renamed over (it records nothing about itself)."""
    tmp = temporary_beside(path)
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError as exc:
        raise DataError(f"{path}: cannot be written ({exc.strerror or exc})") from None
    finally:
        tmp.unlink(missing_ok=True)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
