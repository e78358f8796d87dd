"""Fixed-length windows over episodes, padded at episode edges as Diffusion Policy pads them.

A window of ``horizon`` steps may start up to ``pad_before`` steps before an episode and end
up to ``pad_after`` steps after it; steps outside the episode repeat its first or last
step. With ``pad_before = n_obs_steps - 1`` and ``pad_after = n_action_steps - 1`` every
step of every episode is seen as the "current" observation at least once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from gpc.datasets.errors import DataError


@dataclass(frozen=True)
class WindowSpec:
    """How many steps a sample spans and how far it may hang over episode edges."""

    horizon: int
    pad_before: int = 0
    pad_after: int = 0

    def __post_init__(self) -> None:
        if self.horizon < 1:
            raise DataError(f"horizon {self.horizon}: must be at least 1")
        if not 0 <= self.pad_before < self.horizon or not 0 <= self.pad_after < self.horizon:
            raise DataError(f"padding ({self.pad_before}, {self.pad_after}) must lie in [0, horizon={self.horizon})")


def window_starts(episode_ends: np.ndarray, episodes: np.ndarray, spec: WindowSpec) -> np.ndarray:
    """``(N, 3)`` rows of (episode start, episode length, window offset in the episode)."""
    rows = []
    for i in episodes:
        start = int(episode_ends[i - 1]) if i else 0
        length = int(episode_ends[i]) - start
        offsets = np.arange(-spec.pad_before, length - spec.horizon + spec.pad_after + 1)
        rows.append(np.stack([np.full_like(offsets, start), np.full_like(offsets, length), offsets], axis=1))
    if not rows or sum(len(r) for r in rows) == 0:
        raise DataError(
            f"no window of {spec.horizon} steps fits the selected episodes (horizon longer than every episode?)"
        )
    return np.concatenate(rows).astype(np.int64)


def window_indices(row: np.ndarray, horizon: int) -> np.ndarray:
    """Absolute step indices of one window, edge-padded by clipping into its episode."""
    start, length, offset = (int(v) for v in row)
    return start + np.clip(offset + np.arange(horizon), 0, length - 1)


def split_episodes(n_episodes: int, val_ratio: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Seeded episode-level train/validation split (whole episodes never straddle it)."""
    if not 0.0 <= val_ratio < 1.0:
        raise DataError(f"val_ratio {val_ratio}: must lie in [0, 1)")
    n_val = 0 if val_ratio == 0 or n_episodes < 2 else min(max(1, round(n_episodes * val_ratio)), n_episodes - 1)
    rng = np.random.default_rng(seed)
    val = np.sort(rng.choice(n_episodes, size=n_val, replace=False)) if n_val else np.zeros(0, np.int64)
    train = np.setdiff1d(np.arange(n_episodes), val)
    return train, val


def recorded_split(record: dict[str, Any]) -> tuple[int, float] | None:
    """(seed, val ratio) of the split a run record describes (``split_seed`` once a run was started
    from a checkpoint and kept its split; ``seed`` before); None when it records none."""
    if "val_ratio" not in record:
        return None
    return int(record.get("split_seed", record["seed"])), float(record["val_ratio"])


def recorded_held_out(n_episodes: int, record: dict[str, Any]) -> np.ndarray:
    """The episodes a run record held out from training."""
    split = recorded_split(record)
    if split is None:
        raise DataError("the checkpoint does not record its training split; pass --split all with held-out data")
    return split_episodes(n_episodes, split[1], split[0])[1]
