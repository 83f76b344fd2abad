"""Builders of the training pipeline's parts from explicit arguments (no Hydra config is passed in).

Each ``make_*`` function turns a few plain settings into one part — the goal metric, the trade-off
schedule, the replay buffer with its sampler, the HER transform, the goal generator. ``fast`` (the run's
``plain`` setting, negated) chooses the speed devices of the sampler and the buffer or their plain paths.
A builder takes every setting explicitly and checks none: a run's settings are checked once, before anything is built,
by :func:`gchgg.run.config.check` (whose choice lists name the ``kind`` each builder takes), and each
part checks its own arguments when it is built. A ``kind`` that is not one raises a ``KeyError``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.transforms import Compose

from gchgg.fast.storage import FieldStorage
from gchgg.graph import USER_CACHE_DIR, EuclideanMetric, GoalGraph
from gchgg.hgg import HGGGoalGenerator, TrajectoryPool
from gchgg.samplers import (
    AdaptiveTradeoff,
    CherSampler,
    EnergySampler,
    ExponentialTradeoff,
    FixedTradeoff,
    GraphCurriculumSampler,
)
from gchgg.transforms import DEFAULT_DROP_KEYS, EpisodeEnergy, GoalToNext, HindsightRelabel, ObservationNoise

PROXIMITY_KEYS = {  # curriculum.proximity -> (stored goal measured from, stored goal measured to)
    "goal_to_target": ("desired_goal", "task_goal"),  # eq. 15: hindsight goal to the target-task goal T*
    "achieved_to_goal": ("achieved_goal", "desired_goal"),  # the authors' code: closeness to success
}
DIVERSITY_KEYS = {"goal": "desired_goal", "achieved": "achieved_goal"}  # curriculum.diversity_of -> stored key
TRADEOFFS = {"adaptive": AdaptiveTradeoff, "exponential": ExponentialTradeoff, "fixed": FixedTradeoff}


def make_metric(kind: str, field=None, obstacles=(), **graph):
    """The goal metric: ``EuclideanMetric()``, or a ``GoalGraph`` over ``field`` with ``obstacles`` and the
    graph's settings ``n``, ``margin``, ``snap`` and ``cache_dir`` (lattice size, safety margin,
    goal-to-vertex rule, folder of the distance-table cache: ``None`` is the per-user default), each given.

    Args:
        kind: ``"euclidean"`` or ``"graph"``.
        field, obstacles: boxes ``(centre, half-sizes)`` in metres (only for ``"graph"``).
    """
    if kind == "graph":  # the graph checks its settings and the density criterion (eq. 12) before its long build
        cache_dir = USER_CACHE_DIR if graph["cache_dir"] is None else graph["cache_dir"]
        return GoalGraph(field, obstacles, graph["n"], graph["margin"], snap=graph["snap"], cache_dir=cache_dir)
    if graph:
        raise ValueError(f"a Euclidean metric takes no graph settings, got {', '.join(graph)}")
    return {"euclidean": EuclideanMetric}[kind]()


def make_tradeoff(kind: str, **settings):
    """The λ schedule ``kind`` with its settings: adaptive (eq. 20: ``eta``, ``sigma``, ``update_every``),
    exponential (eq. 4: ``lambda_0``, ``tau``) or fixed (``value``)."""
    return TRADEOFFS[kind](**settings)


def make_sampler(kind: str, metric, tradeoff, *, fast: bool, **settings):
    """The replay sampler ``kind`` with its own settings: uniform, EBP, graph curriculum (Alg. 1, candidates
    drawn with EBP) or CHER (``pool_size``). ``fast``: EBP and the curriculum on their speed devices, or on
    their plain paths (the same batches: :class:`~gchgg.samplers.GraphCurriculumSampler`'s "Speed"); uniform
    sampling (TorchRL's) and CHER have none.

    For the curriculum: ``num_candidates`` (K), ``proximity`` (a key of :data:`PROXIMITY_KEYS`) says which
    two stored goals F_prox measures, ``diversity_of`` (``"goal"`` or ``"achieved"``) whose nearest
    neighbours F_div scores, with ``diversity_metric`` (``None``: ``metric``), and ``scale`` (``"raw"``
    or ``"standardized"``) how the two terms are weighed (see :class:`~gchgg.samplers.GraphCurriculumSampler`).
    """
    if kind in ("uniform", "ebp") and settings:
        raise ValueError(f"algo.sampler={kind} takes no settings, got {', '.join(settings)}")
    if kind == "curriculum":
        goal_key, target_key = PROXIMITY_KEYS[settings["proximity"]]
        return GraphCurriculumSampler(
            metric,
            settings["num_candidates"],
            tradeoff,
            goal_key=goal_key,
            target_key=target_key,
            diversity_key=DIVERSITY_KEYS[settings["diversity_of"]],
            diversity_metric=settings["diversity_metric"],
            scale=settings["scale"],
            energy_key="energy",
            on_write="redraw",  # every batch from the buffer as it is when sampled (the recorded runs)
            diagnostics=True,  # metrics.csv's diversity_spread, proximity_spread and diversity_decided
            fast=fast,
        )
    if kind == "cher":
        return CherSampler(metric, pool_size=settings["pool_size"], tradeoff=tradeoff)
    return {"uniform": lambda: None, "ebp": lambda: EnergySampler("energy", fast=fast)}[kind]()  # None: RandomSampler


def make_replay_buffer(
    capacity_episodes: int,
    transitions_per_episode: int,
    sampler,
    *,
    batch_size: int,
    generator: torch.Generator,
    fast: bool,
) -> TensorDictReplayBuffer:
    """An episodic FIFO of relabelled transitions: ``capacity_episodes`` whole episodes.

    Every episode occupies ``transitions_per_episode`` = (k+1)·T consecutive rows, so the FIFO
    drops whole episodes. Sampled batches get ``("next", "desired_goal")`` back (:class:`GoalToNext`);
    their rows are read field by field (``fast``: :class:`gchgg.fast.storage.FieldStorage`) or by TorchRL's
    ``LazyTensorStorage`` itself (the same batches).
    """
    kwargs = {} if sampler is None else {"sampler": sampler}
    storage = (FieldStorage if fast else LazyTensorStorage)(capacity_episodes * transitions_per_episode)
    return TensorDictReplayBuffer(
        storage=storage,
        batch_size=batch_size,
        transform=GoalToNext(),
        generator=generator,
        **kwargs,
    )


def make_relabel(
    reward_fn: Callable, *, k: int, strategy: str, generator: torch.Generator, true_achieved_goal_key: str | None = None
) -> Compose:
    """EBP energy of each episode, then HER relabelling into (k+1)·T transitions per episode.

    With ``true_achieved_goal_key`` (observation noise on), the energy and the rewards are computed
    from the true achieved goal, the hindsight goals are the observed ones, and the true copy is not stored.
    """
    if true_achieved_goal_key is None:
        return Compose(EpisodeEnergy(), HindsightRelabel(reward_fn, k, strategy, generator=generator))
    drop = (*DEFAULT_DROP_KEYS, true_achieved_goal_key, ("next", true_achieved_goal_key))
    return Compose(
        EpisodeEnergy(achieved_goal_key=true_achieved_goal_key),
        HindsightRelabel(
            reward_fn, k, strategy, generator=generator, reward_achieved_goal_key=true_achieved_goal_key, drop_keys=drop
        ),
    )


def make_observation_noise(layout, has_object: bool, std: float, generator: torch.Generator) -> ObservationNoise:
    """Gaussian noise of ``std`` metres on the observed position the task's goal is about.

    With an object: the object position and the object-relative position (one draw, so that
    relative = object − grip still holds) and the achieved goal. Without one (reach): the grip
    position and the achieved goal. ``layout`` is the task's named observation layout
    (:func:`envs.observation_layout`).
    """
    slices = [layout["object_position"], layout["object_relative"]] if has_object else [layout["grip_position"]]
    return ObservationNoise(std, slices, generator=generator)


def make_goal_generator(
    kind: str,
    metric,
    *,
    max_dis: float,
    gamma: float,
    stop_threshold: float | None,
    success_threshold: float,
    pool_size: int,
    c: float,
    L: float,
) -> HGGGoalGenerator | None:
    """``None`` (episodes go to the target goals) or an HGG goal generator with its trajectory pool (its
    results say when its stop condition switches the run to target goals: ``stopped_now``)."""
    if kind == "none":
        return None
    return {"hgg": HGGGoalGenerator}[kind](
        metric,
        max_dis=max_dis,
        pool=TrajectoryPool(pool_size),
        c=c,
        L=L,
        gamma=gamma,
        stop_threshold=stop_threshold,
        success_threshold=success_threshold,
    )
