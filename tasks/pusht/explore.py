"""Exploration policies for world-model data: perturbed expert rollouts and random pushes.

An action-conditioned world model must learn how the block answers the disc, including after
actions no expert would take, so its data should be dominated by contact and reach block poses
off the expert's path; a random walk in empty space teaches it almost nothing. ``perturbed``
splices random smooth motions aimed into the block into expert rollouts (the expert then
recovers, which also shows recoveries); ``pushes`` walks around the block and pushes random
points of it in random directions; ``mixed`` draws one of the two per episode.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gpc.tasks.planar.paths import follow, rotate
from gpc.tasks.pusht import geometry
from gpc.tasks.pusht.expert import (
    COG,
    HI,
    LO,
    PushTExpert,
    R,
    approach_paths,
    clearance,
    escape,
    in_workspace,
    sample_contacts,
    to_block,
)
from gpc.tasks.pusht.sim import PushTSim

MODES = ("perturbed", "pushes", "mixed")
_BOX_LO, _BOX_HI = geometry.TEE_BOXES.min(axis=1), geometry.TEE_BOXES.max(axis=1)  # bar, stem


@dataclass(frozen=True)
class ExploreConfig:
    """What kind of exploration to run and how wild it is; ranges are sampled per segment or push."""

    mode: str = "mixed"  # perturbed | pushes | mixed (one of the two drawn per episode)
    perturbed_share: float = 0.5  # in mixed mode, the chance that an episode is a perturbed one
    perturb_prob: float = 0.1  # per expert step, the chance of splicing in a random segment
    perturb_steps: tuple[int, int] = (4, 16)  # length (steps) of a random segment
    wander_speed: tuple[float, float] = (4.0, 12.0)  # px per step of the random smooth motion
    wander_turn: float = 0.35  # std (rad) of the random turn of its heading per step
    push_steps: tuple[int, int] = (4, 18)  # steps a random push goes on past first contact
    push_speed: tuple[float, float] = (3.0, 12.0)  # px per step of a random push
    approach_speed: tuple[float, float] = (11.0, 16.0)  # px per step going around the block
    max_tilt: float = 0.9  # largest angle (rad) between a push and the edge's inward normal
    max_lead: float = 36.0  # the target never runs further than this ahead of the disc (px)
    margin: float = 10.0  # clearance (px) of approach waypoints from the block, beyond the radius

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode {self.mode!r}: use one of {', '.join(MODES)}")
        if not 0.0 <= self.perturbed_share <= 1.0 or not 0.0 <= self.perturb_prob <= 1.0:
            raise ValueError("perturbed_share and perturb_prob must lie in [0, 1]")
        for name in ("perturb_steps", "push_steps"):
            lo, hi = getattr(self, name)
            if not 1 <= lo <= hi:
                raise ValueError(f"{name} {getattr(self, name)}: need 1 <= low <= high")
        for name in ("wander_speed", "push_speed", "approach_speed"):
            lo, hi = getattr(self, name)
            if not 0.0 < lo <= hi <= 25.0:
                raise ValueError(f"{name} {getattr(self, name)}: need 0 < low <= high <= 25 px/step")
        if self.max_lead < self.approach_speed[1] or self.margin <= 0 or self.wander_turn < 0:
            raise ValueError("need max_lead >= approach_speed's high end, margin > 0, wander_turn >= 0")
        if not 0.0 <= self.max_tilt < np.pi / 2:
            raise ValueError(f"max_tilt {self.max_tilt}: must lie in [0, pi/2)")


class ExplorePolicy:
    """Contact-rich exploration controller with the expert's interface (``reset``, ``act``)."""

    def __init__(self, config: ExploreConfig = ExploreConfig()) -> None:
        self.config = config
        self._expert = PushTExpert()
        self.reset(0)

    def reset(self, seed: int) -> None:
        cfg = self.config
        self._rng = np.random.default_rng(seed)
        self.episode_mode = cfg.mode
        if cfg.mode == "mixed":
            self.episode_mode = "perturbed" if self._rng.random() < cfg.perturbed_share else "pushes"
        self._expert.reset(int(self._rng.integers(2**31)))
        self._carrot: np.ndarray | None = None
        self._wander_left, self._heading, self._aim, self._speed = 0, 0.0, np.zeros(2), 1.0
        self._path: np.ndarray | None = None
        self._path_s = 0.0
        self._queue: list[np.ndarray] = []
        self._push_targets: list[np.ndarray] = []  # the planned push, run once the path is done

    def act(self, sim: PushTSim, goal_pose: np.ndarray) -> np.ndarray:
        agent, pose = np.asarray(sim.agent.position, dtype=np.float64), sim.block_pose()
        if self._carrot is None:
            self._carrot = agent.copy()
        if self.episode_mode == "perturbed":
            target = self._perturbed(sim, goal_pose, agent, pose)
        else:
            target = self._pushes(agent, pose)
        self._carrot = np.clip(target, 0.0, geometry.WORKSPACE)
        return self._carrot.copy()

    def _draw(self, bounds: tuple[float, float]) -> float:
        return float(self._rng.uniform(*bounds))

    # ------------------------------------------------------------------ perturbed expert
    def _perturbed(self, sim: PushTSim, goal_pose: np.ndarray, agent: np.ndarray, pose: np.ndarray) -> np.ndarray:
        cfg = self.config
        assert self._carrot is not None  # set by act before any planning
        if self._wander_left == 0 and self._rng.random() < cfg.perturb_prob:
            self._wander_left = int(self._rng.integers(cfg.perturb_steps[0], cfg.perturb_steps[1] + 1))
            self._speed = self._draw(cfg.wander_speed)
            self._aim = self._aim_point(pose)
            to_aim = self._aim - self._carrot
            self._heading = float(np.arctan2(to_aim[1], to_aim[0]))
        if self._wander_left == 0:
            return self._expert.act(sim, goal_pose)
        self._wander_left -= 1
        target = self._wander(agent, pose)
        if self._wander_left == 0:
            self._expert.interrupt(target)
        return target

    def _aim_point(self, pose: np.ndarray) -> np.ndarray:
        """A random world point inside the T (bar or stem in proportion to area)."""
        box = int(self._rng.random() < 2700.0 / geometry.TEE_AREA)
        return geometry.to_world(self._rng.uniform(_BOX_LO[box], _BOX_HI[box])[None], pose)[0]

    def _wander(self, agent: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """One step of a smooth random motion that keeps steering into the block."""
        assert self._carrot is not None  # set by act before any planning
        to_aim = self._aim - self._carrot
        if np.linalg.norm(to_aim) < 2.0 * self._speed:
            self._aim = self._aim_point(pose)
            to_aim = self._aim - self._carrot
        turn = (np.arctan2(to_aim[1], to_aim[0]) - self._heading + np.pi) % (2 * np.pi) - np.pi
        self._heading += float(np.clip(turn, -0.4, 0.4) + self._rng.normal(0.0, self.config.wander_turn))
        target = self._carrot + self._speed * np.array([np.cos(self._heading), np.sin(self._heading)])
        lead = target - agent
        if np.linalg.norm(lead) > self.config.max_lead:
            target = agent + lead * self.config.max_lead / np.linalg.norm(lead)
        return np.clip(target, LO, HI)

    # ------------------------------------------------------------------ random pushes
    def _pushes(self, agent: np.ndarray, pose: np.ndarray) -> np.ndarray:
        if self._queue:
            return self._queue.pop(0)
        if self._path is None:
            self._plan_push(pose)
        if self._path is None:  # nowhere reachable from here: back away and look again
            assert self._carrot is not None  # set by act before any planning
            here = to_block(self._carrot, pose)
            away = geometry.to_world(escape(here, float(clearance(here)) + 20.0)[None], pose)[0]
            step = away - self._carrot
            return self._carrot + step * min(1.0, self.config.approach_speed[0] / (np.linalg.norm(step) + 1e-9))
        self._path_s, target = follow(self._path, self._path_s, self._speed, agent, self.config.max_lead)
        if np.allclose(target, self._path[-1]):
            self._queue, self._path = self._push_targets, None
        return target

    def _plan_push(self, pose: np.ndarray) -> None:
        """Pick a random contact (edges extended past their corners) and direction; prefer near ones."""
        cfg, rng = self.config, self._rng
        assert self._carrot is not None  # set by act before any planning
        n = 8
        contact, normal = sample_contacts(rng, n, overhang=0.15)
        d = rotate(-normal, rng.uniform(-cfg.max_tilt, cfg.max_tilt, n))
        gap = rng.uniform(8.0, 20.0, (n, 1))
        staging = contact - d * gap
        world = geometry.to_world(staging, pose)
        ok = (clearance(staging) >= R + cfg.margin / 2 + 1.0) & in_workspace(world)
        # Near a wall, do not push the block further into it.
        centre = geometry.to_world(COG[None], pose)[0]
        inward = (geometry.WORKSPACE / 2 - centre) / (np.linalg.norm(geometry.WORKSPACE / 2 - centre) + 1e-9)
        if np.abs(centre - geometry.WORKSPACE / 2).max() > 130.0:
            ok &= rotate(d, pose[2]) @ inward > -0.3
        idx = np.flatnonzero(ok)
        if len(idx) == 0:
            self._path = None
            return
        paths = approach_paths(to_block(self._carrot, pose), staging[idx], pose, cfg.margin)
        lengths = np.array([np.inf if p is None else np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in paths])
        if not np.isfinite(lengths).any():
            self._path = None
            return
        j = int(np.argmin(lengths * rng.uniform(1.0, 2.0, len(lengths))))
        i, path = idx[j], paths[j]
        assert path is not None  # finite length, so a path exists
        self._path, self._path_s = geometry.to_world(path, pose), 0.0
        self._speed = self._draw(cfg.approach_speed)
        s_w, d_w = world[i], rotate(d[i], pose[2])
        speed = self._draw(cfg.push_speed)
        steps = int(np.ceil(gap[i, 0] / speed)) + int(rng.integers(cfg.push_steps[0], cfg.push_steps[1] + 1))
        out = [s_w + d_w * speed * (k + 1) for k in range(steps)]
        self._push_targets = out + [out[-1] - d_w * speed * 1.5, out[-1] - d_w * speed * 3.0]


def _run(policy, seeds: Sequence[int], goal: str, max_steps: int, stop_on_success: bool) -> dict:
    from gpc.tasks.pusht.record import RecordConfig, record_episode

    record = RecordConfig(max_steps=max_steps, stop_on_success=stop_on_success, images=False, goal=goal)
    fractions, steps, seconds, cells = [], [], [], set()
    for seed in seeds:
        t0 = time.perf_counter()
        data, stats = record_episode(policy, int(seed), record)
        seconds.append(time.perf_counter() - t0)
        fractions.append(stats.contact_fraction)
        steps.append(stats.steps)
        cells |= geometry.pose_cells(data["state"])
    contacts = float(np.dot(fractions, steps))
    return {"contact_fractions": fractions, "steps": steps, "seconds": seconds,
            "contact_fraction": contacts / max(1, sum(steps)), "pose_coverage": len(cells) / (16 * 16 * 12)}


def evaluate_explore(seeds: Sequence[int], config: ExploreConfig = ExploreConfig(), goal: str = "fixed",
                     max_steps: int = 300, compare_expert: bool = True) -> dict:
    """Contact fraction (steps whose ``sim.step`` reported contact) and block-pose grid coverage.

    Exploration episodes run all ``max_steps``; the expert's, for comparison, stop at success
    as demonstrations do.
    """
    policy = ExplorePolicy(config)
    res = _run(policy, seeds, goal, max_steps, stop_on_success=False)
    res["seeds"] = [int(s) for s in seeds]
    res["modes"] = []
    for seed in seeds:
        policy.reset(int(seed))
        res["modes"].append(policy.episode_mode)
    if compare_expert:
        ref = _run(PushTExpert(), seeds, goal, max_steps, stop_on_success=True)
        res["expert_contact_fraction"], res["expert_pose_coverage"] = ref["contact_fraction"], ref["pose_coverage"]
    return res
