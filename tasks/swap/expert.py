"""Scripted swap expert: park one object out of the way, push the other onto its target, bring the first.

The scene is quasi-static (no velocity memory) and frictionless, so an object moves only while the disc pushes it,
along the contact normal: the sphere along the line of centres, the cube along the pushed face's normal, turning by
the contact's lever. Pushes are closed-loop: each step the target is set behind the object, on the line to its
target and a lead ahead, so the PD-tracked disc (critically damped: it never overshoots its target) stops the
object on its target. The cube is steered: the lever turns the pushed face until the push points at the target.
The last pixels are pushed slowly along the cube's own axes, which is what its coverage measures. Between pushes the
disc walks around both objects (``paths.shortest_path``). The parking spot follows from the starts (a policy must
be able to tell it from what it sees); speeds, gaps and waypoints are drawn from the seed, so demonstrations vary;
the caller's scene is only read.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpc.tasks.planar.paths import follow, rotate
from gpc.tasks.planar.scene import WORKSPACE
from gpc.tasks.swap import geometry
from gpc.tasks.swap.paths import R, away, clearance, in_workspace, shortest_path
from gpc.tasks.swap.sim import SwapSim

CUBE, SPHERE = 0, 1
_FACES = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])  # the cube's outward face normals (its frame)
PARK_LOW, PARK_HIGH = 95.0, 417.0  # where a parked object's centre may go
SIDE_BIAS = 30.0  # px of clearance a parking spot on the side away from the workspace's centre must gain to be chosen


@dataclass(frozen=True)
class ExpertConfig:
    """Tunable behaviour; ranges are drawn per push (speeds, gap) or per episode (order, parking spot)."""

    approach_speed: tuple[float, float] = (11.0, 16.0)  # px per step of the target in free space
    push_speed: tuple[float, float] = (6.0, 10.0)  # px per step while pushing far from a target
    fine_speed: tuple[float, float] = (1.5, 2.5)  # px per step for the last pixels
    fine_distance: float = 12.0  # below this distance (px) from its target an object is pushed slowly, along axes
    place_tolerance: float = 1.2  # px: an object is placed when its error (the cube's per axis) is below this
    park_tolerance: float = 15.0  # px: a parked object is close enough to its parking spot
    park_done: float = 85.0  # px: ... or far enough from the other object's straight path to its target
    staging_gap: tuple[float, float] = (8.0, 14.0)  # a push starts this far (px) behind first contact
    margin: float = 10.0  # clearance (px) of approach paths from the objects, beyond the disc's radius
    max_lead: float = 36.0  # the target never runs further than this ahead of the disc (px)
    steer_gain: float = 40.0  # lever (px) per rad of the cube's push direction off its target
    max_lever: float = 16.0  # largest lever (px) of a steering push, off the face's middle
    park_clearance: float = 110.0  # a parking spot keeps this far (px) from the other moves' straight paths
    cube_first: float = 0.0  # the chance that the cube is parked (else the sphere); 0: the plan follows from the scene

    def __post_init__(self) -> None:
        for name in ("approach_speed", "push_speed", "fine_speed", "staging_gap"):
            lo, hi = getattr(self, name)
            if not 0.0 < lo <= hi <= 25.0:
                raise ValueError(f"{name} {getattr(self, name)}: need 0 < low <= high <= 25")
        for name in ("fine_distance", "place_tolerance", "park_tolerance", "park_done", "margin", "max_lead", "park_clearance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} {getattr(self, name)}: must be positive")
        if self.max_lead < self.approach_speed[1] or self.staging_gap[0] < self.margin / 2:
            raise ValueError("need max_lead >= approach_speed's high end and staging_gap >= margin / 2")
        if not 0.0 <= self.max_lever < geometry.CUBE_SIDE / 2 or self.steer_gain < 0:
            raise ValueError(f"max_lever {self.max_lever}: must lie in [0, {geometry.CUBE_SIDE / 2}); steer_gain >= 0")
        if not 0.0 <= self.cube_first <= 1.0:
            raise ValueError(f"cube_first {self.cube_first}: must lie in [0, 1]")


def segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points ``p`` to segments ``a -> b`` (all ``(..., 2)``, broadcast)."""
    ab, ap = b - a, p - a
    t = np.clip((ap * ab).sum(axis=-1) / np.maximum((ab * ab).sum(axis=-1), 1e-9), 0.0, 1.0)
    return np.linalg.norm(ap - t[..., None] * ab, axis=-1)


