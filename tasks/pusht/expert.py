"""Scripted Push-T expert: a quasi-static pushing planner with lookahead in a private simulator.

The scene has no ground friction and zero velocity damping, so the block moves only while the
disc pushes it, and the frictionless contact pushes along the edge normal: a push is predicted
well by a few steps of the simulator itself. Each cycle the expert samples contact points on
the T's edges, rolls the candidate pushes out in a *private* ``PushTSim`` (stepping the
caller's scene would change pymunk's cached contact impulses and with them its future), picks
a good one at random, walks the disc around the block to a staging point, then commits to a
push length chosen by exact rollouts from the true state. Near the goal it plans on coverage
with short, slow pushes, since the last few percent need about a pixel of precision.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gpc.tasks.planar.paths import all_pairs, follow, rotate
from gpc.tasks.planar.scene import AGENT_RADIUS
from gpc.tasks.pusht import geometry
from gpc.tasks.pusht.sim import PushTSim, SimSnapshot

R = AGENT_RADIUS
COG = np.array([0.0, 45.0])  # the block's centre of gravity in block coordinates
_BOX_C = np.array([[0.0, 15.0], [0.0, 75.0]])  # bar and stem centres (block frame)
_BOX_H = np.array([[60.0, 15.0], [15.0, 45.0]])  # their half extents
# Where the disc's centre can first touch each edge (a segment), and the edge's outward normal.
# In the pockets beside the stem the ranges stop where the disc would also touch the other box.
_EDGE_A = np.array([[-60, -R], [60 + R, 0], [-60 - R, 0], [16 + R, 30 + R], [-60, 30 + R],
                    [15 + R, 31 + R], [-15 - R, 31 + R], [-15, 120 + R]])
_EDGE_B = np.array([[60, -R], [60 + R, 30], [-60 - R, 30], [60, 30 + R], [-16 - R, 30 + R],
                    [15 + R, 120], [-15 - R, 120], [15, 120 + R]])
_EDGE_N = np.array([[0, -1], [1, 0], [-1, 0], [0, 1], [0, 1], [1, 0], [-1, 0], [0, 1]], dtype=float)
# The T's outline corners and the diagonal along which a waypoint keeps clear of each.
_CORNERS = np.array([[-60, 0], [60, 0], [60, 30], [15, 120], [-15, 120], [-60, 30], [15, 30], [-15, 30]], float)
_CORNER_DIRS = np.array([[-1, -1], [1, -1], [1, 1], [1, 1], [-1, 1], [-1, 1], [1, 1], [-1, 1]], float)
LO, HI = 25.0, 486.0  # box the disc's centre keeps to, clear of the walls at 5 and 506


@dataclass(frozen=True)
class ExpertConfig:
    """Tunable behaviour of the expert; speed ranges are sampled per push to vary demonstrations."""

    approach_speed: tuple[float, float] = (11.0, 16.0)  # px per step of the target in free space
    push_speed: tuple[float, float] = (7.0, 10.0)  # px per step while pushing far from the goal
    fine_speed: tuple[float, float] = (2.0, 3.0)  # px per step for the final, precise pushes
    max_lead: float = 36.0  # the target never runs further than this ahead of the disc (px)
    margin: float = 10.0  # clearance (px) of approach waypoints from the block, beyond the radius
    staging_gap: float = 12.0  # a push starts this far (px) before touching the edge
    max_depth: float = 70.0  # longest push (px) beyond first contact
    fine_depth: float = 14.0  # longest push (px) in fine mode
    max_tilt: float = 0.45  # largest angle (rad) between push direction and edge normal
    n_candidates: int = 28  # pushes rolled out per plan
    rho: float = 60.0  # px of position error that weigh as much as 1 rad of angle error
    fine_coverage: float = 0.75  # above this coverage, plan on coverage with short slow pushes
    choice_slack: float = 0.8  # pick at random among pushes scoring at least this x the best
    hold_steps: int = 2  # steps the target rests at a push's end before backing off

    def __post_init__(self) -> None:
        for name in ("approach_speed", "push_speed", "fine_speed"):
            lo, hi = getattr(self, name)
            if not 0.0 < lo <= hi <= 25.0:
                raise ValueError(f"{name} {getattr(self, name)}: need 0 < low <= high <= 25 px/step")
        for name in ("max_lead", "margin", "staging_gap", "max_depth", "fine_depth", "rho"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} {getattr(self, name)}: must be positive")
        if self.max_lead < self.approach_speed[1]:
            raise ValueError(f"max_lead {self.max_lead}: must be at least approach_speed's high end")
        if not 0.0 <= self.max_tilt < np.pi / 2:
            raise ValueError(f"max_tilt {self.max_tilt}: must lie in [0, pi/2)")
        if self.n_candidates < 1 or self.hold_steps < 0:
            raise ValueError("n_candidates must be >= 1 and hold_steps >= 0")
        if not 0.0 < self.fine_coverage < 1.0 or not 0.0 < self.choice_slack <= 1.0:
            raise ValueError("fine_coverage must lie in (0, 1) and choice_slack in (0, 1]")


# ---------------------------------------------------------------------- block-frame geometry
def clearance(points: np.ndarray) -> np.ndarray:
    """Distance (px) from block-frame points ``(..., 2)`` to the T (0 inside)."""
    d = np.abs(np.asarray(points, dtype=np.float64)[..., None, :] - _BOX_C) - _BOX_H
    return np.linalg.norm(np.maximum(d, 0.0), axis=-1).min(axis=-1)


def segments_clear(a: np.ndarray, b: np.ndarray, min_clearance: float) -> np.ndarray:
    """Whether block-frame segments ``a -> b`` (``(M, 2)`` each) keep ``min_clearance`` from the T."""
    t = np.linspace(0.0, 1.0, 96)[:, None]
    return clearance(a[:, None, :] + t * (b - a)[:, None, :]).min(axis=-1) >= min_clearance


def escape(point: np.ndarray, target: float) -> np.ndarray:
    """Climb the clearance field from a block-frame point until ``target`` px clear (pockets take a few steps)."""
    p, eps = np.asarray(point, dtype=np.float64), 1e-3
    for _ in range(12):
        gap = target - clearance(p)
        if gap <= 0.5:
            break
        grad = np.array([clearance(p + [eps, 0]) - clearance(p - [eps, 0]),
                         clearance(p + [0, eps]) - clearance(p - [0, eps])])
        norm = np.linalg.norm(grad)
        grad = grad / norm if norm > 1e-9 else (p - COG) / (np.linalg.norm(p - COG) + 1e-9)
        p = p + grad * gap
    return p


def to_block(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World points ``(..., 2)`` in the frame of a block at ``pose`` (inverse of ``geometry.to_world``)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = np.asarray(points, dtype=np.float64) - pose[:2]
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def sample_contacts(rng: np.random.Generator, n: int, overhang: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Random block-frame disc centres touching the T and the touched edges' outward normals.

    Edges are drawn in proportion to their length; ``overhang`` stretches each edge's range by
    that fraction past both ends, so corners get pushed too.
    """
    weights = np.linalg.norm(_EDGE_B - _EDGE_A, axis=1) + 10.0
    e = rng.choice(len(_EDGE_A), size=n, p=weights / weights.sum())
    u = rng.uniform(-overhang, 1.0 + overhang, (n, 1))
    return _EDGE_A[e] + u * (_EDGE_B[e] - _EDGE_A[e]), _EDGE_N[e]


