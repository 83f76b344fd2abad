"""dm_control-style KUKA iiwa tasks (reach, push_new, pick_no_obstacle, pick_obstacle) and their batched TorchRL env."""

from __future__ import annotations

from envs.geometry import GEOMETRY, TASKS, Box, TaskGeometry, geometry
from envs.layout import observation_layout
from envs.reward import reward


def task_seeds(seed: int | None, num_envs: int) -> list[int | None]:
    """The seed of each simulation's task random state for env seed ``seed``.

    Independent streams drawn from ``np.random.SeedSequence(seed)``; all ``None`` (fresh entropy)
    when ``seed`` is ``None``. ``envs.load(name, seed=task_seeds(s, n)[i])`` reproduces simulation
    ``i`` of ``envs.make(name, num_envs=n, seed=s)``.

    >>> task_seeds(0, 2)
    [2968811710, 3677149159]
    """
    import numpy as np

    if seed is None:
        return [None] * num_envs
    return [int(s) for s in np.random.SeedSequence(seed).generate_state(num_envs)]


def episode_seeds(seed: int, episodes: int, num_envs: int = 100) -> list[int]:
    """Task seeds of ``episodes`` episodes run in batches of ``num_envs`` simulations, batch ``b``
    seeded ``seed + b`` (as ``gchgg.analysis.evaluate`` runs them): a standalone controller that runs episode
    ``j`` with ``envs.load(name, seed=episode_seeds(seed, N)[j])`` sees the same goals and objects.

    >>> (episode_seeds(0, 3, num_envs=2)[:2] == task_seeds(0, 2),
    ...  episode_seeds(0, 3, num_envs=2)[2] == task_seeds(1, 1)[0])
    (True, True)
    """
    out = []
    for batch, start in enumerate(range(0, episodes, num_envs)):
        out.extend(task_seeds(seed + batch, min(num_envs, episodes - start)))
    return out


def load(name: str, seed=None, **options):
    """The dm_control ``control.Environment`` of task ``name``.

    Args:
        name: one of :data:`TASKS`; anything else is a ``ValueError`` listing them.
        seed: seed of the task's random state (goals and object positions).
        **options: ``threshold`` (success distance in metres, default 0.05), ``start``
            (``"original"`` or, for the pick tasks, ``"above"``: :func:`envs.geometry.with_start`) and
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


__all__ = [
    "GEOMETRY", "TASKS", "Box", "TaskGeometry", "episode_seeds", "geometry", "load", "make", "observation_layout",
    "reward", "task_seeds",
]  # fmt: skip