_GRID = np.stack(np.meshgrid(np.arange(PARK_LOW, PARK_HIGH + 1e-9, 7.0), np.arange(PARK_LOW, PARK_HIGH + 1e-9, 7.0)),
                 axis=-1).reshape(-1, 2)  # the parking spots considered, a fixed grid: the plan is a function of the scene


def parking_plan(cube: np.ndarray, sphere: np.ndarray, clearance_px: float, cube_first: float,
                 rng: np.random.Generator | None = None) -> tuple[int, np.ndarray]:
    """Which object to park and where: the spot clearing the three moves' straight paths by ``clearance_px`` (or as
    near to it as the workspace allows) with the shortest detour.

    Parking the sphere at P: sphere B->P (cube at A), cube A->B (sphere at P), sphere P->A (cube at B); parking the
    cube mirrors it. The spot is a function of the two starts alone, which every observation carries as the goal:
    a policy that sees the scene can tell where the parked object is going (a spot drawn at random could not be
    learned from the demonstrations). The sphere is parked (its pushes need no steering) unless ``rng`` draws the
    cube with chance ``cube_first``.
    """
    a, b = np.asarray(cube, dtype=np.float64), np.asarray(sphere, dtype=np.float64)
    parked = CUBE if rng is not None and rng.random() < cube_first else SPHERE
    start, stay = (a, b) if parked == CUBE else (b, a)  # the parked object's start, the other's
    gap = np.minimum.reduce([segment_distance(stay, start, _GRID), segment_distance(_GRID, stay, start),
                             segment_distance(start, _GRID, stay)])
    travel = np.linalg.norm(_GRID - start, axis=1) + np.linalg.norm(_GRID - stay, axis=1)
    score = np.minimum(gap, clearance_px) - 0.05 * travel  # clearance first (1 px of it is worth 20 px of travel)
    # The two sides of the line between the objects mirror each other, so their best spots tie to within a pixel and
    # the argmax flipped sides for starts 3 px apart (a spot 50 px or more away in 17 of 100 random scenes, 1 now:
    # tests/test_swap.py): a choice no policy could learn from what it sees. The side facing the workspace's centre wins unless the other
    # clears the paths by SIDE_BIAS px more.
    line, centre = start - stay, np.full(2, WORKSPACE / 2) - stay
    facing = np.sign(line[0] * centre[1] - line[1] * centre[0])
    away = np.sign(line[0] * (_GRID[:, 1] - stay[1]) - line[1] * (_GRID[:, 0] - stay[0])) != facing
    return parked, _GRID[int(np.argmax(score - SIDE_BIAS * away))].copy()


@dataclass
class _Push:
    obj: int
    face: int  # the cube's pushed face (index into _FACES); unused for the sphere
    fine: bool
    speed: float
    path: np.ndarray  # world polyline to the staging point
    aim: np.ndarray  # where the push takes the object: the move's target, or a detour point on the way
    detour: bool = False
    walked: bool = False
    best: float = np.inf  # the smallest error seen during the push
    stalled: int = 0  # steps without progress


