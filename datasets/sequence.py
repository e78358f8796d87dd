"""Fixed-length windows over episodes, padded at episode edges as Diffusion Policy pads them.

A window of ``horizon`` steps may start up to ``pad_before`` steps before an episode and end
up to ``pad_after`` steps after it; steps outside the episode repeat its first or last
step. With ``pad_before = n_obs_steps - 1`` and ``pad_after = n_action_steps - 1`` every
step of every episode is seen as the "current" observation at least once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gpc.datasets.errors import DataError

# A store's attribute ``episode_starts``: ``MID_MOTION`` where its episodes begin inside longer runs (no start padding).
MID_MOTION = "mid-motion"


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


def window_starts(episode_ends: np.ndarray, episodes: np.ndarray, spec: WindowSpec, strict: bool = True,
                  mid_motion: np.ndarray | None = None) -> np.ndarray:
    """``(N, 3)`` rows of (episode start, episode length, window offset in the episode).

    ``mid_motion``: per episode (all of them, by index), whether it begins while things move (a replay cut from a
    longer run, ``MID_MOTION``): no window starts before it, since a history repeating its first step would claim rest."""
    rows = []
    for i in episodes:
        start = int(episode_ends[i - 1]) if i else 0
        length = int(episode_ends[i]) - start
        before = 0 if mid_motion is not None and mid_motion[i] else spec.pad_before
        offsets = np.arange(-before, length - spec.horizon + spec.pad_after + 1)
        rows.append(np.stack([np.full_like(offsets, start), np.full_like(offsets, length), offsets], axis=1))
    if not rows or sum(len(r) for r in rows) == 0:
        if not strict:
            return np.zeros((0, 3), np.int64)
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


def identities(sources: Sequence[str], counts: Sequence[int], episodes: Sequence[int]) -> list[list[Any]]:
    """``[store, episode]`` of each of the concatenated stores' ``episodes`` (global indices), the store by its
    absolute path: what a checkpoint records of its held-out episodes, whatever order the stores come in."""
    starts = np.concatenate([[0], np.cumsum(counts)])
    out = []
    for i in episodes:
        s = int(np.searchsorted(starts, i, side="right") - 1)
        out.append([str(Path(sources[s]).resolve()), int(i - starts[s])])
    return out


def select(wanted: Sequence[Sequence[Any]], sources: Sequence[str], counts: Sequence[int], strict: bool = True) -> np.ndarray:
    """Global indices, over the given stores, of the ``[store, episode]`` identities ``wanted``; a store is found by
    its absolute path, or else by its name when only one given store has it. ``strict``: missing stores are named
    in an error (else their episodes are left out)."""
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(int)
    paths = [str(Path(s).resolve()) for s in sources]
    names = [Path(p).name for p in paths]
    chosen, missing = [], []
    for store, episode in wanted:
        if store in paths:
            s = paths.index(store)
        elif names.count(Path(store).name) == 1:
            s = names.index(Path(store).name)
        else:
            missing.append(store)
            continue
        if episode < counts[s]:
            chosen.append(starts[s] + int(episode))
    if missing and strict:
        raise DataError(f"the checkpoint held out episodes of {', '.join(sorted(set(missing)))}; pass those stores "
                        "with --dataset (or --split all with stores it never saw)")
    return np.array(sorted(chosen), dtype=np.int64)


@dataclass(frozen=True)
class HeldOutOf:
    """Another run's data record (what it trained on and held out) and the name errors give it."""

    name: str
    record: dict[str, Any]

    @property
    def label(self) -> str:
        return f"held out by {self.name}"


def held_out_by(other: dict[str, Any], own: dict[str, Any], sources: Sequence[str], counts: Sequence[int],
                other_name: str = "the other run") -> np.ndarray:
    """The episodes, among the given stores, that another run held out, refused where this run trained on one of
    them: two models compared on exactly the episodes neither saw. A store this run's record lists is matched by its
    path, or by its name where that path is not on this machine."""
    if other.get("held_out") is None:
        raise DataError(f"{other_name} does not list its held-out episodes by store (trained before gpc recorded them)")
    chosen = select(other["held_out"], sources, counts, strict=False)
    if len(chosen) == 0:
        raise DataError(f"{other_name} held out no episode of the given stores; pass the stores it was trained on")
    paths = [str(Path(s).resolve()) for s in sources]
    trained = set()
    for store in own.get("datasets", []):
        mine = Path(store).resolve()
        trained |= {i for i, p in enumerate(paths) if p == str(mine) or (not mine.exists() and Path(p).name == mine.name)}
    own_held = set(select(own["held_out"], sources, counts, strict=False).tolist()) if own.get("held_out") else set()
    starts = np.concatenate([[0], np.cumsum(counts)])
    for i in chosen.tolist():
        s = int(np.searchsorted(starts, i, side="right") - 1)
        if s in trained and i not in own_held:
            raise DataError(f"{sources[s]} episode {i - starts[s]}: held out by {other_name} but in this model's "
                            "training data; compare on stores it never saw or whose held-out episodes it shares")
    return chosen


def recorded_held_out(record: dict[str, Any], sources: Sequence[str], counts: Sequence[int], strict: bool = True) -> np.ndarray:
    """The episodes, among the given stores, that a run record held out from training: by their identity when the
    record lists them (``held_out``), else by its split seed and ratio over the stores in the order given.
    ``strict``: a recorded store missing from ``sources`` is an error (else its episodes are left out)."""
    if record.get("held_out") is not None:
        return select(record["held_out"], sources, counts, strict)
    split = recorded_split(record)
    if split is None:
        raise DataError("the checkpoint does not record its training split; pass --split all with held-out data")
    return split_episodes(int(sum(counts)), split[1], split[0])[1]
