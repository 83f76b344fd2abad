"""Physics and Task shared by the four KUKA tasks (the factories are in :mod:`envs.suite`).

The arm is moved Fetch-style: every control step the mocap body welded to the hand is placed at the
hand's position plus ``0.05 m * action[:3]`` (clipped to the task's workspace), with the hand's
orientation held pointing down. ``action[3]``, where the task has it, sets the finger opening
(+1 open, -1 closed); 3-D tasks hold the gripper closed.
"""

from __future__ import annotations

import collections
import math
import numbers

import mujoco as mj
import numpy as np
from dm_control import mujoco
from dm_control.suite import base
from dm_env import specs

from envs.geometry import Box, TaskGeometry
from envs.layout import NO_OBJECT, WITH_OBJECT, observation_size
from envs.reward import DEFAULT_THRESHOLD, reward

CONTROL_TIMESTEP = 0.05  # seconds per control step (20 Hz): 25 physics steps of 0.002 s
_ACTION_SCALE = 0.05  # metres of mocap motion per unit action per control step
_FINGER_OPEN = 0.0425  # metres: finger servo target (each finger's opening) for action[3] = +1
_FINGER_CLOSED = -0.02  # metres: finger servo target for action[3] = -1, past closed so that the grasp squeezes
_WORKSPACE_SLACK = 0.05  # metres: the grip site may leave the goal field by this much
_GRIP_ABOVE_TABLE = 0.015  # metres: lowest grip-site height above the table (finger ends 5 mm above it)
_ARM_JOINTS = tuple(f"joint{i}" for i in range(1, 8))
_SHOULDER_HEIGHT = 0.3405  # metres: joint 2 above the base
_LINK = 0.3995  # metres: joint 2 to joint 4, and joint 4 to joint 6
_WRIST_TO_GRIP = 0.1265 + 0.08  # metres: joint 6 to the flange, flange to the grip site

# Start pose per task and start point (arm joints, hand position, hand quaternion), solved once per process.
_START_POSE: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


class Physics(mujoco.Physics):
    """KUKA iiwa physics with named read-outs; ids and array views are cached for fast access."""

    def _reload_from_data(self, data):
        super()._reload_from_data(data)
        model = self.model.ptr
        self._grip = mj.mj_name2id(model, mj.mjtObj.mjOBJ_SITE, "grip")
        self._target = mj.mj_name2id(model, mj.mjtObj.mjOBJ_SITE, "target")
        self._hand = mj.mj_name2id(model, mj.mjtObj.mjOBJ_BODY, "hand")
        self._object = mj.mj_name2id(model, mj.mjtObj.mjOBJ_BODY, "object")  # -1 without an object
        fingers = [model.joint(f"{side}_finger") for side in ("left", "right")]
        self._finger_qpos = np.array([j.qposadr[0] for j in fingers])
        self._finger_qvel = np.array([j.dofadr[0] for j in fingers])
        self._arm_qpos = np.array([model.joint(name).qposadr[0] for name in _ARM_JOINTS])
        if self._object >= 0:
            joint = model.joint("object")
            self._object_qpos = slice(joint.qposadr[0], joint.qposadr[0] + 7)
            self._object_qvel = slice(joint.dofadr[0], joint.dofadr[0] + 6)
        self._velocity = np.zeros(6)  # scratch for mj_objectVelocity: (angular, linear)

    @property
    def has_object(self) -> bool:
        return self._object >= 0

    def grip_position(self) -> np.ndarray:
        """World position of the grip site between the finger pads (a view)."""
        return self.data.site_xpos[self._grip]

    def hand_position(self) -> np.ndarray:
        return self.data.xpos[self._hand]

    def arm_joints(self) -> np.ndarray:
        """The seven arm joint angles in radians (a copy)."""
        return self.data.qpos[self._arm_qpos].copy()

    def set_arm_joints(self, angles) -> None:
        self.data.qpos[self._arm_qpos] = angles

    def set_finger_positions(self, opening) -> None:
        """Each finger's opening in metres (one value for both, or one each)."""
        self.data.qpos[self._finger_qpos] = opening

    def hand_quaternion(self) -> np.ndarray:
        return self.data.xquat[self._hand]

    def finger_positions(self) -> np.ndarray:
        """Opening of each finger in metres, 0 (closed) to 0.0425 (open)."""
        return self.data.qpos[self._finger_qpos]

    def finger_velocities(self) -> np.ndarray:
        return self.data.qvel[self._finger_qvel]

    def grip_velocity(self) -> np.ndarray:
        """Linear velocity of the grip site in the world frame (m/s)."""
        mj.mj_objectVelocity(self.model.ptr, self.data.ptr, mj.mjtObj.mjOBJ_SITE, self._grip, self._velocity, 0)
        return self._velocity[3:].copy()

    def object_position(self) -> np.ndarray:
        return self.data.xpos[self._object]

    def object_quaternion(self) -> np.ndarray:
        return self.data.xquat[self._object]

    def object_velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """Linear and angular velocity of the object in the world frame (m/s, rad/s)."""
        mj.mj_objectVelocity(self.model.ptr, self.data.ptr, mj.mjtObj.mjOBJ_BODY, self._object, self._velocity, 0)
        return self._velocity[3:].copy(), self._velocity[:3].copy()

    def target_position(self) -> np.ndarray:
        return self.model.site_pos[self._target]

    def set_target(self, position) -> None:
        self.model.site_pos[self._target] = position

    def set_object_pose(self, position, quaternion=(1.0, 0.0, 0.0, 0.0)) -> None:
        self.data.qpos[self._object_qpos] = (*position, *quaternion)
        self.data.qvel[self._object_qvel] = 0.0

    def set_mocap(self, position, quaternion=None) -> None:
        self.data.mocap_pos[0] = position
        if quaternion is not None:
            self.data.mocap_quat[0] = quaternion


