"""The task interface: everything outside ``tasks/`` receives a task as one ``Task`` and nothing else.

A task brings its data schema (``TaskLayout``: state entries, action box, each object's
outline and goal, frame geometry), its environment, how one step is observed, its scripted
collectors (an expert and an explorer), the ground-truth simulator as a world model, a
renderer for predicted futures and a one-line description for a vision-language model.
Collection, training, planning and closed-loop evaluation are written against this class
only; ``tests/toy_task.py`` defines a second task with it and runs every planner on it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from gpc.datasets.layout import TaskLayout

COLLECTORS = ("expert", "explore")
# Environment seeds are 32-bit: Push-T's reset draws from NumPy's legacy RandomState (Diffusion Policy's test seeds), and
# Lightning's seed_everything takes no more. Commands refuse a larger seed, naming the option, before they make anything.
MAX_SEED = 2**32 - 1


def check_seeds(first: int, last: int, option: str) -> None:
    """Refuse seeds outside 0..MAX_SEED in one line naming ``option`` (``first``..``last``: the seeds it gives)."""
    if first < 0:
        raise ValueError(f"{option}: seed {first} is negative; seeds run from 0 to {MAX_SEED} (2**32 - 1)")
    if last > MAX_SEED:
        raise ValueError(f"{option}: seed {last} is past {MAX_SEED}, the largest seed (2**32 - 1)")
STATE_KEY, ACTION_KEY, GOAL_KEY, IMAGE_KEY = "state", "action", "goal", "img"  # the data keys every component shares
EXPERT_ACTION_KEY = "expert_action"  # a noisy demonstration's labels: what the expert asked for (``action``: what ran)


@dataclass(frozen=True)
class ActionNoise:
    """DART-style demonstrations (Laskey et al. 2017): the expert's actions run with noise added, so its
    demonstrations visit the states a policy's own errors lead to, and record what the expert asked for there.

    The noise is Gaussian, ``scale`` of each action entry's range, correlated over about ``steps`` control steps
    (an Ornstein-Uhlenbeck process: one step's noise would be filtered out by a PD-tracked agent before it moved
    anything), drawn from the episode's seed. A store keeps ``action`` as what ran (the world model learns from it)
    and ``expert_action`` as the label a policy learns (``gpc train policy --labels expert_action``).
    """

    scale: float
    steps: float = 4.0

    def __post_init__(self) -> None:
        if not 0.0 < self.scale <= 0.5:
            raise ValueError(f"--dart {self.scale}: the noise's share of the action range must lie in (0, 0.5]")
        if not self.steps >= 1.0:
            raise ValueError(f"--dart-steps {self.steps}: the noise's correlation must span at least 1 step")

    def sampler(self, seed: int, low: np.ndarray, high: np.ndarray) -> Callable[[], np.ndarray]:
        """The episode's noise, one draw per step: independent of the expert's own random stream."""
        rng = np.random.default_rng([seed, 0xDA27])
        sigma, rho = self.scale * (high - low), float(np.exp(-1.0 / self.steps))
        state = rng.normal(0.0, 1.0, sigma.shape) * sigma

        def draw() -> np.ndarray:
            nonlocal state
            out = state
            state = rho * state + np.sqrt(1.0 - rho**2) * rng.normal(0.0, 1.0, sigma.shape) * sigma
            return out

        return draw


class TaskEnv(Protocol):
    """The Gymnasium calls the harness makes (``reset(seed=...)``, ``step``), and a frame for videos."""

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]: ...

    def step(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict[str, Any]]: ...

    def frame(self, size: int) -> np.ndarray: ...


@dataclass(frozen=True)
class EpisodeStats:
    """What a scripted episode achieved (``Task.record`` returns it beside the arrays)."""

    seed: int
    steps: int
    score: float  # the episode's maximum reward
    success: bool
    contact_fraction: float  # share of steps with the agent touching the object (0 when the task does not count)


def _score_reaches_one(scores: np.ndarray) -> np.ndarray:
    return np.asarray(scores) >= 1.0


@dataclass(frozen=True)
class Task:
    """One task, as collection, training, planning and evaluation see it."""

    layout: TaskLayout
    description: str  # one line a vision-language model is told the task is
    goal_modes: tuple[str, ...]  # "fixed" (the layout's goal) and, if supported, "random" (a goal per seed)
    make_env: Callable[[str], TaskEnv]  # goal mode -> a fresh environment
    observe: Callable[[TaskEnv, bool, bool], dict[str, np.ndarray]]  # (env, images, simulator state) -> one step's observation
    record_keys: Callable[[bool, str], list[str]]  # (images, goal mode) -> the keys ``record`` stores
    # (collector, seed, goal, images, max steps[, the expert's action noise]) -> the arrays and their summary; called
    # with five arguments unless `gpc collect --dart` gives noise (a task that takes none then is refused)
    record: Callable[..., tuple[dict[str, np.ndarray], EpisodeStats]]
    collector_params: Callable[[str, int], dict[str, Any]]  # (collector, max steps) -> what a store records about it
    env_params: Callable[[str, int], dict[str, Any]]  # (goal mode, max steps) -> what a store records about the env
    simulator: Callable[[], Any]  # the true simulator as a world model (the ceiling planner ``gt-sim``)
    sim_key: str  # the observation the simulator world model restores from
    render_state: Callable[..., np.ndarray]  # (state, goal=None, size=96) -> RGB frame as the camera would show it
    # (a store's arrays by key (``state``, and ``goal`` where it holds one), episode ends) -> each episode's score
    episode_scores: Callable[[Mapping[str, np.ndarray], np.ndarray], np.ndarray]
    max_episode_steps: int = 300
    # Episode scores -> which succeeded, where success is a function of the score alone (Push-T: a score of 1, coverage
    # 0.95; drawing: an F1 above 0.9, as its env says); None where it is not (both of swap's objects, stacking's settled
    # steps): a store's summary then reports no success rate rather than a wrong one.
    succeeded: Callable[[np.ndarray], np.ndarray] | None = _score_reaches_one
    # The reward planners score predicted states with, by name (``gpc.models.rewards.state``): tasks never import models.
    state_reward: str = "registration"
    info_metrics: tuple[str, ...] = ()  # step-info values whose episode maximum a result records (``<name>_max``)
    info_minima: tuple[str, ...] = ()  # ... and those whose minimum it records (``<name>_min``: a distance, lower is better)
    draw_plan: Callable[[np.ndarray, np.ndarray, int], np.ndarray] | None = None  # (frame, chunk, executed) -> frame
    draw_futures: Callable[[np.ndarray, np.ndarray, np.ndarray, int], np.ndarray] | None = None  # (frame, futures, scores, chosen)
    pose_coverage: Callable[[np.ndarray], float] | None = None  # states -> share of the object's pose space visited
    check_replay: Callable[..., dict[str, Any]] | None = None  # recorded store -> how closely the simulator replays it
    row_shapes: Mapping[str, tuple[int, ...]] = field(default_factory=dict)  # one step's shape per stored key, beyond the layout's
    references: Mapping[str, Mapping[str, float]] = field(default_factory=dict)  # published tables: name -> controller label -> score
    # Policies trained elsewhere: their observation names (LeRobot's, Diffusion Policy's) -> (this task's
    # observation key, how many leading entries of it the feature is; None: all of it).
    foreign_features: Mapping[str, tuple[str, int | None]] = field(default_factory=dict)
    # Observation keys computed from a step's other keys (never recorded), for such policies.
    derived: Mapping[str, Callable[[Mapping[str, np.ndarray]], np.ndarray]] = field(default_factory=dict)
    # LeRobot datasets: an episode of a store -> LeRobot features, and back (``gpc data export`` / ``import``).
    to_lerobot: Callable[[Mapping[str, np.ndarray]], dict[str, np.ndarray]] | None = None
    from_lerobot: Callable[[Mapping[str, np.ndarray]], dict[str, np.ndarray]] | None = None
    fps: int = 10  # control steps per second (a LeRobot dataset's fps)

    def __post_init__(self) -> None:
        if not self.goal_modes or self.goal_modes[0] != "fixed":
            raise ValueError(f"task {self.name}: goal modes {self.goal_modes} must start with 'fixed'")

    @property
    def name(self) -> str:
        return self.layout.name

    def row_shape(self, key: str) -> tuple[int, ...] | None:
        """The shape one step of ``key`` must have in this task's stores (None: not fixed, e.g. image sizes)."""
        known = {STATE_KEY: (self.layout.state.dim,), ACTION_KEY: (self.layout.action.dim,),
                 EXPERT_ACTION_KEY: (self.layout.action.dim,),
                 GOAL_KEY: (len(self.layout.pose_dims),), **self.row_shapes}
        return known.get(key)

    def observed_keys(self, images: bool, goal: str) -> list[str]:
        """Every key a controller can read: the recorded ones and the derived ones."""
        return self.record_keys(images, goal) + [k for k in self.derived if k not in self.record_keys(images, goal)]

    def with_derived(self, obs: dict[str, np.ndarray], keys: tuple[str, ...]) -> dict[str, np.ndarray]:
        """``obs`` plus the derived keys among ``keys`` (those a controller reads)."""
        for key in keys:
            if key in self.derived and key not in obs:
                obs[key] = self.derived[key](obs)
        return obs

    def check_goal(self, goal: str) -> None:
        if goal not in self.goal_modes:
            raise ValueError(f"--goal {goal!r}: task {self.name} supports {', '.join(self.goal_modes)}")
