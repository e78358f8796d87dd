"""What a task's arrays mean: the schema every component reads instead of a task's constants.

A task (``gpc.tasks``) describes its data once as a ``TaskLayout``: where the agent and each
object sit in the ``state`` vector and which entries are angles, the action box, each object's
outline and goal (what a registration reward compares) and how rendered frames map to world
coordinates. Models build their configs from it (``gpc.models`` never imports a task),
and the harness hands it to every component, so a new task needs no line changed in ``models``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


def _distinct_in_range(name: str, dims: tuple[int, ...], dim: int) -> None:
    if len(set(dims)) != len(dims) or not all(0 <= d < dim for d in dims):
        raise ValueError(f"{name} {dims}: need distinct indices in [0, {dim})")


@dataclass(frozen=True)
class StateLayout:
    """Entries of one ``state`` vector that are not an object's: the agent, the angles, the action targets.

    ``action_targets`` are the entries an action is a position target for (the agent a controller drives
    there); ``agent_xy`` must lead the vector (policies read the agent as its first entries).
    """

    dim: int  # entries of one state vector
    agent_xy: tuple[int, ...] = ()  # the agent's position entries (leading), () for none
    angle_dims: tuple[int, ...] = ()  # entries that are angles (wrapped, fed as cos and sin)
    action_targets: tuple[int, ...] = ()  # entries an action is a target for (fed as action - state)
    # (entry, low, high): a range the policy's normaliser spans at least, whatever its demonstrations cover. For a
    # feature the demonstrations barely vary but a policy's own mistakes move far (the ink a drawing puts off its
    # outline: at most 0.017 in the expert's data, 0.1 after one bad chunk), a span fitted to the data alone would
    # put the policy's inputs tens of units outside [-1, 1].
    spans: tuple[tuple[int, float, float], ...] = ()
    # ``package.module:function`` taking ``(N, dim)`` torch states to the labellings a picture cannot tell apart
    # (``(N, E, dim)``; or one, ``(N, dim)``), where the state orders what a frame cannot show (a drawing's corners:
    # which one the seed drew first); the task's reward must score them alike. An image reader learns, of each
    # frame's, the one nearest what it reads. "": states are their labels.
    relabel: str = ""
    # (x, y) entry pairs of fixed points a top-down frame shows (a drawing's corners), in the labels' order: an image
    # reader finds them on a map
    points: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.dim < 1:
            raise ValueError(f"state dim {self.dim}: must be at least 1")
        if len(self.points) % 2:
            raise ValueError(f"points {self.points}: need (x, y) pairs of entries")
        for name in ("agent_xy", "angle_dims", "action_targets", "points"):
            _distinct_in_range(name, getattr(self, name), self.dim)
        _distinct_in_range("spans", tuple(int(i) for i, _, _ in self.spans), self.dim)
        for i, lo, hi in self.spans:
            if not -math.inf < lo < hi < math.inf:
                raise ValueError(f"span of state entry {i}: ({lo}, {hi}) must be finite with low below high")
        if self.relabel and ":" not in self.relabel:
            raise ValueError(f"relabel {self.relabel!r}: name a function as package.module:function")
        if self.agent_xy != tuple(range(len(self.agent_xy))):
            raise ValueError(f"agent_xy {self.agent_xy}: the agent's entries must lead the state vector")


@dataclass(frozen=True)
class ObjectLayout:
    """One object a task is about: where it sits in the state vector, its outline, its default goal.

    ``pose`` holds the entries its goal and its registration reward compare: ``(x, y)``, or
    ``(x, y, angle)`` where the goal fixes the orientation too. ``angle`` is its orientation's entry
    whether or not the goal counts it (object-frame features of a world model read it). ``goal``
    is None where the goal is drawn per episode (observed as the ``goal`` key).
    """

    name: str
    pose: tuple[int, ...]  # the state entries the goal compares: (x, y) or (x, y, angle)
    vertices: tuple[tuple[float, float], ...]  # object-frame points (the registration loss is their mean distance)
    goal: tuple[float, ...] | None = None  # the default goal, laid out as ``pose``; None: the goal varies per episode
    angle: int | None = None  # its orientation's state entry (None: it has none, or the state holds none)
    centroid: tuple[float, float] = (0.0, 0.0)  # the outline's area centroid in the object frame
    size: float = 1.0  # a length of the object's size (state units): scales object-frame features
    height: int | None = None  # its height's state entry in a 3-D scene (Block Stacking's z): judged, never a goal

    def __post_init__(self) -> None:
        if len(self.pose) not in (2, 3) or len(set(self.pose)) != len(self.pose):
            raise ValueError(f"object {self.name}: pose {self.pose} needs distinct (x, y) or (x, y, angle) entries")
        if len(self.pose) == 3 and self.pose[2] != self.angle:
            raise ValueError(f"object {self.name}: pose {self.pose} compares an angle, so its angle entry must be {self.pose[2]}")
        if not self.vertices or any(len(v) != 2 for v in self.vertices):
            raise ValueError(f"object {self.name}: vertices need (x, y) pairs")
        if self.goal is not None and len(self.goal) != len(self.pose):
            raise ValueError(f"object {self.name}: goal {self.goal} is not laid out as its pose {self.pose}")
        if self.size <= 0:
            raise ValueError(f"object {self.name}: size {self.size} must be > 0")
        if self.height is not None and self.height in self.pose + ((self.angle,) if self.angle is not None else ()):
            raise ValueError(f"object {self.name}: height entry {self.height} is one of its pose or angle entries")

    @property
    def has_angle(self) -> bool:
        """Whether its goal fixes its orientation."""
        return len(self.pose) == 3

    @property
    def frame(self) -> tuple[int, ...]:
        """``(x, y, angle)`` entries of the object's own frame, or () without an orientation."""
        return () if self.angle is None else (self.pose[0], self.pose[1], self.angle)