def _quat_to_euler(q: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (radians, x-y-z convention as in Fetch) of a unit quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in q)
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def _start_joints(base: np.ndarray, grip: np.ndarray) -> np.ndarray:
    """Elbow-up arm joints (radians) that put the grip site at ``grip`` with the hand pointing down.

    Joints 3 and 5 stay at zero, so the arm moves in the vertical plane turned by joint 1 and the
    problem is planar: the wrist (joint 6) lies ``_WRIST_TO_GRIP`` above the grip, joints 2 and 4
    bend the two equal links to reach it, joint 6 points the hand down and joint 7 undoes the
    yaw of joint 1.
    """
    q1 = math.atan2(grip[1] - base[1], grip[0] - base[0])
    forward = math.hypot(grip[0] - base[0], grip[1] - base[1])
    up = grip[2] + _WRIST_TO_GRIP - base[2] - _SHOULDER_HEIGHT
    reach = math.hypot(forward, up)
    if not _LINK <= reach <= 2 * _LINK:
        raise ValueError(f"grip start {tuple(grip)} is out of the arm's reach from its base at {tuple(base)}")
    phi = math.atan2(forward, up)  # wrist direction from the vertical
    beta = math.acos(reach / (2 * _LINK))  # angle between the upper arm and the shoulder-wrist line
    q2, q4 = phi - beta, -2 * beta
    q6 = math.pi - (q2 - q4)
    return np.array([q1, q2, 0.0, q4, 0.0, q6, q1])


