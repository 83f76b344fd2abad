"""Named slices of the KUKA tasks' flat observation vector, so that no caller slices it by hand.

``observation_layout(task)`` maps each part of the Fetch-style observation to its slice:

=========================  =====  ==========================================================
name                       with   what (metres, radians; velocities x the control timestep)
                           object
=========================  =====  ==========================================================
``grip_position``          0:3    the grip site (0:3 without an object too)
``object_position``        3:6    the object's centre
``object_relative``        6:9    object − grip (kept consistent with the two above)
``finger_positions``       9:11   the two finger openings (3:5 without an object)
``object_rotation``        11:14  the object's Euler angles (x-y-z)
``object_velocity``        14:17  object linear velocity relative to the grip
``object_angular_velocity`` 17:20 object angular velocity
``grip_velocity``          20:23  grip linear velocity (5:8 without an object)
``finger_velocities``      23:25  finger velocities (8:10 without an object)
=========================  =====  ==========================================================

>>> layout = observation_layout("push_new")
>>> layout["object_position"], observation_size(layout)
(slice(3, 6, None), 25)
>>> observation_layout("reach")["grip_velocity"]
slice(5, 8, None)
"""

from __future__ import annotations

from types import MappingProxyType

from envs.geometry import geometry

__all__ = ["NO_OBJECT", "WITH_OBJECT", "observation_layout", "observation_size"]


def _layout(parts: list[tuple[str, int]]) -> MappingProxyType:
    out, start = {}, 0
    for name, size in parts:
        out[name] = slice(start, start + size)
        start += size
    return MappingProxyType(out)


WITH_OBJECT = _layout([
    ("grip_position", 3), ("object_position", 3), ("object_relative", 3), ("finger_positions", 2),
    ("object_rotation", 3), ("object_velocity", 3), ("object_angular_velocity", 3), ("grip_velocity", 3),
    ("finger_velocities", 2),
])  # fmt: skip
NO_OBJECT = _layout([("grip_position", 3), ("finger_positions", 2), ("grip_velocity", 3), ("finger_velocities", 2)])


def observation_layout(task: str) -> MappingProxyType:
    """The read-only ``{name: slice}`` of task ``task``'s observation (see the module docstring)."""
    return WITH_OBJECT if geometry(task).object_range is not None else NO_OBJECT


def observation_size(layout) -> int:
    """Number of values in an observation of this layout."""
    return max(s.stop for s in layout.values())