@dataclass(frozen=True)
class ActionBox:
    """Every action entry lies in ``[low, high]``."""

    dim: int
    low: float
    high: float

    def __post_init__(self) -> None:
        if self.dim < 1 or not self.low < self.high:
            raise ValueError(f"action box: dim {self.dim} must be >= 1 and low {self.low} below high {self.high}")


@dataclass(frozen=True)
class ObjectLook:
    """How the renderer draws one object: what a colour readout of frames looks for.

    The readout reads an object's angle from its drawn shape: with ``symmetry`` 1 the angle of its
    principal axis oriented by its skew; a shape that looks the same turned by ``2 pi / n``
    (``symmetry`` n, a square's 4) has its angle read, and compared, modulo that turn.
    """

    colours: tuple[tuple[int, int, int], ...]  # RGB it is drawn in (pick ones no other part of a frame uses)
    angle_offset: float = 0.0  # its angle = the angle its drawn shape reads as + this (radians)
    symmetry: int = 1  # n-fold rotational symmetry of its drawn shape
    tolerance: float = 40.0  # RGB distance (0..255) within which a pixel is the object's (tighter where look-alikes are drawn)

    def __post_init__(self) -> None:
        if not self.colours or self.symmetry < 1 or self.tolerance <= 0:
            raise ValueError(f"object look {self.colours}: need a colour, symmetry {self.symmetry} >= 1, tolerance "
                             f"{self.tolerance} > 0")


@dataclass(frozen=True)
class RegionLook:
    """A part of a frame with extent but no pose (Triangle Drawing's ink): a readout compares where it lies, pixel
    by pixel, since there is no centroid or angle that says what it is."""

    name: str
    colours: tuple[tuple[int, int, int], ...]  # RGB it is drawn in
    tolerance: float = 40.0  # RGB distance (0..255) within which a pixel belongs to it

    def __post_init__(self) -> None:
        if not self.name or not self.colours or self.tolerance <= 0:
            raise ValueError(f"region look {self.name!r}: need a name, a colour and a positive tolerance")


