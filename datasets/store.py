"""Zarr episode store in Diffusion Policy's ReplayBuffer layout.

``data/<key>`` arrays share a time axis; ``meta/episode_ends`` holds cumulative episode
ends. Diffusion Policy's own stores (zarr format 2) open as they are; ours are written in
format 2 too, so Diffusion Policy and LeRobot's converters read them back.

Crash safety: an episode is appended data first, then ``meta/episode_seeds``, and
``meta/episode_ends`` last (zarr writes every file atomically). ``episode_ends`` is the
commit record: arrays longer than its last entry hold a half-written episode, which readers
ignore and the next writer truncates, so a store killed at any moment holds whole episodes.
zarr grows an array before writing the new chunk, so a trailing 0 in ``episode_ends`` is an
append that never landed, and is dropped the same way.

Missing data is never a value: zarr reads an absent chunk as its fill value (zeros), so every chunk
holding committed rows must be on disk (checked at open, one directory listing per array), and
gpc's writer writes every chunk, zeros included (zarr 3 skips all-fill chunks by default), so an
absent one is a lost one. Every read refuses an undecodable chunk, values that are not numbers and
NaN or inf, naming the array and the chunk or step.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import math
import os
import struct
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, cast

import numcodecs
import numpy as np
import zarr
from zarr.core.sync import sync

from gpc.datasets.errors import DataError

FORMAT_VERSION = 2  # 2: every chunk is written (format 1 left chunks of zeros out)
_CHUNK_BYTES = 4 << 20


def _array(node: zarr.Array | zarr.Group) -> zarr.Array:
    """An array node: zarr types every lookup as ``Array | Group``, our layout says which."""
    return cast(zarr.Array, node)


def _group(node: zarr.Array | zarr.Group) -> zarr.Group:
    """A group node (``data/``, ``meta/``), for the same reason as :func:`_array`."""
    return cast(zarr.Group, node)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0][:200]}" if text else type(exc).__name__


def _bad_metadata(path: Path) -> Path | None:
    """The first metadata file under ``path`` that is not valid JSON (what a zarr open error leaves unsaid)."""
    for meta in sorted(path.rglob("*")):
        if meta.name in (".zgroup", ".zarray", ".zattrs", "zarr.json"):
            try:
                json.loads(meta.read_text())
            except (OSError, ValueError):
                return meta
    return None


def _writes_every_chunk(arr: zarr.Array) -> zarr.Array:
    """``arr`` writing chunks of zeros too (zarr 3 skips them by default), so an absent chunk means a lost one."""
    return arr.with_config({"write_empty_chunks": True})


def _unit(name: str) -> str:
    return "steps" if name.startswith("data/") else "entries"


def _first_bad_row(block: np.ndarray) -> int | None:
    """The first row of ``block`` holding NaN or inf (checked in slices: no copy of a large array)."""
    rows = max(1, _CHUNK_BYTES // max(1, block[:1].nbytes))
    for start in range(0, len(block), rows):
        part = block[start : start + rows]
        ok = np.isfinite(part.reshape(len(part), -1)).all(axis=1)
        if not ok.all():
            return start + int(np.argmin(ok))
    return None


async def _others_ended() -> None:
    """Every other task on zarr's event loop has ended. A failed read leaves its sibling chunk reads running; torn
    down at exit, each would print an 'Exception ignored ... Event loop is closed' traceback after gpc's one line."""
    await asyncio.gather(*(asyncio.all_tasks() - {asyncio.current_task()}), return_exceptions=True)


def _compressor() -> numcodecs.Blosc:
    return numcodecs.Blosc(cname="zstd", clevel=5, shuffle=numcodecs.Blosc.BITSHUFFLE)