def in_workspace(world: np.ndarray) -> np.ndarray:
    return np.all((world > LO) & (world < HI), axis=-1)


def approach_paths(start: np.ndarray, goals: np.ndarray, pose: np.ndarray, margin: float) -> list[np.ndarray | None]:
    """Shortest block-frame polylines from ``start`` to each of ``goals`` that go around the T.

    A visibility graph over waypoints off the T's corners (Floyd-Warshall once, then one hop to
    each goal); waypoints the walls rule out are dropped. ``None`` where no path exists.
    """
    first = [start]
    if clearance(start) < R + margin / 2:  # back away from the block before going around it
        start = escape(start, R + margin)
        first.append(start)
    nodes = np.vstack([start[None], _CORNERS + _CORNER_DIRS * (R + margin)])
    usable = in_workspace(geometry.to_world(nodes, pose))
    usable[0] = True
    k = len(nodes)
    ii, jj = np.triu_indices(k, 1)
    vis = segments_clear(nodes[ii], nodes[jj], R + margin / 2) & usable[ii] & usable[jj]
    dist, nxt = all_pairs(nodes, ii, jj, vis)
    g = len(goals)
    reach = segments_clear(np.repeat(nodes, g, axis=0), np.tile(goals, (k, 1)), R + margin / 2)
    total = dist[0][:, None] + np.linalg.norm(nodes[:, None] - goals[None], axis=-1)
    total = np.where(reach.reshape(k, g) & usable[:, None], total, np.inf)
    out: list[np.ndarray | None] = []
    for j in range(g):
        last = int(np.argmin(total[:, j]))
        hops, u = [], 0
        while u != last and np.isfinite(total[last, j]):
            u = int(nxt[u, last])
            hops.append(nodes[u])
        out.append(np.array(first + hops + [goals[j]]) if np.isfinite(total[last, j]) else None)
    return out