@dataclass(frozen=True)
class FrameLayout:
    """How a rendered frame maps to world coordinates, and how it draws the agent and the objects."""

    extent: tuple[float, float]  # world coordinate at the frame's first and last pixel edge (x along columns, y along rows)
    marker_size: float  # the agent's drawn radius (world units): the size of an action drawn into a frame
    objects: tuple[ObjectLook, ...] = ()  # how each object of the layout is drawn (in its order), for colour readouts
    agent_colours: tuple[tuple[int, int, int], ...] = ()  # RGB of the agent
    regions: tuple[RegionLook, ...] = ()  # parts with extent but no pose, for pixel readouts (a drawing's ink)

    @property
    def span(self) -> float:
        """World units one frame spans."""
        return self.extent[1] - self.extent[0]


@dataclass(frozen=True)
class TaskLayout:
    """One task's data schema: the name checkpoints record, and the parts above.

    ``objects``: every object the task is about, in the order the goal (and a ``goal`` observation) lays
    them out. Components that read a single object's pose (a world model's object-frame features) read
    the first. A task with no object to place (a drawing, whose state is the ink) has none: its goal is
    empty, and it names its own reward on states (``Task.state_reward``).
    """

    name: str
    state: StateLayout
    action: ActionBox
    objects: tuple[ObjectLayout, ...]
    frame: FrameLayout | None = None  # None: the task renders no frames
    unit: str = "px"  # how reports show a length: state units times ``unit_scale``, in ``unit`` (Block Stacking: m as mm)
    unit_scale: float = 1.0

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("a task layout needs a name")
        if not self.unit or not 0 < self.unit_scale < float("inf"):
            raise ValueError(f"task {self.name}: unit {self.unit!r} needs a name and a positive, finite scale ({self.unit_scale})")
        names = [o.name for o in self.objects]
        if len(set(names)) != len(names):
            raise ValueError(f"task {self.name}: object names {names} repeat")
        for obj in self.objects:
            entries = obj.pose + (() if obj.angle is None else (obj.angle,)) + (() if obj.height is None else (obj.height,))
            if not all(0 <= d < self.state.dim for d in entries):
                raise ValueError(f"object {obj.name}: entries {entries} lie outside the state's {self.state.dim}")
            if obj.angle is not None and obj.angle not in self.state.angle_dims:
                raise ValueError(f"object {obj.name}: angle entry {obj.angle} is not one of angle_dims {self.state.angle_dims}")
        if len(set(self.pose_dims)) != len(self.pose_dims):
            raise ValueError(f"task {self.name}: objects share pose entries {self.pose_dims}")
        if self.frame is not None and self.frame.objects and len(self.frame.objects) != len(self.objects):
            raise ValueError(f"task {self.name}: the frame draws {len(self.frame.objects)} objects, the layout has {len(self.objects)}")
        if self.state.action_targets and len(self.state.action_targets) != self.action.dim:
            raise ValueError(f"action_targets {self.state.action_targets}: need one per action entry ({self.action.dim})")

    @property
    def primary(self) -> ObjectLayout:
        """The object single-object components read (the first); check ``objects`` first where a task may have none."""
        if not self.objects:
            raise ValueError(f"task {self.name}: it has no object (its state holds no pose to read)")
        return self.objects[0]

    @property
    def pose_dims(self) -> tuple[int, ...]:
        """Every object's goal entries, in order: how a goal vector (and a ``goal`` observation) is laid out."""
        return tuple(d for obj in self.objects for d in obj.pose)

    @property
    def goal(self) -> tuple[float, ...] | None:
        """The default goal of every object, laid out as ``pose_dims``; None where a goal varies per episode; ()
        without objects (nothing to place, nothing to observe as a goal)."""
        if any(obj.goal is None for obj in self.objects):
            return None
        return tuple(g for obj in self.objects for g in obj.goal)  # type: ignore[union-attr]
