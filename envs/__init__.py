"""dm_control-style KUKA iiwa tasks (reach, push_new, pick_no_obstacle, pick_obstacle) and their batched TorchRL env."""

from __future__ import annotations

from envs.geometry import GEOMETRY, TASKS, Box, TaskGeometry, geometry
from envs.layout import observation_layout
from envs.reward import reward


def load(name: str, seed=None, **options):
    """The dm_control ``control.Environment`` of task ``name``.

    Args:
        name: one of :data:`TASKS`; anything else is a ``ValueError`` listing them.
        seed: seed of the task's random state (goals and object positions).
        **options: ``threshold`` (success distance in metres, default 0.05) and
            ``environment_kwargs`` (passed to ``control.Environment``).

    >>> env = load("reach", seed=0)
    >>> time_step = env.reset()
    >>> sorted(time_step.observation)
    ['achieved_goal', 'desired_goal', 'is_success', 'observation']
    """
    from envs import suite

    return suite.load(name, seed=seed, **options)


def make(name: str, num_envs: int = 1, seed=None, **options):
    """A batched TorchRL env stepping ``num_envs`` simulations of task ``name`` per call.

    See :class:`envs.torchrl_env.KukaEnv` for the keys, the reset options and the errors.
    """
    from envs.torchrl_env import KukaEnv

    return KukaEnv(name, num_envs=num_envs, seed=seed, **options)


__all__ = ["GEOMETRY", "TASKS", "Box", "TaskGeometry", "geometry", "load", "make", "observation_layout", "reward"]
