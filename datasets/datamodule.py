"""Lightning DataModule: stores -> normalizer + episode-split window loaders."""

from __future__ import annotations

from dataclasses import dataclass

import lightning as L
import numpy as np
from torch.utils.data import DataLoader

from gpc.datasets.errors import DataError
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.datasets.sequence import WindowSpec, split_episodes, window_starts
from gpc.datasets.windows import IMAGE_KEYS, WindowDataset, load_stores


@dataclass(frozen=True)
class DataConfig:
    """Which stores and keys to read, and how to cut them into windows."""

    paths: tuple[str, ...]
    obs_keys: tuple[str, ...] = ("state",)
    action_key: str = "action"
    action_source: str | None = None  # read the actions from this array where a store has it (``expert_action``)
    horizon: int = 16  # steps per window (actions predicted)
    n_obs_steps: int = 2  # observation history kept at the window's start
    n_action_steps: int = 8  # actions executed per decision; sets the end padding
    obs_steps_override: int | None = None  # keep this many observation steps instead (world models)
    val_ratio: float = 0.05
    seed: int = 42
    val_episodes: tuple[int, ...] | None = None  # these episodes held out (a run started from a checkpoint keeps its own)
    state_spans: tuple[tuple[int, float, float], ...] = ()  # ranges the "state" key's normaliser spans at least (StateLayout.spans)
    batch_size: int = 256
    num_workers: int = 0

    def __post_init__(self) -> None:
        for name in ("horizon", "n_obs_steps", "n_action_steps", "batch_size"):
            if getattr(self, name) < 1:
                raise DataError(f"{name} {getattr(self, name)}: must be at least 1")
        if self.n_obs_steps > self.horizon or self.n_action_steps > self.horizon:
            raise DataError(f"n_obs_steps and n_action_steps must not exceed horizon {self.horizon}")

    @property
    def spec(self) -> WindowSpec:
        return WindowSpec(self.horizon, self.n_obs_steps - 1, self.n_action_steps - 1)


class EpisodeDataModule(L.LightningDataModule):
    """Loads stores once; the normalizer is fitted on training episodes only."""

    def __init__(self, config: DataConfig) -> None:
        super().__init__()
        self.config = config
        keys = tuple(dict.fromkeys(config.obs_keys + (config.action_key,)))
        self.arrays = load_stores(config.paths, keys, {config.action_key: config.action_source} if config.action_source else None)
        lengths = self.arrays.episode_lengths()
        if lengths.max() + config.spec.pad_before + config.spec.pad_after < config.horizon:
            raise DataError(f"horizon {config.horizon} is longer than every episode (longest {lengths.max()})")
        if config.val_episodes is None:
            self.train_episodes, self.val_episodes = split_episodes(self.arrays.n_episodes, config.val_ratio, config.seed)
        else:
            self.val_episodes = np.array(sorted(config.val_episodes), dtype=np.int64)
            self.train_episodes = np.setdiff1d(np.arange(self.arrays.n_episodes), self.val_episodes)
        for name, episodes in (("training", self.train_episodes), ("held-out", self.val_episodes)):
            if len(episodes) and not len(window_starts(self.arrays.episode_ends, episodes, config.spec, strict=False,
                                                 mid_motion=self.arrays.mid_motion)):
                raise DataError(f"{', '.join(config.paths)}: no {name} episode is long enough for a window of "
                                f"{config.horizon} steps (lower the horizon or --val-ratio, or record longer episodes)")
        mask = np.zeros(len(self.arrays.data[config.action_key]), dtype=bool)
        for i in self.train_episodes:
            start = int(self.arrays.episode_ends[i - 1]) if i else 0
            mask[start : int(self.arrays.episode_ends[i])] = True
        self.normalizer = MinMaxNormalizer.fit(
            {k: v[mask] if k not in IMAGE_KEYS else v[:1] for k, v in self.arrays.data.items()},
            image_keys=IMAGE_KEYS, spans={"state": config.state_spans},
        )
        obs_steps = config.obs_steps_override or config.n_obs_steps
        self.steps = {k: obs_steps for k in config.obs_keys}
        self.steps[config.action_key] = config.horizon

    def _loader(self, episodes: np.ndarray, shuffle: bool) -> DataLoader:
        dataset = WindowDataset(self.arrays, episodes, self.config.spec, self.steps)
        return DataLoader(
            dataset, batch_size=self.config.batch_size, shuffle=shuffle, drop_last=False,
            num_workers=self.config.num_workers, persistent_workers=self.config.num_workers > 0,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_episodes, shuffle=True)

    def val_dataloader(self) -> DataLoader | list[DataLoader]:
        """No validation episodes gives an empty list, which Lightning takes as "skip validation"."""
        if len(self.val_episodes) == 0:
            return []
        return self._loader(self.val_episodes, shuffle=False)
