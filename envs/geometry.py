"""Task geometry of the four KUKA tasks as named boxes, readable without building a simulation.

Every region is a :class:`Box` given by its centre and half-sizes in metres (world frame). The
goal-space ``field`` and the un-inflated ``obstacles`` are what :class:`gchgg.graph.GoalGraph` is
built from; the sampling ranges are what the tasks draw targets and object positions from.
Numbers follow the authors' original KUKA environments (see ``REFERENCE.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple


class Box(NamedTuple):
    """An axis-aligned box: ``center`` and ``half`` (half-sizes), each ``(x, y, z)`` in metres."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]

    @property
    def low(self) -> tuple[float, float, float]:
        return tuple(c - h for c, h in zip(self.center, self.half, strict=True))

    @property
    def high(self) -> tuple[float, float, float]:
        return tuple(c + h for c, h in zip(self.center, self.half, strict=True))


@dataclass(frozen=True)
class TaskGeometry:
    """Where things are in one task.

    Attributes:
        name: task name, one of :data:`envs.TASKS`.
        field: the goal-space field the graph lattice covers.
        obstacles: obstacle boxes, un-inflated (the graph inflates them by its safety margin).
        target_range: box the target goal is drawn from (uniformly; a zero half-size is fixed).
        object_range: box the object's initial position is drawn from, ``None`` without an object.
        episode_length: control steps per episode (T).
        action_dim: 3 (gripper held closed) or 4 (last entry opens/closes the gripper).
        table_height: z of the table top in metres, ``None`` without a table.
        gripper_start: where the grip site (between the finger pads) starts each episode, metres
            (the tool pointing down). In ``reach`` the target range is this point +- 0.15 m.
        finger_start: each finger's opening at the start, metres (0: closed, 0.0425: open).
    """

    name: str
    field: Box
    obstacles: tuple[Box, ...]
    target_range: Box
    object_range: Box | None
    episode_length: int
    action_dim: int
    table_height: float | None
    gripper_start: tuple[float, float, float] = (0.75, 0.0, 1.2)
    finger_start: float = 0.0

    def below_table(self, position):
        """Boolean mask ``[...]`` of object positions ``[..., 3]`` (torch or numpy) whose centre is below
        the table top, i.e. objects that fell off the table. All False for a task without a table."""
        if self.table_height is None:
            return position[..., 2] < float("-inf")
        return position[..., 2] < self.table_height


_PICK_FIELD = Box((0.75, 0.0, 1.2), (0.25, 0.35, 0.2))

GEOMETRY: dict[str, TaskGeometry] = {
    "reach": TaskGeometry(
        name="reach",
        # No obstacle; the field is the target range (initial tip +- 0.15 m) with some slack.
        field=Box((0.75, 0.0, 1.2), (0.2, 0.2, 0.2)),
        obstacles=(),
        target_range=Box((0.75, 0.0, 1.2), (0.15, 0.15, 0.15)),
        object_range=None,
        episode_length=50,
        action_dim=3,
        table_height=None,
        gripper_start=(0.75, 0.0, 1.2),
    ),
    "push_new": TaskGeometry(
        name="push_new",
        field=Box((0.75, 0.0, 0.9), (0.25, 0.35, 0.05)),
        obstacles=(Box((0.685, 0.0, 0.925), (0.185, 0.04, 0.075)),),
        # Goals and the object's start are at the resting height of the 4 cm cube's centre.
        target_range=Box((0.65, -0.2, 0.87), (0.12, 0.12, 0.0)),
        object_range=Box((0.71, 0.25, 0.87), (0.0, 0.0, 0.0)),
        episode_length=100,
        action_dim=3,
        table_height=0.85,
        # The authors' start: their joint angles (0.326, 0.942, 0, -1.74, 0, 0.461, 0.336) put the
        # needle tip here; this arm's joints are solved for the same tip (REFERENCE.md).
        gripper_start=(0.674, 0.160, 0.974),
    ),
    "pick_no_obstacle": TaskGeometry(
        name="pick_no_obstacle",
        field=_PICK_FIELD,
        obstacles=(),
        target_range=Box((0.75, -0.2, 1.3), (0.2, 0.1, 0.0)),
        object_range=Box((0.75, 0.2, 1.015), (0.06, 0.06, 0.0)),  # the 3 cm cube's resting centre
        episode_length=100,
        action_dim=4,
        table_height=1.0,
        # The authors' start (REFERENCE.md): their joint angles (0.356, 0.942, 0, -1.53, 0, 0.628, 0.336)
        # put the tip at the cube's start centre, the fingers half open around it; this arm's joints
        # are solved for the same tip (the same angles on this arm, whose wrist-to-grip is 3.65 cm
        # shorter, would put the grip 3.7 cm higher, the fingers above the cube).
        gripper_start=(0.745, 0.203, 1.019),
        finger_start=0.026,
    ),
    "pick_obstacle": TaskGeometry(
        name="pick_obstacle",
        field=_PICK_FIELD,
        obstacles=(Box((0.75, 0.0, 1.075), (0.25, 0.04, 0.075)),),
        # Goals on the table: the resting height of the 3 cm cube's centre.
        target_range=Box((0.75, -0.2, 1.015), (0.2, 0.1, 0.0)),
        object_range=Box((0.75, 0.2, 1.015), (0.06, 0.06, 0.0)),
        episode_length=100,
        action_dim=4,
        table_height=1.0,
        # The authors' start: angles (0.356, 0.921, 0, -1.49, 0, 0.733, 0.336), the tip 2.6 cm above
        # the cube's start centre, the fingers closed.
        gripper_start=(0.748, 0.204, 1.041),
        finger_start=0.0,
    ),
}

# The authors' start joint angles q1..q7 (radians; REFERENCE.md, "Start states of the original tasks").
# The tasks start where these put the authors' tool tip (``gripper_start``); ``python docs/learnability.py
# --starts`` prints where they would put this arm's grip.
AUTHORS_JOINTS = {
    "push_new": (0.326, 0.942, 0.0, -1.74, 0.0, 0.461, 0.336),
    "pick_no_obstacle": (0.356, 0.942, 0.0, -1.53, 0.0, 0.628, 0.336),
    "pick_obstacle": (0.356, 0.921, 0.0, -1.49, 0.0, 0.733, 0.336),
}

# The pick tasks' start before December 2026: the grip 18.5 cm above and ~10 cm beside the cube's
# start, fingers closed. Kept for the learnability comparison (``start="above"``).
ABOVE_START = {"pick_no_obstacle": (0.75, 0.1, 1.2), "pick_obstacle": (0.75, 0.1, 1.2)}
STARTS = ("original", "above")


def with_start(geom: TaskGeometry, start: str = "original") -> TaskGeometry:
    """``geom`` with start ``"original"`` (the authors' start state, the default) or ``"above"`` (the pick
    tasks' start before December 2026: grip at ``ABOVE_START``, fingers closed)."""
    if start == "original":
        return geom
    if start == "above" and geom.name in ABOVE_START:
        return replace(geom, gripper_start=ABOVE_START[geom.name], finger_start=0.0)
    raise ValueError(
        f"start={start!r} is not a start of task {geom.name!r}: every task has 'original'"
        + (", and 'above'" if geom.name in ABOVE_START else "; 'above' exists for the pick tasks")
    )

TASKS: tuple[str, ...] = tuple(GEOMETRY)


def geometry(name: str) -> TaskGeometry:
    """The geometry of task ``name``; a ``ValueError`` lists the valid names otherwise."""
    try:
        return GEOMETRY[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; valid tasks: {', '.join(TASKS)}") from None