def workspace(geom: TaskGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Low and high corners of the box the grip site is kept in: the goal field plus some slack."""
    low = np.array(geom.field.low) - _WORKSPACE_SLACK
    high = np.array(geom.field.high) + _WORKSPACE_SLACK
    if geom.table_height is not None:
        low[2] = geom.table_height + _GRIP_ABOVE_TABLE
    return low, high


def _uniform(random: np.random.RandomState, box: Box) -> np.ndarray:
    return np.asarray(box.center) + random.uniform(-1.0, 1.0, size=3) * np.asarray(box.half)


class KukaTask(base.Task):
    """A goal-conditioned KUKA task: reach a goal with the grip site, or bring the object to it.

    Observations (Fetch-style) are an ordered dict of ``observation`` (25 values with an object,
    10 without, laid out as :mod:`envs.layout` names them: grip position, object position, object
    position relative to the grip, finger openings, object Euler angles, object linear velocity
    relative to the grip, object angular velocity, grip velocity, finger velocities; velocities
    times the control timestep), ``achieved_goal`` (object
    or grip position), ``desired_goal`` and ``is_success``. The reward is :func:`envs.reward`.

    Args:
        geometry: the task's :class:`~envs.geometry.TaskGeometry`.
        threshold: success distance in metres (eq. 23), > 0.
        random: seed or ``np.random.RandomState``, as in dm_control.
    """

    def __init__(self, geometry: TaskGeometry, threshold: float = DEFAULT_THRESHOLD, random=None):
        if not (isinstance(threshold, numbers.Real) and math.isfinite(threshold) and threshold > 0):
            raise ValueError(f"threshold must be a positive number of metres, got {threshold!r}")
        super().__init__(random=random)
        self.geometry = geometry
        self.threshold = float(threshold)
        self.has_object = geometry.object_range is not None
        self.action_dim = geometry.action_dim
        self.layout = WITH_OBJECT if self.has_object else NO_OBJECT  # named slices of the observation
        self.obs_dim = observation_size(self.layout)
        self._low, self._high = workspace(geometry)

    # -- episode set-up -------------------------------------------------------------------------

    def _start_pose(self, physics: Physics):
        """Arm joints, hand position and quaternion that put the grip at ``geometry.gripper_start``."""
        name = (self.geometry.name, self.geometry.gripper_start)
        if name not in _START_POSE:
            base = physics.model.body("base").pos
            physics.set_arm_joints(_start_joints(base, np.asarray(self.geometry.gripper_start)))
            physics.forward()
            _START_POSE[name] = (physics.arm_joints(), physics.hand_position().copy(), physics.hand_quaternion().copy())
        return _START_POSE[name]

    def initialize_episode(self, physics: Physics) -> None:
        """Puts the arm in its start pose and the fingers at their start opening, draws the goal and (where
        there is one) the object's position."""
        qpos, hand_pos, hand_quat = self._start_pose(physics)
        physics.set_arm_joints(qpos)
        physics.set_finger_positions(self.geometry.finger_start)
        physics.data.qvel[:] = 0.0
        physics.set_mocap(hand_pos, hand_quat)  # dm_control resets the mocap to the model default
        if self.has_object:
            self.set_object_position(physics, _uniform(self.random, self.geometry.object_range))
        self.set_goal(physics, _uniform(self.random, self.geometry.target_range))
        super().initialize_episode(physics)

    def set_goal(self, physics: Physics, goal) -> None:
        """Uses ``goal`` (3 floats, metres) as this episode's desired goal."""
        physics.set_target(goal)

    def set_object_position(self, physics: Physics, position) -> None:
        """Places the object upright and at rest at ``position``'s x, y on the table (z is its resting height)."""
        z = self.geometry.object_range.center[2]
        physics.set_object_pose((position[0], position[1], z))

    # -- control --------------------------------------------------------------------------------

    def action_spec(self, physics: Physics) -> specs.BoundedArray:
        return specs.BoundedArray((self.action_dim,), np.float64, -1.0, 1.0, name="action")

    def before_step(self, action, physics: Physics) -> None:
        """Moves the mocap to the hand plus ``0.05 m * action[:3]`` (grip kept in the workspace); sets the fingers."""
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (self.action_dim,):
            raise ValueError(f"action must have shape ({self.action_dim},) in task "
                             f"{self.geometry.name!r}, got {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action must be finite, got {action}")
        action = np.clip(action, -1.0, 1.0)
        grip = physics.grip_position()
        target = np.clip(grip + _ACTION_SCALE * action[:3], self._low, self._high)
        physics.data.mocap_pos[0] = physics.hand_position() + (target - grip)
        closedness = 0.5 * (1.0 - action[3]) if self.action_dim == 4 else 1.0
        physics.data.ctrl[:] = _FINGER_OPEN + closedness * (_FINGER_CLOSED - _FINGER_OPEN)

    # -- observation and reward -----------------------------------------------------------------

    def observe_into(self, physics: Physics, observation: np.ndarray, achieved_goal: np.ndarray) -> None:
        """Writes the observation vector and the achieved goal into the given 1-D arrays."""
        grip = physics.grip_position()
        fingers = physics.finger_positions()
        grip_vel = physics.grip_velocity() * CONTROL_TIMESTEP
        finger_vel = physics.finger_velocities() * CONTROL_TIMESTEP
        part = self.layout
        observation[part["grip_position"]] = grip
        observation[part["finger_positions"]] = fingers
        observation[part["grip_velocity"]] = grip_vel
        observation[part["finger_velocities"]] = finger_vel
        if not self.has_object:
            achieved_goal[:] = grip
            return
        obj = physics.object_position()
        lin, ang = physics.object_velocity()
        observation[part["object_position"]] = obj
        observation[part["object_relative"]] = obj - grip
        observation[part["object_rotation"]] = _quat_to_euler(physics.object_quaternion())
        observation[part["object_velocity"]] = lin * CONTROL_TIMESTEP - grip_vel
        observation[part["object_angular_velocity"]] = ang * CONTROL_TIMESTEP
        achieved_goal[:] = obj

    def get_observation(self, physics: Physics) -> collections.OrderedDict:
        observation = np.empty(self.obs_dim)
        achieved_goal = np.empty(3)
        self.observe_into(physics, observation, achieved_goal)
        desired_goal = physics.target_position().copy()
        success = reward(achieved_goal, desired_goal, self.threshold) == 0.0
        return collections.OrderedDict(
            observation=observation, achieved_goal=achieved_goal, desired_goal=desired_goal,
            is_success=np.array([success]))

    def get_reward(self, physics: Physics) -> float:
        achieved = physics.object_position() if self.has_object else physics.grip_position()
        return float(reward(achieved, physics.target_position(), self.threshold))