def store_record(path: Path) -> dict[str, Any]:
    """The attributes of the store at ``path``, its arrays unread ({} where there is no readable Zarr group): whose
    store it is stays known when its data is damaged (``--overwrite`` replaces a damaged store gpc wrote)."""
    try:
        return dict(zarr.open_group(str(path), mode="r").attrs) if path.is_dir() else {}
    except Exception:  # zarr raises several types for unreadable metadata
        return {}


class EpisodeStore:
    """Episodes of time-aligned arrays, appended whole and read by index."""

    def __init__(self, path: Path, group: zarr.Group, writable: bool) -> None:
        self.path = path
        self.root = group
        self.writable = writable
        self._validate()

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, path: str | os.PathLike, writable: bool = False) -> EpisodeStore:
        """Open an existing store; a half-written last episode is dropped when writable."""
        path = Path(path)
        if not path.exists():
            raise DataError(f"{path}: no such file or directory")
        if not path.is_dir() or not ((path / ".zgroup").exists() or (path / "zarr.json").exists()):
            if (path / "meta" / "info.json").is_file():
                raise DataError(f"{path}: a LeRobot dataset, not a Zarr episode store: convert it once with "
                                f"`gpc data import {path} --out STORE.zarr`")
            raise DataError(f"{path}: not a Zarr episode store (no .zgroup or zarr.json)")
        bad = _bad_metadata(path)  # zarr reads array metadata lazily, and its JSON errors name no file
        if bad is not None:
            raise DataError(f"{bad}: unreadable Zarr store (its metadata is not valid JSON)")
        try:
            group = zarr.open_group(str(path), mode="r+" if writable else "r")
        except Exception as exc:  # zarr raises several types for unreadable metadata
            raise DataError(f"{_bad_metadata(path) or path}: unreadable Zarr store ({_first_line(exc)})") from None
        store = cls(path, group, writable)
        if writable:
            store.verify()  # a writer never appends to damaged data, and refusing changes no byte
            store._repair()
        return store

    @classmethod
    def create(cls, path: str | Path, attrs: dict[str, Any]) -> EpisodeStore:
        """A new empty store carrying ``attrs`` (provenance); it never replaces anything already there."""
        path = Path(path)
        if path.exists():
            raise DataError(f"{path}: already exists; gpc writes a new store only where nothing is")
        path.parent.mkdir(parents=True, exist_ok=True)
        group = zarr.open_group(str(path), mode="w", zarr_format=2)
        group.create_group("data")
        meta = group.create_group("meta")
        for name in ("episode_ends", "episode_seeds"):
            meta.create_array(name, shape=(0,), chunks=(4096,), dtype=np.int64, compressors=None)
        meta.create_array("episode_scores", shape=(0,), chunks=(4096,), dtype=np.float64, compressors=None)
        group.attrs.update({"gpc_format": FORMAT_VERSION, **attrs})
        return cls(path, group, writable=True)

    def _validate(self) -> None:
        if "meta" not in self.root or "episode_ends" not in _group(self.root["meta"]):
            raise DataError(f"{self.path}: missing key meta/episode_ends")
        if "data" not in self.root:
            raise DataError(f"{self.path}: missing group data/")
        for part in ("data", "meta"):  # a node whose .zarray is damaged reads back as a group
            for name in _group(self.root[part]).keys():
                if not isinstance(_group(self.root[part])[name], zarr.Array):
                    raise DataError(f"{self.path / part / name / '.zarray'}: not a readable Zarr array (damaged metadata)")
        raw = _array(self.root["meta/episode_ends"])
        if raw.ndim != 1:
            raise DataError(f"{self.path}: meta/episode_ends has shape {raw.shape}; it must be 1-D (one end per episode)")
        if not np.issubdtype(raw.dtype, np.integer):
            raise DataError(f"{self.path}: meta/episode_ends holds {raw.dtype} values, not integers")
        # The last entry's chunk may be absent only when it holds that entry alone: an append that never landed.
        self._check_chunks(raw, "meta/episode_ends", max(0, raw.shape[0] - 1))
        ends = np.asarray(self._decoded(raw, "meta/episode_ends", 0, raw.shape[0]), dtype=np.int64)
        if ends.size and ends[-1] == 0 and (ends.size == 1 or ends[-2] > 0):
            # Grown but not yet filled: a writer died between zarr's resize and its chunk write.
            ends = ends[:-1]
        if ends.size and (ends[0] <= 0 or np.any(np.diff(ends) <= 0)):
            raise DataError(f"{self.path}: meta/episode_ends is not strictly increasing and positive")
        self._ends = ends
        n = self.n_steps
        for key, arr in _group(self.root["data"]).arrays():
            if arr.ndim == 0 or arr.shape[0] < n:
                raise DataError(
                    f"{self.path}: data/{key} has {arr.shape[0] if arr.ndim else 0} steps but meta/episode_ends needs {n}"
                )
            self._check_chunks(arr, f"data/{key}", n)
        meta = _group(self.root["meta"])
        for name in ("episode_seeds", "episode_scores"):
            if name in meta:
                arr = _array(meta[name])
                if arr.ndim != 1:
                    raise DataError(f"{self.path}: meta/{name} has shape {arr.shape}; it must be 1-D (one entry per episode)")
                self._check_chunks(arr, f"meta/{name}", min(arr.shape[0], self.n_episodes))

    def _check_chunks(self, arr: zarr.Array, name: str, stop: int) -> None:
        """Every chunk file holding rows ``[0, stop)`` of ``arr`` is on disk (one listing of its folder): zarr would
        read an absent one as its fill value."""
        if stop <= 0 or 0 in arr.shape:
            return
        folder = self.path / arr.path
        stored = {str(Path(root, f).relative_to(folder).as_posix()) for root, _, files in os.walk(folder) for f in files}
        chunk = tuple(arr.shards or arr.chunks)
        rows = int(chunk[0])
        across = [range(math.ceil(s / c)) for s, c in zip(arr.shape[1:], chunk[1:])]
        blosc = getattr(getattr(arr.metadata, "compressor", None), "codec_id", None) == "blosc"  # format 2's one codec
        for i in range(math.ceil(stop / rows)):
            where = f"{self.path}: {name} chunk {i} ({_unit(name)} {i * rows}-{min((i + 1) * rows, arr.shape[0]) - 1})"
            for rest in itertools.product(*across):
                key = arr.metadata.encode_chunk_key((i, *rest))
                if key not in stored:
                    raise DataError(f"{where} is missing (no file {name}/{key}){self._skipped_zeros_note()}")
                if blosc:  # blosc trusts its header: a truncated chunk of incompressible bytes would decode from past its end
                    with open(folder / key, "rb") as f:
                        head, size = f.read(16), os.fstat(f.fileno()).st_size
                    if len(head) < 16 or struct.unpack_from("<I", head, 12)[0] != size:
                        said = f", its header says {struct.unpack_from('<I', head, 12)[0]}" if len(head) == 16 else ""
                        raise DataError(f"{where} is damaged (file {name}/{key} has {size} bytes{said})")

    def _skipped_zeros_note(self) -> str:
        """What else an absent chunk may be in a store not written by gpc's format 2 (whose writer writes every one)."""
        fmt = self.root.attrs.get("gpc_format")
        if isinstance(fmt, int) and fmt >= 2:
            return ""
        return ("; a writer that skips chunks of zeros (zarr 3's default, gpc before format 2) may have left it out: "
                "if so, write the store again with every chunk")

    def _repair(self) -> None:
        """Drop what a killed writer left past the last committed episode."""
        n, e = self.n_steps, self.n_episodes
        for _, arr in _group(self.root["data"]).arrays():
            if arr.shape[0] > n:
                arr.resize((n,) + arr.shape[1:])
        if _array(self.root["meta/episode_ends"]).shape[0] > e:
            _array(self.root["meta/episode_ends"]).resize((e,))
        meta = _group(self.root["meta"])
        for name in ("episode_seeds", "episode_scores"):
            if name in meta and _array(meta[name]).shape[0] > e:
                _array(meta[name]).resize((e,))
        for partial in self.path.rglob("*.partial"):
            partial.unlink(missing_ok=True)

    # ------------------------------------------------------------------ reading
    @property
    def attrs(self) -> dict[str, Any]:
        return dict(self.root.attrs)

    @property
    def episode_ends(self) -> np.ndarray:
        return self._ends

    @property
    def n_episodes(self) -> int:
        return int(self._ends.size)

    @property
    def n_steps(self) -> int:
        return int(self._ends[-1]) if self._ends.size else 0

    @property
    def keys(self) -> list[str]:
        return sorted(k for k, _ in _group(self.root["data"]).arrays())

    def shape(self, key: str) -> tuple[int, ...]:
        return (self.n_steps,) + tuple(self.array(key).shape[1:])

    def array(self, key: str) -> zarr.Array:
        if key not in _group(self.root["data"]):
            raise DataError(f"{self.path}: missing key data/{key} (has {', '.join(self.keys) or 'none'})")
        return _array(_group(self.root["data"])[key])

    def read(self, key: str, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Steps ``[start, stop)`` of ``key``, never past the last whole episode: numbers, every one finite."""
        stop = self.n_steps if stop is None else min(stop, self.n_steps)
        arr = self.array(key)
        if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
            raise DataError(f"{self.path}: data/{key} holds {arr.dtype} values, not numbers")
        block = self._decoded(arr, f"data/{key}", start, stop)
        bad = _first_bad_row(block) if np.issubdtype(block.dtype, np.inexact) else None
        if bad is not None:
            raise DataError(f"{self.path}: data/{key} holds NaN or inf (first at step {start + bad})")
        return block

    def _decoded(self, arr: zarr.Array, name: str, start: int, stop: int) -> np.ndarray:
        """``arr[start:stop]``; a chunk that cannot be decoded (truncated, corrupt) is named in one line."""
        try:
            return np.asarray(arr[start:stop])
        except Exception as exc:  # numcodecs and zarr raise many types for a damaged chunk
            sync(_others_ended())
            step = int(arr.chunks[0]) if arr.chunks else 1
            for first in range(start - start % step, stop, step):  # find the chunk that fails
                try:
                    arr[first : min(first + step, arr.shape[0])]
                except Exception:
                    raise DataError(f"{self.path}: {name} chunk {first // step} ({_unit(name)} {first}-"
                                    f"{min(first + step, arr.shape[0]) - 1}) cannot be decoded ({_first_line(exc)})") from None
            raise DataError(f"{self.path}: {name} cannot be read ({_first_line(exc)})") from None

    def episode_slice(self, i: int) -> slice:
        if not -self.n_episodes <= i < self.n_episodes:
            raise DataError(f"{self.path}: episode {i} out of range (store has {self.n_episodes})")
        i %= self.n_episodes
        return slice(int(self._ends[i - 1]) if i else 0, int(self._ends[i]))

    def episode(self, i: int, keys: list[str] | None = None) -> dict[str, np.ndarray]:
        s = self.episode_slice(i)
        return {k: self.read(k, s.start, s.stop) for k in (keys or self.keys)}

    def episode_seeds(self) -> np.ndarray | None:
        """Seeds of our collected episodes; ``None`` for stores recorded elsewhere."""
        if "episode_seeds" not in _group(self.root["meta"]):
            return None
        return self._decoded(_array(self.root["meta/episode_seeds"]), "meta/episode_seeds", 0, self.n_episodes)

    def episode_scores(self) -> np.ndarray | None:
        if "episode_scores" not in _group(self.root["meta"]):
            return None
        return self._decoded(_array(self.root["meta/episode_scores"]), "meta/episode_scores", 0, self.n_episodes)

    def verify(self, keys: list[str] | None = None) -> None:
        """Read every committed step of ``keys`` (all by default) a few chunks at a time, so what :meth:`read`
        refuses (an undecodable chunk, values that are not numbers, NaN or inf) is found before any work."""
        for key in keys or self.keys:
            arr = self.array(key)
            rows = int(arr.chunks[0]) * max(1, _CHUNK_BYTES // max(1, arr.dtype.itemsize * math.prod(arr.chunks)))
            for start in range(0, self.n_steps, rows):
                self.read(key, start, start + rows)

    # ------------------------------------------------------------------ writing
    def append_episode(self, data: dict[str, np.ndarray], seed: int = -1, score: float = np.nan) -> None:
        """Append one whole episode; ``episode_ends`` is written last (the commit)."""
        self.append_episodes([data], [seed], [score])

    def append_episodes(self, episodes: Sequence[dict[str, np.ndarray]], seeds: Sequence[int],
                        scores: Sequence[float] | None = None) -> None:
        """Append whole episodes in one write per array (many short ones cost one chunk rewrite, not one each);
        ``episode_ends`` is written last (the commit): an interrupted call adds none of them."""
        if not self.writable:
            raise DataError(f"{self.path}: opened read-only")
        if not episodes or len(seeds) != len(episodes) or (scores is not None and len(scores) != len(episodes)):
            raise DataError(f"{self.path}: {len(episodes)} episodes need as many seeds and scores")
        keys = set(episodes[0])
        lengths = []
        for data in episodes:
            sizes = {k: len(v) for k, v in data.items()}
            length = next(iter(sizes.values()), 0)
            if length == 0 or any(n != length for n in sizes.values()):
                raise DataError(f"{self.path}: episode arrays must be non-empty and equally long, got {sizes}")
            if set(data) != keys or (self.n_episodes and keys != set(self.keys)):
                raise DataError(f"{self.path}: episode keys {sorted(data)} differ from the store's {self.keys or sorted(keys)}")
            lengths.append(length)
        joined = {k: np.concatenate([np.asarray(d[k]) for d in episodes]) for k in episodes[0]}
        group, meta = _group(self.root["data"]), _group(self.root["meta"])
        for key, value in joined.items():  # every check before the first write: a refused episode changes nothing
            if np.issubdtype(value.dtype, np.floating) and not np.all(np.isfinite(value)):
                raise DataError(f"{self.path}: refusing to write NaN or inf into data/{key}")
            if key in group and _array(group[key]).shape[1:] != value.shape[1:]:
                raise DataError(f"{self.path}: data/{key} has rows {_array(group[key]).shape[1:]}, episode has {value.shape[1:]}")
        for name in ("episode_seeds", "episode_scores"):
            if name not in meta:
                raise DataError(f"{self.path}: meta/{name} is missing (not a store gpc can append to)")
        for key, value in joined.items():
            if key not in group:
                row = int(np.prod(value.shape[1:])) * value.dtype.itemsize
                chunk = max(1, min(4096, _CHUNK_BYTES // max(1, row)))
                group.create_array(key, shape=(0,) + value.shape[1:], chunks=(chunk,) + value.shape[1:],
                                   dtype=value.dtype, compressors=_compressor())
            arr = _writes_every_chunk(_array(group[key]))
            arr.append(value.astype(arr.dtype, copy=False), axis=0)
        _writes_every_chunk(_array(meta["episode_seeds"])).append(np.asarray(seeds, dtype=np.int64))
        _writes_every_chunk(_array(meta["episode_scores"])).append(
            np.full(len(episodes), np.nan) if scores is None else np.asarray(scores, dtype=np.float64))
        new_ends = self.n_steps + np.cumsum(lengths, dtype=np.int64)
        _writes_every_chunk(_array(meta["episode_ends"])).append(new_ends)
        self._ends = np.append(self._ends, new_ends)

    def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
        for i in range(self.n_episodes):
            yield self.episode(i)