def pose_error(pose: np.ndarray, goal: np.ndarray, rho: float) -> float:
    """Centre-of-gravity distance and scaled angle error; linear in the angle so a half-turn still has a slope."""
    offset = rotate(COG, pose[2]) - rotate(COG, goal[2])
    dx, dy = pose[0] - goal[0] + offset[0], pose[1] - goal[1] + offset[1]
    da = (pose[2] - goal[2] + np.pi) % (2 * np.pi) - np.pi
    return float(np.sqrt(dx * dx + dy * dy + (rho * da) ** 2))


@dataclass
class _Push:
    staging: np.ndarray  # world point the push starts from
    direction: np.ndarray  # unit world direction of the push
    speed: float
    depth: float
    path: np.ndarray  # world polyline from the target to the staging point
    pose: np.ndarray  # block pose when planned; the block should not move until the push


class PushTExpert:
    """Privileged scripted expert; ``act`` returns the disc's next target position (px)."""

    def __init__(self, config: ExpertConfig = ExpertConfig()) -> None:
        self.config = config
        self._model = PushTSim()  # private scene for lookahead; the caller's scene is only read
        self.reset(0)

    def reset(self, seed: int) -> None:
        self._rng = np.random.default_rng(seed)
        self._carrot: np.ndarray | None = None  # the last commanded target
        self._path_s = 0.0
        self._push: _Push | None = None
        self._queue: list[np.ndarray] = []  # committed targets (push, hold, back-off)
        self._speed = self._draw(self.config.approach_speed)

    def interrupt(self, target: np.ndarray) -> None:
        """Forget the current plan (another controller took over); resume smoothly from ``target``."""
        self._carrot = np.asarray(target, dtype=np.float64).copy()
        self._push, self._queue = None, []

    def _draw(self, bounds: tuple[float, float]) -> float:
        return float(self._rng.uniform(*bounds))

    def act(self, sim: PushTSim, goal_pose: np.ndarray) -> np.ndarray:
        goal = np.asarray(goal_pose, dtype=np.float64)
        snap = sim.snapshot()
        agent, pose = np.array(snap.agent[:2]), np.array(snap.block[:3])
        if self._carrot is None or np.linalg.norm(self._carrot - agent) > 3 * self.config.max_lead:
            self.interrupt(agent)  # first call, or a scene we were not driving
        assert self._carrot is not None  # interrupt set it
        if not self._queue:
            if self._push is not None and np.abs(self._push.pose - pose).max() > 0.5:
                self._push = None  # the block moved during the approach: plan again
            if self._push is None:
                self._push = self._plan(snap, goal)
                self._path_s, self._speed = 0.0, self._draw(self.config.approach_speed)
            if self._push is None:
                self._queue = self._back_off(pose)
            else:
                self._path_s, self._carrot = follow(self._push.path, self._path_s, self._speed, agent,
                                                    self.config.max_lead)
                if np.allclose(self._carrot, self._push.path[-1]):
                    self._queue = self._commit(snap, goal, self._push)
                    self._push = None
        if self._queue:
            self._carrot = self._queue.pop(0)
        return np.clip(self._carrot, 0.0, geometry.WORKSPACE).astype(np.float64)

    def _back_off(self, pose: np.ndarray) -> list[np.ndarray]:
        """With no useful push from here, move further out (and a little sideways) to look again."""
        assert self._carrot is not None  # act sets it before planning
        here = to_block(self._carrot, pose)
        away = escape(here, float(clearance(here)) + 20.0)
        away = away + rotate(away - COG, np.pi / 2) * self._rng.uniform(-0.3, 0.3)
        dest = np.clip(geometry.to_world(away[None], pose)[0], LO, HI)
        n = max(1, int(np.ceil(np.linalg.norm(dest - self._carrot) / self._speed)))
        return [self._carrot + (dest - self._carrot) * (k + 1) / n for k in range(n)]

    # ------------------------------------------------------------------ lookahead
    def _objective(self, pose: np.ndarray, goal: np.ndarray, fine: bool) -> float:
        return 1.0 - geometry.coverage(pose, goal) if fine else pose_error(pose, goal, self.config.rho)

    def _rollout(self, snap: SimSnapshot, targets: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Block poses after each target from ``snap``, in the private scene with no cached contacts."""
        m = self._model
        m.restore_clean(snap)
        poses = []
        for t in targets:
            m.step(t)
            poses.append(m.block_pose())
        return poses

    def _push_targets(self, staging: np.ndarray, d: np.ndarray, speed: float, length: float,
                      settle: bool = True) -> list[np.ndarray]:
        n = int(np.ceil(length / speed))
        out = [staging + d * min((k + 1) * speed, length) for k in range(n)]
        if settle:  # rest, then back off so the block comes to a stop
            out += [out[-1]] * self.config.hold_steps + [out[-1] - d * speed * k for k in (1.5, 3.0)]
        return out

    # ------------------------------------------------------------------ planning
    def _candidates(self, pose: np.ndarray, goal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Staging points and directions (block frame) whose first-order effect reduces the error.

        A frictionless push along ``-n`` at lever ``l`` about the centre of gravity moves the
        block along ``-n`` and turns it at ``l / I`` rad per px (unit mass), both scaled by
        ``1 / (1 + l^2 / I)``.
        """
        cfg, rng = self.config, self._rng
        n = cfg.n_candidates * 3
        contact, normal = sample_contacts(rng, n)
        d = rotate(-normal, rng.uniform(-cfg.max_tilt, cfg.max_tilt, n))
        staging = contact - d * cfg.staging_gap
        r = contact - normal * R - COG
        lever = r[:, 1] * normal[:, 0] - r[:, 0] * normal[:, 1]
        inertia = self._model.block.moment
        v = rotate(-normal, pose[2]) / (1.0 + lever**2 / inertia)[:, None]
        w = lever / inertia / (1.0 + lever**2 / inertia)
        dc = geometry.to_world(COG[None], pose)[0] - geometry.to_world(COG[None], goal)[0]
        da = (pose[2] - goal[2] + np.pi) % (2 * np.pi) - np.pi
        ok = (dc @ v.T + cfg.rho**2 * da * w < 0) & (clearance(staging) >= R + cfg.margin / 2 + 1.0)
        ok &= in_workspace(geometry.to_world(staging, pose))
        idx = np.flatnonzero(ok)[: cfg.n_candidates]
        return staging[idx], d[idx]

    def _plan(self, snap: SimSnapshot, goal: np.ndarray) -> _Push | None:
        """Roll each candidate out from its staging point and pick a quick, effective one."""
        cfg = self.config
        assert self._carrot is not None  # act sets it before planning
        pose = np.array(snap.block[:3])
        fine = geometry.coverage(pose, goal) >= cfg.fine_coverage
        staging, dirs = self._candidates(pose, goal)
        paths = approach_paths(to_block(self._carrot, pose), staging, pose, cfg.margin)
        speed = self._draw(cfg.fine_speed if fine else cfg.push_speed)
        depth = cfg.fine_depth if fine else cfg.max_depth
        j0 = self._objective(pose, goal, fine)
        scored: list[tuple[float, int]] = []
        for i, path in enumerate(paths):
            if path is None:
                continue
            s_w, d_w = geometry.to_world(staging[i][None], pose)[0], rotate(dirs[i], pose[2])
            at_rest = SimSnapshot((s_w[0], s_w[1], 0.0, 0.0), snap.block)
            targets = self._push_targets(s_w, d_w, speed, cfg.staging_gap + depth, settle=False)
            vals = [self._objective(p, goal, fine) for p in self._rollout(at_rest, targets)]
            k = int(np.argmin(vals))
            if vals[k] >= j0:
                continue
            travel = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
            score = (j0 - vals[k]) / (travel / self._speed + k + 4.0)
            if fine and 1.0 - vals[k] > geometry.SUCCESS_COVERAGE + 0.005:
                score *= 4.0  # a push predicted to finish the task beats any partial progress
            scored.append((score, i))
        if not scored:
            return None
        top = max(sc for sc, _ in scored)
        pool = [i for sc, i in scored if sc >= cfg.choice_slack * top]
        i = pool[int(self._rng.integers(len(pool)))]
        s_w, path = geometry.to_world(staging[i][None], pose)[0], paths[i]
        assert path is not None  # only candidates with a path were scored
        return _Push(s_w, rotate(dirs[i], pose[2]), speed, depth, geometry.to_world(path, pose), pose)

    def _commit(self, snap: SimSnapshot, goal: np.ndarray, push: _Push) -> list[np.ndarray]:
        """Choose the push length by exact rollouts from the true state; [] if no length helps."""
        cfg = self.config
        pose = np.array(snap.block[:3])
        fine = geometry.coverage(pose, goal) >= cfg.fine_coverage
        j0 = self._objective(pose, goal, fine)
        longest = cfg.staging_gap + push.depth
        probe = [push.staging] + self._push_targets(push.staging, push.direction, push.speed, longest, settle=False)
        k = int(np.argmin([self._objective(p, goal, fine) for p in self._rollout(snap, probe)]))
        best, best_val = [], j0
        for frac in (-1.5, -1.0, -0.5, 0.0, 0.5, 1.0):
            length = (k + frac) * push.speed
            if 0 < length <= longest:
                targets = [push.staging] + self._push_targets(push.staging, push.direction, push.speed, length)
                val = self._objective(self._rollout(snap, targets)[-1], goal, fine)
                if val < best_val:
                    best, best_val = targets, val
        return best
