"""How faithfully our simulator and renderer reproduce recorded Push-T data.

Replay: from each episode's first recorded state, step the recorded actions and compare
block poses with the recorded ones. Render: draw recorded states and compare with the
recorded frames. These are the acceptance figures for using Diffusion Policy's data.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gpc.datasets.store import EpisodeStore
from gpc.tasks.pusht.render import draw_state
from gpc.tasks.pusht.sim import PushTSim


@dataclass(frozen=True)
class ReplayReport:
    pos_err: np.ndarray  # (E,) max block position error over each episode, px
    ang_err: np.ndarray  # (E,) max block angle error over each episode, degrees
    pos_tol: float
    ang_tol: float

    @property
    def within(self) -> np.ndarray:
        return (self.pos_err <= self.pos_tol) & (self.ang_err <= self.ang_tol)

    def summary(self) -> dict:
        q = [50, 90, 97, 99, 100]
        return {
            "episodes": int(self.pos_err.size),
            "fraction_within": float(self.within.mean()),
            "tolerance": {"px": self.pos_tol, "deg": self.ang_tol},
            "pos_err_px_percentiles": dict(zip(map(str, q), np.percentile(self.pos_err, q).tolist())),
            "ang_err_deg_percentiles": dict(zip(map(str, q), np.percentile(self.ang_err, q).tolist())),
            "episodes_outside": np.flatnonzero(~self.within).tolist(),
        }


def replay(states: np.ndarray, actions: np.ndarray, episode_ends: np.ndarray,
           pos_tol: float = 0.01, ang_tol: float = 0.01) -> ReplayReport:
    """Replay every episode's actions from its first recorded state."""
    states = np.asarray(states, dtype=np.float64)
    actions = np.asarray(actions, dtype=np.float64)
    pos_err, ang_err = [], []
    start = 0
    for end in np.asarray(episode_ends, dtype=np.int64):
        sim = PushTSim()
        sim.set_state(states[start])
        got = np.empty((end - start - 1, 5))
        for i, t in enumerate(range(start, end - 1)):
            sim.step(actions[t])
            got[i] = sim.state()
        want = states[start + 1 : end]
        pos = np.abs(got[:, 2:4] - want[:, 2:4]).max() if len(got) else 0.0
        ang = np.abs((got[:, 4] - want[:, 4] + np.pi) % (2 * np.pi) - np.pi) if len(got) else np.zeros(1)
        pos_err.append(float(pos))
        ang_err.append(float(np.degrees(ang.max())))
        start = int(end)
    return ReplayReport(np.array(pos_err), np.array(ang_err), pos_tol, ang_tol)


def render_errors(states: np.ndarray, images: np.ndarray) -> np.ndarray:
    """Mean absolute difference (0..255 scale) per frame between our render and ``images``."""
    out = np.empty(len(states))
    for i, (s, img) in enumerate(zip(states, images)):
        ours = draw_state(np.asarray(s, dtype=np.float64), size=img.shape[0]).astype(np.float32)
        out[i] = np.abs(ours - np.asarray(img, dtype=np.float32)).mean()
    return out


def restore_divergence(states: np.ndarray, actions: np.ndarray, episode_ends: np.ndarray,
                       samples: int = 200, horizon: int = 16, seed: int = 0) -> np.ndarray:
    """Block-position gap (px) after ``horizon`` steps between a run and its restored replay.

    Measures what the snapshot leaves out (pymunk's private contact warm-start cache): at
    random recorded moments, step ``horizon`` recorded actions, restore, step them again.
    """
    states = np.asarray(states, dtype=np.float64)
    actions = np.asarray(actions, dtype=np.float64)
    ends = np.asarray(episode_ends, dtype=np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    rng = np.random.default_rng(seed)
    gaps: list[float] = []
    while len(gaps) < samples:
        e = int(rng.integers(len(ends)))
        if ends[e] - starts[e] <= horizon + 2:
            continue
        t = int(rng.integers(1, ends[e] - starts[e] - horizon))
        sim = PushTSim()
        sim.set_state(states[starts[e]])
        for k in range(starts[e], starts[e] + t):
            sim.step(actions[k])
        snap = sim.snapshot()
        for k in range(starts[e] + t, starts[e] + t + horizon):
            sim.step(actions[k])
        first = sim.block_pose()
        sim.restore(snap)
        for k in range(starts[e] + t, starts[e] + t + horizon):
            sim.step(actions[k])
        gaps.append(float(np.abs(sim.block_pose()[:2] - first[:2]).max()))
    return np.array(gaps)


def check_store(path: str | Path, episodes: int = 0, frame_stride: int = 10) -> dict:
    """Replay, restore and render figures of a recorded Push-T store (``gpc check-sim``)."""
    store = EpisodeStore.open(path)
    for key in ("state", "action"):
        store.array(key)
    n_eps = store.n_episodes if episodes == 0 else min(episodes, store.n_episodes)
    stop = int(store.episode_ends[n_eps - 1])
    states, actions = store.read("state", 0, stop), store.read("action", 0, stop)
    store.verify(["state", "action"])
    rep = replay(states, actions, store.episode_ends[:n_eps])
    gaps = restore_divergence(states, actions, store.episode_ends[:n_eps])
    out = {"data": str(path), "replay": rep.summary(),
           "restore": {"samples": int(gaps.size), "horizon": 16, "exact_fraction": float(np.mean(gaps == 0)),
                       "gap_px_p50": float(np.median(gaps)), "gap_px_p95": float(np.percentile(gaps, 95)),
                       "gap_px_max": float(gaps.max())}}
    if "img" in store.keys:
        idx = np.arange(0, stop, frame_stride)
        imgs = np.asarray(store.array("img").oindex[idx])  # each chunk decompressed once
        mad = render_errors(states[idx], imgs)
        out["render"] = {"frames": int(idx.size), "mad_mean": float(mad.mean()),
                         "mad_p99": float(np.percentile(mad, 99)), "mad_max": float(mad.max())}
    return out
