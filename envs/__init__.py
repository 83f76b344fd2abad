"""dm_control-style KUKA iiwa tasks (reach, push_new, pick_no_obstacle, pick_obstacle) and their batched TorchRL env."""

from envs.geometry import GEOMETRY, TASKS, Box, TaskGeometry, geometry

__all__ = ["GEOMETRY", "TASKS", "Box", "TaskGeometry", "geometry"]