class SwapExpert:
    """Privileged scripted expert; ``act`` returns the disc's next target position (px)."""

    def __init__(self, config: ExpertConfig = ExpertConfig()) -> None:
        self.config = config
        self.reset(0)

    def reset(self, seed: int) -> None:
        self._rng = np.random.default_rng(seed)
        self._carrot: np.ndarray | None = None
        self._phases: list[tuple[int, np.ndarray, float]] | None = None  # (object, target, tolerance)
        self._push: _Push | None = None
        self._parking: tuple[int, np.ndarray, float] | None = None  # the plan's parking move (none in set_moves' plans)
        self._path_s = 0.0
        self._queue: list[np.ndarray] = []
        self._speed = self._draw(self.config.approach_speed)

    def _draw(self, bounds: tuple[float, float]) -> float:
        return float(self._rng.uniform(*bounds))

    def interrupt(self, target: np.ndarray) -> None:
        """Forget the current push (another controller took over); resume smoothly from ``target``."""
        self._carrot = np.asarray(target, dtype=np.float64).copy()
        self._push, self._queue = None, []

    def set_moves(self, moves: list[tuple[int, np.ndarray, float]]) -> None:
        """Replace the plan by ``moves``: (object: ``CUBE`` or ``SPHERE``, target, tolerance px), done in order.

        Once they are done the expert keeps both objects on the goal's targets, as after its own plan.
        """
        self._phases = [(obj, np.asarray(target, dtype=np.float64), float(tol)) for obj, target, tol in moves]
        self._push = None

    @property
    def idle(self) -> bool:
        """Whether every move is done (both objects on their targets): the disc rests."""
        return self._phases is not None and not self._phases and self._push is None

    @property
    def pushing(self) -> bool:
        """Whether the disc is past its approach, pushing."""
        return self._push is not None and self._push.walked

    # ------------------------------------------------------------------ the scene as the expert reads it
    @staticmethod
    def _read(sim: SwapSim) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = sim.state()
        return s[:2], np.array([s[2], s[3], sim.cube.angle]), s[5:7]

    @staticmethod
    def _error(obj: int, cube_pose: np.ndarray, sphere: np.ndarray, target: np.ndarray) -> float:
        """The object's error: the sphere's distance, the cube's largest offset along its own axes."""
        if obj == SPHERE:
            return float(np.linalg.norm(target - sphere))
        return float(np.abs(rotate(target - cube_pose[:2], -cube_pose[2])).max())

    def act(self, sim: SwapSim, goal: np.ndarray) -> np.ndarray:
        cfg = self.config
        agent, cube_pose, sphere = self._read(sim)
        goal = np.asarray(goal, dtype=np.float64)
        if self._carrot is None or np.linalg.norm(self._carrot - agent) > 3 * cfg.max_lead:
            self._carrot, self._push, self._queue = agent.copy(), None, []
        if self._phases is None:
            parked, spot = parking_plan(cube_pose[:2], sphere, cfg.park_clearance, cfg.cube_first, self._rng)
            targets = {CUBE: goal[0:2], SPHERE: goal[2:4]}
            self._parking = (parked, spot, cfg.park_tolerance)
            self._phases = [self._parking, (1 - parked, targets[1 - parked], cfg.place_tolerance),
                            (parked, targets[parked], cfg.place_tolerance)]
        if self._queue:
            target = self._queue.pop(0)
        else:
            target = self._control(agent, cube_pose, sphere, goal)
        lead = target - agent
        if np.linalg.norm(lead) > cfg.max_lead:
            target = agent + lead * cfg.max_lead / np.linalg.norm(lead)
        self._carrot = np.clip(target, 0.0, WORKSPACE)
        return self._carrot.copy()

    def _current(self, cube_pose: np.ndarray, sphere: np.ndarray, goal: np.ndarray) -> tuple[int, np.ndarray, float] | None:
        """The move under way: the first unfinished phase; after the three, whichever object lost its place."""
        assert self._phases is not None
        while self._phases:
            obj, target, tol = self._phases[0]
            if self._error(obj, cube_pose, sphere, target) > tol and not (
                    self._phases[0] is self._parking and self._out_of_the_way(obj, cube_pose, sphere, goal)):
                return obj, target, tol
            self._phases.pop(0)
            self._push = None
        tol = self.config.place_tolerance
        errors = [self._error(CUBE, cube_pose, sphere, goal[0:2]), self._error(SPHERE, cube_pose, sphere, goal[2:4])]
        worst = int(np.argmax(errors))
        if errors[worst] > 2.0 * tol:  # a placed object was nudged: place it again
            self._phases.append((worst, goal[0:2] if worst == CUBE else goal[2:4], tol))
            return self._phases[0]
        return None

    def _out_of_the_way(self, obj: int, cube_pose: np.ndarray, sphere: np.ndarray, goal: np.ndarray) -> bool:
        """Whether the parked ``obj`` is ``park_done`` px from the other object's straight path to its target: the
        parking ends there (or at the spot), a condition a policy reads from what it sees, overshoot included."""
        pos, other = (cube_pose[:2], sphere) if obj == CUBE else (sphere, cube_pose[:2])
        other_target = goal[2:4] if obj == CUBE else goal[0:2]
        return float(segment_distance(pos, other, other_target)) >= self.config.park_done

    # ------------------------------------------------------------------ control
    def _control(self, agent: np.ndarray, cube_pose: np.ndarray, sphere: np.ndarray, goal: np.ndarray) -> np.ndarray:
        assert self._carrot is not None
        move = self._current(cube_pose, sphere, goal)
        if move is None:  # done: rest where the disc is
            self._push = None
            return self._carrot
        obj, target, tol = move
        pos = cube_pose[:2] if obj == CUBE else sphere
        fine = bool(tol < self.config.park_tolerance and np.linalg.norm(target - pos) < self.config.fine_distance)
        push = self._push
        if push is not None and (push.obj != obj or push.fine != fine):
            push = None
        if push is None:
            push = self._plan(obj, fine, cube_pose, sphere, target) or self._detour(obj, pos, cube_pose, sphere, target)
            if push is None:
                return self._back_off(cube_pose, sphere)
            self._push, self._path_s = push, 0.0
        if not push.walked:
            self._path_s, point = follow(push.path, self._path_s, self._speed, agent, self.config.max_lead)
            if np.allclose(point, push.path[-1]):
                push.walked = True
            return point
        error = self._error(obj, cube_pose, sphere, push.aim)
        push.stalled = 0 if error < push.best - 0.2 else push.stalled + 1
        push.best = min(push.best, error)
        out = None if push.detour and error < 6.0 else self._push_target(push, agent, cube_pose, sphere, push.aim, tol)
        if out is None or push.stalled > 8:
            self._push = None
            return self._back_off(cube_pose, sphere)
        return out

    @staticmethod
    def _face(cube_pose: np.ndarray, target: np.ndarray) -> int:
        """The cube face whose inward normal points closest to ``target``."""
        e = target - cube_pose[:2]
        return int(np.argmax(-rotate(_FACES, cube_pose[2]) @ (e / max(float(np.linalg.norm(e)), 1e-9))))

    def _axis_face(self, cube_pose: np.ndarray, target: np.ndarray) -> int:
        """For fine pushes: the face to push so the larger of the cube-frame offsets shrinks."""
        e = rotate(target - cube_pose[:2], -cube_pose[2])
        k = int(np.argmax(np.abs(e)))
        normal = np.zeros(2)
        normal[k] = -np.sign(e[k]) if e[k] != 0 else 1.0
        return int(np.argmax(_FACES @ normal))

    def _ideal(self, push: _Push, cube_pose: np.ndarray, sphere: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Where the disc's centre touches the object for this push, the push direction and how far it has to go."""
        if push.obj == SPHERE:
            e = target - sphere
            d = float(np.linalg.norm(e))
            u = e / max(d, 1e-9)
            return sphere - u * (geometry.SPHERE_RADIUS + R), u, d
        normal = rotate(_FACES[push.face], cube_pose[2])
        p = -normal
        e = target - cube_pose[:2]
        lever = 0.0
        if not push.fine:
            u = e / max(float(np.linalg.norm(e)), 1e-9)
            phi = float(np.arctan2(p[0] * u[1] - p[1] * u[0], p @ u))  # u's angle from p, counter-clockwise
            lever = float(np.clip(self.config.steer_gain * phi, -self.config.max_lever, self.config.max_lever))
        tangent = rotate(normal, np.pi / 2)
        contact = cube_pose[:2] + normal * geometry.CUBE_SIDE / 2 + tangent * lever
        return contact + normal * R, p, float(e @ p)

    def _plan(self, obj: int, fine: bool, cube_pose: np.ndarray, sphere: np.ndarray, target: np.ndarray) -> _Push | None:
        """A push of ``obj`` towards ``target`` and the path to its staging point (None: no path from here)."""
        cfg = self.config
        assert self._carrot is not None
        face = 0 if obj == SPHERE else self._axis_face(cube_pose, target) if fine else self._face(cube_pose, target)
        push = _Push(obj, face, fine, self._draw(cfg.fine_speed if fine else cfg.push_speed), np.zeros((1, 2)), target)
        ideal, p, _ = self._ideal(push, cube_pose, sphere, target)
        staging = ideal - p * self._draw(cfg.staging_gap)
        if not in_workspace(staging) or clearance(staging, cube_pose, sphere) < R + cfg.margin / 2:
            return None
        path = shortest_path(self._carrot, staging, cube_pose, sphere, cfg.margin, turn=self._rng.uniform(0, np.pi / 6))
        if path is None:
            return None
        push.path = np.vstack([path[:1], path]) if len(path) == 1 else path
        self._speed = self._draw(cfg.approach_speed)
        return push

    def _detour(self, obj: int, pos: np.ndarray, cube_pose: np.ndarray, sphere: np.ndarray, target: np.ndarray) -> _Push | None:
        """Where no push towards the target can start (a wall or the other object behind the object), a push some way
        off to the side first."""
        e = target - pos
        u = e / max(float(np.linalg.norm(e)), 1e-9)
        for alpha in self._rng.permutation([0.5, -0.5, 1.0, -1.0, 1.4, -1.4]):
            push = self._plan(obj, False, cube_pose, sphere, pos + rotate(u, alpha) * min(float(np.linalg.norm(e)), 60.0))
            if push is not None:
                push.detour = True
                return push
        return None

    def _push_target(self, push: _Push, agent: np.ndarray, cube_pose: np.ndarray, sphere: np.ndarray, target: np.ndarray,
                     tol: float) -> np.ndarray | None:
        """This step's target of a closed-loop push; None when the disc is no longer behind the object."""
        ideal, p, remaining = self._ideal(push, cube_pose, sphere, target)
        rel = agent - ideal
        behind = -(rel @ p)  # how far the disc is behind its touching point
        side = abs(rel[0] * p[1] - rel[1] * p[0])
        if behind > 30.0 or behind < -8.0 or side > (12.0 if push.obj == CUBE else 14.0):
            return None
        if push.obj == CUBE:
            if push.fine and abs(remaining) < 0.5 * tol:
                return None  # this axis is done; the next push takes the other
            if not push.fine and abs(remaining) < 0.5 * self.config.fine_distance and push.best < self.config.fine_distance:
                return None
            if not push.fine and self._face(cube_pose, target) != push.face:
                return None
        return ideal + p * float(np.clip(remaining, 0.0, 2.0 * push.speed))

    def _back_off(self, cube_pose: np.ndarray, sphere: np.ndarray) -> np.ndarray:
        """Step away from the nearer object (and a little sideways) before planning again."""
        assert self._carrot is not None
        here = self._carrot
        step = rotate(away(here, cube_pose, sphere), self._rng.uniform(-0.5, 0.5)) * self._draw(self.config.approach_speed) * 0.6
        dest = np.clip(here + step, R + 10.0, WORKSPACE - R - 10.0)
        self._queue = [dest + step * 0.5]
        return dest

