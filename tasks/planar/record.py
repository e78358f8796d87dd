"""The recording loop of scripted episodes, in Diffusion Policy's data layout.

Each step stores what was observed before acting, the action taken, and ``n_contacts`` of the step that led to the
observation (as Diffusion Policy's recorder does); images are uint8, everything else float32. A task wraps it: it
builds and resets its environment and its controller, and says how a step is observed.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Protocol, TypeVar

import numpy as np

from gpc.tasks.base import EXPERT_ACTION_KEY, ActionNoise, EpisodeStats
from gpc.tasks.planar.scene import WORKSPACE
from gpc.tasks.planar.sim_model import SIM_KEY

Scene = TypeVar("Scene", contravariant=True)


class ScriptedPolicy(Protocol[Scene]):
    """A privileged controller: reads the true scene and the goal, returns a target position."""

    def reset(self, seed: int) -> None: ...

    def act(self, sim: Scene, goal: np.ndarray) -> np.ndarray: ...


class SteppedEnv(Protocol):
    """A reset environment whose ``step`` reports the step's contacts as ``info["n_contacts"]``."""

    def step(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict[str, Any]]: ...


class ResettableEnv(SteppedEnv, Protocol):
    """A ``SteppedEnv`` that starts an episode from a seed (Gymnasium's ``reset``)."""

    def reset(self, *, seed: int | None = None) -> Any: ...


class Seeded(Protocol):
    """A controller that restarts from a seed (every scripted one: its draws come from the episode's seed)."""

    def reset(self, seed: int) -> None: ...


def record_loop(env: SteppedEnv, act: Callable[[], np.ndarray], observe: Callable[[], dict[str, np.ndarray]], seed: int,
                max_steps: int, stop_on_success: bool, low: float | np.ndarray = 0.0,
                high: float | np.ndarray = WORKSPACE, noise: ActionNoise | None = None) -> tuple[dict[str, np.ndarray], EpisodeStats]:
    """Step ``env`` with ``act()``'s targets (clipped to ``[low, high]``, per entry where arrays: the planar
    workspace by default) for at most ``max_steps``; the arrays and their summary.

    ``terminated`` is success; demonstrations stop there (``stop_on_success``), exploration runs on. ``truncated``
    (a simulation gone unstable) ends the episode with its score so far. With ``noise`` the step runs the target
    plus the noise (clipped), stored as ``action``, and the target itself is stored as ``expert_action``.
    """
    rows: dict[str, list[np.ndarray]] = {}
    best, success, n_contacts, contacts = 0.0, False, 0, []
    draw: Callable[[], np.ndarray] | None = None
    for _ in range(max_steps):
        action = label = np.clip(np.asarray(act(), dtype=np.float64), low, high)
        labels: dict[str, np.ndarray] = {}
        if noise is not None:  # the sampler is made at the first step, which gives the action's width
            draw = draw or noise.sampler(seed, np.broadcast_to(low, label.shape), np.broadcast_to(high, label.shape))
            action, labels = np.clip(label + draw(), low, high), {EXPERT_ACTION_KEY: label}
        step = {**observe(), "action": action, "n_contacts": np.array([n_contacts], np.float64), **labels}
        for key, value in step.items():
            rows.setdefault(key, []).append(value)
        _, reward, terminated, truncated, info = env.step(action)
        n_contacts = info["n_contacts"]
        contacts.append(n_contacts > 0)
        best = max(best, reward)
        success = success or terminated
        if (terminated and stop_on_success) or truncated:
            break
    data = {k: np.stack(v).astype(np.uint8 if k == "img" else np.float32) for k, v in rows.items()}
    return data, EpisodeStats(seed, len(data["action"]), float(best), bool(success), float(np.mean(contacts)))


def record_from_reset(env: ResettableEnv, policy: Seeded, act: Callable[[], np.ndarray],
                      observe: Callable[[], dict[str, np.ndarray]], seed: int, config: RecordConfig,
                      low: float | np.ndarray = 0.0, high: float | np.ndarray = WORKSPACE) -> tuple[dict[str, np.ndarray], EpisodeStats]:
    """Reset ``env`` and ``policy`` to ``seed``, then ``record_loop`` as ``config`` says: a task's ``record_episode``."""
    env.reset(seed=seed)
    policy.reset(seed)
    return record_loop(env, act, observe, seed, config.max_steps, config.stop_on_success, low, high, noise=config.noise)


def with_extras(obs: dict[str, np.ndarray], env: Any, images: bool, sim: bool) -> dict[str, np.ndarray]:
    """``obs`` with the camera's frame (``img``) and the full simulator state (``SIM_KEY``: never recorded, the
    ground-truth world model restores from it) where asked: the tail of every task's ``observe``."""
    if images:
        obs["img"] = env.render()
    if sim:
        obs[SIM_KEY] = env.sim.vector()
    return obs


def episode_maxima(rewards: np.ndarray, episode_ends: np.ndarray) -> np.ndarray:
    """Each episode's score, its largest per-step reward; ``episode_ends`` as a store's (exclusive, cumulative)."""
    ends = np.asarray(episode_ends).astype(int)
    starts = np.concatenate([[0], ends[:-1]])
    return np.array([np.max(rewards[s:e]) for s, e in zip(starts, ends)])


def scripted_params(policy: object, kind: str, max_steps: int) -> dict[str, Any]:
    """What a store records about the scripted collector that wrote it (its class and config): resuming checks it."""
    config = getattr(policy, "config", None)
    return {"policy": type(policy).__name__, "config": asdict(config) if config is not None else {},
            "stop_on_success": kind == "expert", "max_steps": max_steps}


@dataclass(frozen=True)
class RecordConfig:
    """How long episodes run and what is stored (a task subclasses it for its own episode length)."""

    max_steps: int = 300
    stop_on_success: bool = True  # demonstrations end at success; exploration runs on
    images: bool = True
    noise: ActionNoise | None = None  # DART: the expert's actions run with this noise (``record_loop``)

    def __post_init__(self) -> None:
        if self.max_steps < 1:
            raise ValueError(f"max_steps {self.max_steps}: must be at least 1")


@dataclass(frozen=True)
class ScriptedCollectors:
    """A task's two scripted collectors (``module:Class``, imported when first used, so naming a task loads neither) and
    the module recording their episodes (its ``RecordConfig`` and ``record_episode``): what ``gpc collect`` (the expert,
    stopping at success) and ``--explore`` run, as ``Task.record`` and ``Task.collector_params``."""

    expert: str
    explore: str
    recorder: str

    def policy(self, kind: str) -> Any:
        """A fresh collector of ``kind``."""
        spec = {"expert": self.expert, "explore": self.explore}.get(kind)
        if spec is None:
            raise ValueError(f"collector {kind!r}: use expert or explore")
        module, name = spec.split(":")
        return getattr(importlib.import_module(module), name)()

    def params(self, kind: str, max_steps: int) -> dict[str, Any]:
        return scripted_params(self.policy(kind), kind, max_steps)

    def record(self, kind: str, seed: int, goal: str, images: bool, max_steps: int,
               noise: ActionNoise | None = None) -> tuple[dict[str, np.ndarray], EpisodeStats]:
        recorder = importlib.import_module(self.recorder)
        config = recorder.RecordConfig(max_steps=max_steps, stop_on_success=kind == "expert", images=images, noise=noise)
        return recorder.record_episode(self.policy(kind), seed, config)
