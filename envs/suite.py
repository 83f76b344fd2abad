"""The four KUKA tasks as thin tagged dm_control factories over one private builder."""

from __future__ import annotations

from dm_control.rl import control
from dm_control.utils import containers

from envs import common, kuka
from envs.geometry import geometry, with_start

SUITE = containers.TaggedTasks()

_OPTIONS = ("threshold", "start", "environment_kwargs")


def _build(name: str, seed=None, threshold: float = kuka.DEFAULT_THRESHOLD, start: str = "original",
           environment_kwargs: dict | None = None) -> control.Environment:
    """The dm_control environment of task ``name``: its MJCF, a :class:`kuka.KukaTask`, T control steps.

    Args:
        name: one of :data:`envs.TASKS`.
        seed: seed of the task's random state (goals, object positions).
        threshold: success distance in metres.
        start: ``"original"`` (the authors' start state) or, for the pick tasks, ``"above"`` (their
            start before December 2026); see :func:`envs.geometry.with_start`.
        environment_kwargs: extra keyword arguments of ``control.Environment``.
    """
    geom = with_start(geometry(name), start)
    physics = kuka.Physics.from_xml_string(common.read_model(f"{name}.xml"), common.ASSETS)
    task = kuka.KukaTask(geom, threshold=threshold, random=seed)
    # Half a step short of T, so that float rounding can neither add nor drop a step.
    time_limit = (geom.episode_length - 0.5) * kuka.CONTROL_TIMESTEP
    return control.Environment(physics, task, time_limit=time_limit, control_timestep=kuka.CONTROL_TIMESTEP,
                               **(environment_kwargs or {}))


@SUITE.add("no_object")
def reach(seed=None, **options):
    """KukaReach: move the grip site to a goal in the air (3-D action, T = 50)."""
    return _build("reach", seed=seed, **options)


@SUITE.add("object", "obstacle")
def push_new(seed=None, **options):
    """KukaPushNew: push the cube around the wall's end to a goal on the table (3-D action, T = 100)."""
    return _build("push_new", seed=seed, **options)


@SUITE.add("object", "grasp")
def pick_no_obstacle(seed=None, **options):
    """KukaPickNoObstacle: pick the cube and place it at a goal in the air (4-D action, T = 100)."""
    return _build("pick_no_obstacle", seed=seed, **options)


@SUITE.add("object", "grasp", "obstacle")
def pick_obstacle(seed=None, **options):
    """KukaPickObstacle: pick the cube, lift it over the wall, place it behind (4-D action, T = 100)."""
    return _build("pick_obstacle", seed=seed, **options)


def check_options(options: dict) -> None:
    """Raises a ``TypeError`` naming any option the tasks do not take."""
    unknown = sorted(set(options) - set(_OPTIONS))
    if unknown:
        raise TypeError(f"unknown option(s) {unknown}; the tasks take {list(_OPTIONS)}")


def load(name: str, seed=None, **options):
    """The dm_control environment of task ``name`` (see :func:`envs.load`)."""
    geometry(name)  # a clear error listing the tasks for an unknown name
    check_options(options)
    return SUITE[name](seed=seed, **options)
