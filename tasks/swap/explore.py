"""Exploration for world-model data: random pushes of either object, into free space or into the other object, and
expert rollouts with random motions spliced in.

An action-conditioned world model must learn how the objects answer the disc and each other, also after actions no
expert takes, so the data should be dominated by contact: ``pushes`` drives the expert's closed-loop push of a
random object towards a random spot, or straight into the other object (the contacts between the two), and cuts it
after a random length; ``perturbed`` lets the expert solve the task and splices in smooth random motions aimed into
an object (the expert then recovers); ``mixed`` draws one of the two per episode.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gpc.tasks.swap.env import MAX_EPISODE_STEPS, SwapEnv
from gpc.tasks.swap.expert import CUBE, PARK_HIGH, PARK_LOW, SPHERE, SwapExpert
from gpc.tasks.swap.paths import HI, LO
from gpc.tasks.swap.sim import SwapSim

MODES = ("perturbed", "pushes", "mixed")
MIDDLE_LOW, MIDDLE_HIGH = 150.0, 362.0  # an object pushed into another there stays clear of the walls
MOVE_STEPS = 80  # a random move that has not ended after this many steps (walking included) gives way to another


@dataclass(frozen=True)
class ExploreConfig:
    """What kind of exploration to run and how wild it is; ranges are drawn per push or segment."""

    mode: str = "mixed"  # perturbed | pushes | mixed (one of the two drawn per episode)
    perturbed_share: float = 0.5  # in mixed mode, the chance that an episode is a perturbed one
    into_other: float = 0.4  # the chance that a random push aims one object at the other
    near_first: float = 0.7  # the chance that a random push moves the object nearer the disc
    ahead: float = 0.7  # the chance that a push to a spot goes on roughly the way the disc faces the object
    push_steps: tuple[int, int] = (4, 24)  # steps a random push goes on after the approach
    perturb_prob: float = 0.08  # per expert step, the chance of splicing in a random segment
    perturb_steps: tuple[int, int] = (4, 16)  # length (steps) of a random segment
    wander_speed: tuple[float, float] = (4.0, 12.0)  # px per step of the random smooth motion
    wander_turn: float = 0.35  # std (rad) of the random turn of its heading per step
    max_lead: float = 36.0  # the target never runs further than this ahead of the disc (px)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode {self.mode!r}: use one of {', '.join(MODES)}")
        for name in ("perturbed_share", "into_other", "near_first", "ahead", "perturb_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} {getattr(self, name)}: must lie in [0, 1]")
        for name in ("push_steps", "perturb_steps"):
            lo, hi = getattr(self, name)
            if not 1 <= lo <= hi:
                raise ValueError(f"{name} {getattr(self, name)}: need 1 <= low <= high")
        lo, hi = self.wander_speed
        if not 0.0 < lo <= hi <= 25.0 or self.wander_turn < 0 or self.max_lead <= 0:
            raise ValueError("need 0 < wander_speed low <= high <= 25, wander_turn >= 0 and max_lead > 0")


class ExplorePolicy:
    """Contact-rich exploration controller with the expert's interface (``reset``, ``act``)."""

    def __init__(self, config: ExploreConfig = ExploreConfig()) -> None:
        self.config = config
        self._expert = SwapExpert()
        self.reset(0)

    def reset(self, seed: int) -> None:
        cfg = self.config
        self._rng = np.random.default_rng([seed, 0xE7])
        self.episode_mode = cfg.mode
        if cfg.mode == "mixed":
            self.episode_mode = "perturbed" if self._rng.random() < cfg.perturbed_share else "pushes"
        self._expert.reset(int(self._rng.integers(2**31)))
        self._carrot: np.ndarray | None = None
        self._push_left = 0  # steps left of the current random push once it pushes (pushes mode)
        self._move_left = 0  # steps left of the current random move, walking included
        self._wander_left, self._heading, self._speed, self._aim_obj = 0, 0.0, 1.0, CUBE

    def _draw(self, bounds: tuple[float, float]) -> float:
        return float(self._rng.uniform(*bounds))

    def act(self, sim: SwapSim, goal: np.ndarray) -> np.ndarray:
        agent = np.asarray(sim.agent.position, dtype=np.float64)
        if self._carrot is None:
            self._carrot = agent.copy()
        if self.episode_mode == "pushes":
            target = self._pushes(sim, goal)
        else:
            target = self._perturbed(sim, goal, agent)
        self._carrot = np.asarray(target, dtype=np.float64)
        return self._carrot.copy()

    # ------------------------------------------------------------------ random pushes
    def _new_push(self, sim: SwapSim, agent: np.ndarray) -> None:
        """A random move: an object strayed near a wall back to the middle; else the nearer object (more often) to a
        random spot, or into the other object when that one is far enough from the walls to be pushed on."""
        cfg, state = self.config, sim.state()
        centres = {CUBE: state[2:4], SPHERE: state[5:7]}
        stray = [o for o, c in centres.items() if np.any((c < PARK_LOW - 10.0) | (c > PARK_HIGH + 10.0))]
        if stray:
            obj, target = stray[0], self._rng.uniform(MIDDLE_LOW, MIDDLE_HIGH, 2)
        else:
            near = CUBE if np.linalg.norm(centres[CUBE] - agent) < np.linalg.norm(centres[SPHERE] - agent) else SPHERE
            obj = near if self._rng.random() < cfg.near_first else 1 - near
            other = centres[1 - obj]
            into = self._rng.random() < cfg.into_other and np.all((other >= MIDDLE_LOW) & (other <= MIDDLE_HIGH))
            if into:
                target = other
            elif self._rng.random() < cfg.ahead:  # onwards from where the disc is: a short walk, a long push
                away = centres[obj] - agent
                heading = float(np.arctan2(away[1], away[0])) + self._rng.normal(0.0, 0.5)
                target = centres[obj] + self._rng.uniform(40.0, 150.0) * np.array([np.cos(heading), np.sin(heading)])
                target = np.clip(target, PARK_LOW, PARK_HIGH)
            else:
                target = self._rng.uniform(PARK_LOW, PARK_HIGH, 2)
        self._expert.set_moves([(obj, target, 8.0)])
        self._push_left = int(self._rng.integers(cfg.push_steps[0], cfg.push_steps[1] + 1))
        self._move_left = MOVE_STEPS

    def _pushes(self, sim: SwapSim, goal: np.ndarray) -> np.ndarray:
        if self._push_left <= 0:
            self._new_push(sim, np.asarray(sim.agent.position, dtype=np.float64))
        target = self._expert.act(sim, goal)
        self._move_left -= 1
        if self._expert.pushing:
            self._push_left -= 1
        if self._move_left <= 0:  # no way to push that object there from here: another move
            self._push_left = 0
        return target

    # ------------------------------------------------------------------ perturbed expert
    def _perturbed(self, sim: SwapSim, goal: np.ndarray, agent: np.ndarray) -> np.ndarray:
        cfg = self.config
        if self._wander_left == 0 and self._rng.random() < cfg.perturb_prob:
            self._wander_left = int(self._rng.integers(cfg.perturb_steps[0], cfg.perturb_steps[1] + 1))
            self._speed = self._draw(cfg.wander_speed)
            self._aim_obj = CUBE if self._rng.random() < 0.5 else SPHERE
            to_aim = self._aim(sim) - agent
            self._heading = float(np.arctan2(to_aim[1], to_aim[0]))
        if self._wander_left == 0:
            if self._expert.idle:  # the task is done: a random push (the expert then puts the objects back)
                return self._pushes(sim, goal)
            return self._expert.act(sim, goal)
        self._wander_left -= 1
        target = self._wander(sim, agent)
        if self._wander_left == 0:
            self._expert.interrupt(target)
        return target

    def _aim(self, sim: SwapSim) -> np.ndarray:
        s = sim.state()
        return s[2:4] if self._aim_obj == CUBE else s[5:7]

    def _wander(self, sim: SwapSim, agent: np.ndarray) -> np.ndarray:
        """One step of a smooth random motion that keeps steering into the aimed object."""
        assert self._carrot is not None
        to_aim = self._aim(sim) - self._carrot
        turn = (np.arctan2(to_aim[1], to_aim[0]) - self._heading + np.pi) % (2 * np.pi) - np.pi
        self._heading += float(np.clip(turn, -0.4, 0.4) + self._rng.normal(0.0, self.config.wander_turn))
        target = self._carrot + self._speed * np.array([np.cos(self._heading), np.sin(self._heading)])
        lead = target - agent
        if np.linalg.norm(lead) > self.config.max_lead:
            target = agent + lead * self.config.max_lead / np.linalg.norm(lead)
        return np.clip(target, LO, HI)


