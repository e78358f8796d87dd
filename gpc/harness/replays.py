"""The policy's proposals replayed in the true simulator, kept as short episodes a state world model trains on.

A ranking planner asks its world model to tell apart K chunks from one state. The episodes a model is trained on
hold one chunk per state (the one executed), so it learns where trajectories go more than what a different chunk
would change. At each decision of the ranking probe (``gpc eval ranking --save-replays``) every proposal is already
replayed from the exact simulator state; this keeps those replays. Each becomes one short episode laid out as a
world-model window wants it (``WorldModelConfig``'s timeline; here L = 3 observed states)::

    states   | s_-2 s_-1 s_0 | f_1 ... f_T |    the last L observed states, then the proposal's true futures
    actions  | a_-2 a_-1 c_1 | c_2 ... pad |    a_-2, a_-1: the actions executed before; c: the proposal (T actions)

A proposal runs from the current step (T = horizon - now), so L = n_obs_steps + now observed states make each
replay exactly one window of a world model with the policy's history and horizon, whose first prediction (s_0 from
a_-1) is of a step that truly happened. The store says its episodes begin mid-motion (``episode_starts``), so no
window pads their start: a history repeating its first state would claim the scene was at rest. Decisions without
L - 1 executed actions before them (an episode's first ones) are skipped.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gpc.datasets.errors import DataError
from gpc.datasets.fresh import fresh
from gpc.datasets.sequence import MID_MOTION
from gpc.datasets.store import EpisodeStore
from gpc.harness.files import check_out
from gpc.models.planning.planner import Planner
from gpc.tasks.base import ACTION_KEY, STATE_KEY, Task


def check_replay_out(path: Path) -> None:
    """Before any work: ``path`` is new (a replay store is written whole, never appended to) and writable."""
    if path.exists() or path.is_symlink():
        raise DataError(f"{path}: already exists; --save-replays writes a new store (give another path, or remove it)")
    check_out(path.parent)


class ReplayLog:
    """Mini-episodes of the replayed proposals, per episode in seed order, kept in memory until written."""

    def __init__(self, history: int) -> None:
        self.history = history  # L: observed states kept before each replay
        self.executed: dict[int, deque[np.ndarray]] = {}  # seed -> the last L - 1 actions it executed
        self.episodes: list[tuple[int, dict[str, np.ndarray]]] = []

    @classmethod
    def for_proposer(cls, proposer: Planner) -> ReplayLog:
        """Replays one window long for a world model with ``proposer``'s history and horizon (the module docstring)."""
        return cls(proposer.n_obs_steps + proposer.now)

    def add(self, seeds: Sequence[int], states: np.ndarray, chunks: np.ndarray, futures: np.ndarray,
            executed: np.ndarray) -> None:
        """One decision of the episodes ``seeds``: their observed ``states`` (B, >=L, D), the proposals ``chunks``
        (B, K, T, A), their true ``futures`` (B, K, T, D), and the actions then executed (B, n, A)."""
        h, k = self.history, chunks.shape[1]
        for b, seed in enumerate(seeds):
            before = self.executed.setdefault(int(seed), deque(maxlen=max(h - 1, 1)))
            if len(before) >= h - 1:
                past = np.stack(list(before)[len(before) - (h - 1):]) if h > 1 else np.zeros((0, chunks.shape[-1]))
                actions = np.concatenate([np.broadcast_to(past, (k, *past.shape)), chunks[b], chunks[b, :, -1:]], axis=1)
                state = np.concatenate([np.broadcast_to(states[b, -h:], (k, h, states.shape[-1])), futures[b]], axis=1)
                actions, state = actions.astype(np.float32), state.astype(np.float32)
                self.episodes.extend((int(seed), {STATE_KEY: state[i], ACTION_KEY: actions[i]}) for i in range(k))
            before.extend(np.asarray(executed[b]))

    def write(self, path: Path, task: Task, provenance: dict[str, Any]) -> int:
        """A new store at ``path`` holding every mini-episode (grouped by seed, in the order decided); their count."""
        if not self.episodes:
            raise DataError(f"{path}: no decision had {self.history - 1} executed actions before it; nothing to save")
        by_seed: dict[int, list[dict[str, np.ndarray]]] = {}
        for seed, data in self.episodes:  # per seed, in the order decided
            by_seed.setdefault(seed, []).append(data)
        with fresh(path) as made:
            store = EpisodeStore.create(path, {"task": task.name, "collector": {"kind": "replays", **provenance},
                                               "keys": [STATE_KEY, ACTION_KEY], "episode_starts": MID_MOTION})
            for seed in sorted(by_seed):  # one write per seed; scores unknown (`gpc data info` reads them off the states)
                store.append_episodes(by_seed[seed], [seed] * len(by_seed[seed]))
            made.keep()
        return len(self.episodes)
