"""What a task's arrays mean: the schema every component reads instead of a task's constants.

A task (``gpc.tasks``) describes its data once as a ``TaskLayout``: where the agent and the
object sit in the ``state`` vector and which entries are angles, the action box, the object's
outline and goal pose (what a registration reward compares) and how rendered frames map to
world coordinates. Models build their configs from it (``gpc.models`` never imports a task),
and the harness hands it to every component, so a new task needs no line changed in ``models``.
"""

from __future__ import annotations

from dataclasses import dataclass


def _distinct_in_range(name: str, dims: tuple[int, ...], dim: int) -> None:
    if len(set(dims)) != len(dims) or not all(0 <= d < dim for d in dims):
        raise ValueError(f"{name} {dims}: need distinct indices in [0, {dim})")


@dataclass(frozen=True)
class StateLayout:
    """Entries of one ``state`` vector.

    ``object_pose`` is the pose a registration reward places the object at: ``(x, y)`` or
    ``(x, y, angle)``; ``action_targets`` are the entries an action is a position target for
    (the agent a controller drives there); ``agent_xy`` must lead the vector (policies read the
    agent as its first entries).
    """

    dim: int  # entries of one state vector
    object_pose: tuple[int, ...]  # (x, y) or (x, y, angle) of the object the task is about
    agent_xy: tuple[int, ...] = ()  # the agent's position entries (leading), () for none
    angle_dims: tuple[int, ...] = ()  # entries that are angles (wrapped, fed as cos and sin)
    action_targets: tuple[int, ...] = ()  # entries an action is a target for (fed as action - state)
    object_size: float = 1.0  # a length of the object's size (state units): scales object-frame features

    def __post_init__(self) -> None:
        if self.dim < 1:
            raise ValueError(f"state dim {self.dim}: must be at least 1")
        for name in ("object_pose", "agent_xy", "angle_dims", "action_targets"):
            _distinct_in_range(name, getattr(self, name), self.dim)
        if len(self.object_pose) not in (2, 3):
            raise ValueError(f"object_pose {self.object_pose}: need (x, y) or (x, y, angle) entries")
        if len(self.object_pose) == 3 and self.object_pose[2] not in self.angle_dims:
            raise ValueError(f"object_pose {self.object_pose}: its third entry must be one of angle_dims {self.angle_dims}")
        if self.agent_xy != tuple(range(len(self.agent_xy))):
            raise ValueError(f"agent_xy {self.agent_xy}: the agent's entries must lead the state vector")
        if self.object_size <= 0:
            raise ValueError(f"object_size {self.object_size}: must be > 0")

    @property
    def has_angle(self) -> bool:
        return len(self.object_pose) == 3


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
class PoseTarget:
    """The object's outline and the goal a registration reward compares it with."""

    vertices: tuple[tuple[float, float], ...]  # object-frame points (the registration loss is their mean distance)
    goal: tuple[float, ...]  # default goal pose, laid out as StateLayout.object_pose
    centroid: tuple[float, float] = (0.0, 0.0)  # the outline's area centroid in the object frame

    def __post_init__(self) -> None:
        if not self.vertices or any(len(v) != 2 for v in self.vertices):
            raise ValueError("pose target vertices: need (x, y) pairs")


@dataclass(frozen=True)
class FrameLayout:
    """How a rendered frame maps to world coordinates, and how it draws the agent and the object."""

    extent: tuple[float, float]  # world coordinate at the frame's first and last pixel edge (x along columns, y along rows)
    marker_size: float  # the agent's drawn radius (world units): the size of an action drawn into a frame
    object_colours: tuple[tuple[int, int, int], ...] = ()  # RGB of the object, for colour readouts
    agent_colours: tuple[tuple[int, int, int], ...] = ()  # RGB of the agent
    angle_offset: float = 0.0  # object angle = angle of its longest principal axis + this (radians)

    @property
    def span(self) -> float:
        """World units one frame spans."""
        return self.extent[1] - self.extent[0]


@dataclass(frozen=True)
class TaskLayout:
    """One task's data schema: the name checkpoints record, and the parts above."""

    name: str
    state: StateLayout
    action: ActionBox
    target: PoseTarget
    frame: FrameLayout | None = None  # None: the task renders no frames

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("a task layout needs a name")
        if len(self.target.goal) != len(self.state.object_pose):
            raise ValueError(f"goal {self.target.goal} is not laid out as object_pose {self.state.object_pose}")
        if self.state.action_targets and len(self.state.action_targets) != self.action.dim:
            raise ValueError(f"action_targets {self.state.action_targets}: need one per action entry ({self.action.dim})")
