"""Training samples: windows of observations and actions drawn from one or more stores."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from gpc.datasets.errors import DataError
from gpc.datasets.sequence import MID_MOTION, WindowSpec, window_indices, window_starts
from gpc.datasets.store import EpisodeStore

IMAGE_KEYS = ("img", "pixels")


@dataclass
class EpisodeArrays:
    """Steps of several stores concatenated in memory, with their joint episode ends."""

    data: dict[str, np.ndarray]
    episode_ends: np.ndarray
    sources: list[str] = field(default_factory=list)
    counts: list[int] = field(default_factory=list)  # episodes per source, in order
    mid_motion: np.ndarray | None = None  # per episode: it begins mid-motion (its store's ``episode_starts``)

    @property
    def n_episodes(self) -> int:
        return int(self.episode_ends.size)

    def episode_lengths(self) -> np.ndarray:
        return np.diff(np.concatenate([[0], self.episode_ends]))


def load_stores(paths: Sequence[str | Path], keys: Sequence[str], prefer: Mapping[str, str] | None = None) -> EpisodeArrays:
    """Read ``keys`` of every store into memory; images are kept as uint8 to save memory. ``prefer`` reads a key
    from another array where a store has it (``{"action": "expert_action"}``: a DART store's labels, and the
    actions of stores whose expert ran without noise)."""
    if not paths:
        raise DataError("no dataset given (pass --dataset PATH)")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    ends, offset, counts, moving = [], 0, [], []
    for path in paths:
        store = EpisodeStore.open(path)
        if store.n_episodes == 0:
            raise DataError(f"{path}: holds no episodes")
        held = set(store.keys) if prefer else set()  # listed once per store, only when a key may come from elsewhere
        for key in keys:
            source = (prefer or {}).get(key, key)
            # numbers, every one finite, from chunks that are all there (the store checks)
            arr = store.read(source if source in held else key)
            if key in IMAGE_KEYS and arr.dtype != np.uint8:  # (uint8 already is; rint would widen it)
                arr = np.clip(np.rint(arr), 0, 255).astype(np.uint8)
            if parts[key] and parts[key][0].shape[1:] != arr.shape[1:]:
                raise DataError(f"{path}: data/{key} rows are {arr.shape[1:]}, other stores have {parts[key][0].shape[1:]}")
            parts[key].append(arr)
        ends.append(store.episode_ends + offset)
        offset += store.n_steps
        counts.append(store.n_episodes)
        moving.append(np.full(store.n_episodes, store.attrs.get("episode_starts") == MID_MOTION))
    return EpisodeArrays(
        {k: np.concatenate(v) for k, v in parts.items()}, np.concatenate(ends), [str(p) for p in paths], counts,
        np.concatenate(moving) if any(m.any() for m in moving) else None,
    )


class WindowDataset(Dataset):
    """Each item: for every key, ``steps[key]`` consecutive steps of one padded window.

    A policy keeps the first ``n_obs_steps`` observations and all ``horizon`` actions; a
    world model keeps every step. Tensors are float32; images stay ``(T, H, W, C)`` 0..255.
    """

    def __init__(self, arrays: EpisodeArrays, episodes: np.ndarray, spec: WindowSpec, steps: dict[str, int]) -> None:
        for key, n in steps.items():
            if key not in arrays.data:
                raise DataError(f"key {key!r} was not loaded (have {', '.join(arrays.data)})")
            if not 1 <= n <= spec.horizon:
                raise DataError(f"{key}: {n} steps do not fit a window of {spec.horizon}")
        self.arrays, self.spec, self.steps = arrays, spec, steps
        self.rows = window_starts(arrays.episode_ends, episodes, spec, mid_motion=arrays.mid_motion)

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        idx = window_indices(self.rows[i], self.spec.horizon)
        return {
            key: torch.from_numpy(np.ascontiguousarray(self.arrays.data[key][idx[:n]])).float()
            for key, n in self.steps.items()
        }