def evaluate_explore(seeds: Sequence[int], config: ExploreConfig = ExploreConfig(), max_steps: int = MAX_EPISODE_STEPS) -> dict:
    """Shares of steps with contact over all episodes' steps (episodes run all ``max_steps``): ``contact_fraction``
    (any agent-object or object-object contact, the stores' ``n_contacts > 0``) and, apart, ``agent_cube``,
    ``agent_sphere`` and ``cube_sphere``; ``moving``: steps in which an object moved (contacts that push: resting
    ones, an object left touching the other, count as contacts too, as Push-T's count the disc resting on its T)."""
    policy = ExplorePolicy(config)
    hits, moved, seconds, modes = [], [], [], []
    for seed in seeds:
        t0 = time.perf_counter()
        env = SwapEnv()
        env.reset(seed=int(seed))
        policy.reset(int(seed))
        for _ in range(max_steps):
            before = env.sim.state()
            hits.append(env.step(policy.act(env.sim, env.goal))[4]["contacts"] > 0)
            moved.append(np.abs(env.sim.state()[2:] - before[2:]).max() > 0.05)
        seconds.append(time.perf_counter() - t0)
        modes.append(policy.episode_mode)
    h, m = np.array(hits), np.array(moved)
    return {"seeds": [int(s) for s in seeds], "modes": modes, "seconds": seconds, "steps": len(h),
            "contact_fraction": float(h.any(axis=1).mean()), "agent_cube": float(h[:, 0].mean()),
            "agent_sphere": float(h[:, 1].mean()), "cube_sphere": float(h[:, 2].mean()), "moving": float(m.mean())}
