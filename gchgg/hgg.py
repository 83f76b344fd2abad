"""Intermediate goal generation of HGG and G-HGG (paper Sec. III-B, eqs. 5–7, Alg. 2 line 6).

Each iteration starts from K target tasks (initial achieved goal ĝ0ʲ, target goal ĝʲ) drawn from the
target distribution T*. :class:`HGGGoalGenerator` matches them to K *distinct* trajectories of a
:class:`TrajectoryPool` of recently achieved-goal trajectories, minimising the total cost of eq. 6

    w(j, i) = c·‖ag_i0 − ĝ0ʲ‖ + min_t [ d(ag_it, ĝʲ) − V_it · max_dis · (1 − γ) / L ]

by an exact weighted bipartite matching (:func:`scipy.optimize.linear_sum_assignment`), and takes
from each matched trajectory the point that attains the minimum (eq. 7) as the intermediate goal.
``V_it = V(s_i0, ag_it)`` is the agent's value of reaching the pool point from the trajectory's
initial observation, clipped to ``[−1/(1 − γ), 0]``, so ``V_it·(1 − γ)`` lies in ``[−1, 0]`` and the
value bonus is at most ``max_dis / L`` metres (this scaling is the original code's reading of the
paper's ``V / L``). ``d`` is any metric object with ``distance(a, b)``: :class:`gchgg.graph.GoalGraph`
gives G-HGG, :class:`gchgg.graph.EuclideanMetric` gives HGG. The initial-state term is Euclidean in
both, as in the paper and the original code.

The generator also reports D_G(T, T*) (eq. 21), the mean metric distance between each intermediate
goal and its target, which the adaptive trade-off (eq. 20) reads, and it keeps the stop condition
that switches the run to plain HER once the intermediate goals have reached the targets.

Decisions where the paper is silent (the README's HGG section repeats them):

* **Admission.** A trajectory enters the pool if its final achieved goal is more than
  ``min_displacement`` (0.01 m) from its first (Euclidean), as in the original code; the pool is a
  FIFO of the last ``capacity`` (1,000) admitted trajectories.
* **Infinite distances** (a goal outside the graph's field or on a removed vertex) become the finite
  ``infinite_distance`` (9999, as the original) before anything else, so costs, the matching and
  D_G never see ``inf`` or ``NaN``.
* **Pool smaller than K** (``small_pool``). ``"repeat"`` (default): every pool trajectory may serve
  up to ``ceil(K / P)`` targets, and the matching stays exact under that capacity; the original code
  instead pads the pool to its full length with copies. ``"targets"``: the best ``P`` targets get
  distinct trajectories, the others keep their own target goal. With ``P >= K`` the K trajectories
  are always distinct (the paper; the original pads a part-filled pool and may reuse trajectories).
* **Stop condition.** After a generation that took every goal from the pool, the fraction of
  intermediate goals within ``success_threshold`` (Euclidean, the success criterion of eq. 23) of
  *some* target goal of that call is compared with ``stop_threshold``; above it (strictly), every
  later call returns the targets themselves (plain HER). Generations from an empty pool (the first
  iteration) never trigger it, which is the original's "from the second iteration" rule made safe
  for a pool that is still empty then. The original compares with a fresh sample of target goals
  rather than the call's own targets; both are samples of T*.
* **D_G** is 0 when the targets themselves are returned (empty pool, or stopped).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from gchgg.common.validation import check_choice, check_number
from gchgg.ddpg.loss import DDPGConfig, check_gamma
from gchgg.graph import Metric

__all__ = ["GoalGeneration", "HGGGoalGenerator", "TrajectoryPool", "estimate_max_distance"]

ValueFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

DEFAULT_CAPACITY = 1000  # trajectories in the pool (original default)
DEFAULT_MIN_DISPLACEMENT = 0.01  # metres: the goal must move this far (first to last point) to be admitted
INFINITE_DISTANCE = 9999.0  # metres: stands in for an infinite graph distance (original code)
_SMALL_POOL_CHOICES = ("repeat", "targets")


class TrajectoryPool:
    """FIFO pool of recent achieved-goal trajectories with the observation each started from.

    Storage is allocated on the first :meth:`add` (the trajectory length ``T + 1`` and the observation
    size are fixed from then on) on ``device`` (default: that of the first data).

    Args:
        capacity: most trajectories held; the oldest are overwritten first.
        min_displacement: metres; a trajectory is admitted only if its last achieved goal is more
            than this far (Euclidean) from its first.

    Keyword Args:
        device: where the pool's tensors live; by default the device of the first added data.

    Example:
        >>> import torch
        >>> pool = TrajectoryPool(capacity=2)
        >>> still = torch.zeros(1, 4, 3)  # the goal never moved: not admitted
        >>> moved = torch.linspace(0, 0.1, 4)[None, :, None].expand(3, 4, 3)
        >>> pool.add(torch.cat([still, moved]), torch.zeros(4, 5)).tolist()
        [False, True, True, True]
        >>> len(pool), pool.achieved_goals.shape  # capacity 2: the oldest moved one was dropped
        (2, torch.Size([2, 4, 3]))
    """

    def __init__(
        self,
        capacity: int = DEFAULT_CAPACITY,
        min_displacement: float = DEFAULT_MIN_DISPLACEMENT,
        *,
        device: torch.device | str | None = None,
    ) -> None:
        check_number("capacity (trajectories held)", capacity, integer=True, low=1)
        check_number("min_displacement (metres)", min_displacement, low=0)
        self.capacity = int(capacity)
        self.min_displacement = float(min_displacement)
        self.device = None if device is None else torch.device(device)
        self._goals: torch.Tensor | None = None  # [capacity, T + 1, 3]
        self._observations: torch.Tensor | None = None  # [capacity, obs_dim]
        self._size = 0
        self._cursor = 0  # next slot to write; the oldest trajectory once the pool is full

    def __len__(self) -> int:
        return self._size

    @property
    def storage_device(self) -> torch.device | None:
        """Where the trajectories are kept: ``device`` if given, else that of the first ones added (``None`` before)."""
        return self._goals.device if self._goals is not None else self.device

    @property
    def achieved_goals(self) -> torch.Tensor:
        """float32 ``[len(self), T + 1, 3]``: the stored trajectories (storage order, not age order)."""
        if self._goals is None:
            raise RuntimeError("the trajectory pool is empty and has no trajectory length yet; add trajectories first")
        return self._goals[: self._size]

    @property
    def initial_observations(self) -> torch.Tensor:
        """float32 ``[len(self), obs_dim]``: the observation each stored trajectory started from."""
        if self._observations is None:
            raise RuntimeError("the trajectory pool is empty and has no observation size yet; add trajectories first")
        return self._observations[: self._size]

    def add(self, achieved_goals: torch.Tensor, initial_observations: torch.Tensor) -> torch.Tensor:
        """Admit the trajectories whose goal moved more than ``min_displacement``.

        Args:
            achieved_goals: ``[N, T + 1, 3]`` achieved goals of N episodes, initial one included.
            initial_observations: ``[N, obs_dim]`` observation at the start of each episode (without
                the goal), the ``s0`` that the value function is evaluated from.

        Returns:
            bool ``[N]``: which trajectories were admitted (if more than ``capacity`` are, only the
            last ``capacity`` of them remain).

        Raises:
            ValueError: wrong shapes, a length or observation size other than the pool's, or
                non-finite values.
        """
        goals = torch.as_tensor(achieved_goals)
        observations = torch.as_tensor(initial_observations)
        if goals.ndim != 3 or goals.shape[-1] != 3 or goals.shape[1] < 1:
            raise ValueError(f"achieved_goals must have shape [N, T + 1, 3], got {tuple(goals.shape)}")
        if observations.ndim != 2 or observations.shape[0] != goals.shape[0]:
            raise ValueError(
                f"initial_observations must have shape [N, obs_dim] with N = {goals.shape[0]} "
                f"(one per trajectory), got {tuple(observations.shape)}"
            )
        if not (torch.isfinite(goals).all() and torch.isfinite(observations).all()):
            raise ValueError("achieved_goals and initial_observations must be finite (found NaN or inf)")
        if self._goals is None:
            device = self.device if self.device is not None else goals.device
            self._goals = torch.zeros(self.capacity, goals.shape[1], 3, device=device)
            self._observations = torch.zeros(self.capacity, observations.shape[1], device=device)
        elif goals.shape[1:] != self._goals.shape[1:] or observations.shape[1] != self._observations.shape[1]:
            raise ValueError(
                f"trajectories of shape {tuple(goals.shape[1:])} with observations of size {observations.shape[1]} "
                f"do not fit the pool, which holds {tuple(self._goals.shape[1:])} and {self._observations.shape[1]}"
            )
        goals = goals.to(self._goals)
        observations = observations.to(self._observations)
        displacement = torch.linalg.vector_norm(goals[:, -1] - goals[:, 0], dim=-1)
        admitted = displacement > self.min_displacement
        goals, observations = goals[admitted][-self.capacity :], observations[admitted][-self.capacity :]
        count = goals.shape[0]
        slots = (self._cursor + torch.arange(count, device=self._goals.device)) % self.capacity
        self._goals[slots] = goals
        self._observations[slots] = observations
        self._cursor = (self._cursor + count) % self.capacity
        self._size = min(self._size + count, self.capacity)
        return admitted.cpu()

    def state_dict(self) -> dict[str, Any]:
        """The stored trajectories and write position (for checkpoints)."""
        return {
            "capacity": self.capacity,
            "min_displacement": self.min_displacement,
            "size": self._size,
            "cursor": self._cursor,
            "achieved_goals": None if self._goals is None else self._goals[: self._size].clone(),
            "initial_observations": None if self._observations is None else self._observations[: self._size].clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output; the capacity must match this pool's."""
        if state["capacity"] != self.capacity:
            raise ValueError(f"checkpoint pool has capacity {state['capacity']}, this pool {self.capacity}")
        self.min_displacement = float(state["min_displacement"])
        goals, observations = state["achieved_goals"], state["initial_observations"]
        self._size, self._cursor = int(state["size"]), int(state["cursor"])
        if goals is None:
            self._goals = self._observations = None
            return
        device = self.device if self.device is not None else goals.device
        self._goals = torch.zeros(self.capacity, *goals.shape[1:], device=device)
        self._observations = torch.zeros(self.capacity, observations.shape[1], device=device)
        self._goals[: self._size] = goals
        self._observations[: self._size] = observations

    def __repr__(self) -> str:
        shape = None if self._goals is None else tuple(self._goals.shape[1:])
        return (
            f"TrajectoryPool(size={self._size}/{self.capacity}, min_displacement={self.min_displacement}, "
            f"trajectory_shape={shape})"
        )


@dataclass(frozen=True)
class GoalGeneration:
    """What one :meth:`HGGGoalGenerator.generate` call chose, and why.

    Attributes:
        goals: float32 ``[K, 3]``, the intermediate goal of each target task (the target itself where
            ``matched`` is False).
        matched: bool ``[K]``, whether the goal came from a pool trajectory.
        trajectory_index: int64 ``[K]``, the matched pool trajectory (row of
            :attr:`TrajectoryPool.achieved_goals`), ``-1`` where not matched.
        step_index: int64 ``[K]``, the point of that trajectory chosen by eq. 7, ``-1`` where not matched.
        cost: float32 ``[K]``, the matched cost of eq. 6 per target (0 where not matched).
        distance: float32 ``[K]``, metric distance from each goal to its target (``inf`` replaced by
            ``infinite_distance``; 0 where not matched).
        d_g: D_G(T, T*) of eq. 21, ``distance.mean()``.
        inside_fraction: fraction of goals within ``success_threshold`` (Euclidean) of some target.
        from_pool: True if every goal came from the pool (the stop condition is checked only then).
        stopped_now: True if this call's goals met the stop condition: from the next call on the
            generator returns the targets themselves, and the caller switches what depends on HGG
            running (GC-HGG's curriculum sampler to plain sampling, as the training loop does).
        timings: seconds spent in ``"value"`` (networks), ``"distance"`` (metric), ``"cost"``
            (eqs. 6–7) and ``"matching"``, and ``"total"``.
    """

    goals: torch.Tensor
    matched: torch.Tensor
    trajectory_index: torch.Tensor
    step_index: torch.Tensor
    cost: torch.Tensor
    distance: torch.Tensor
    d_g: float
    inside_fraction: float
    from_pool: bool
    stopped_now: bool = False
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def tradeoff_distances(self) -> torch.Tensor | None:
        """What a trade-off schedule (eq. 20) should see of this generation: the per-episode
        intermediate-to-target distances when the goals came from the pool, ``None`` when the
        episodes go to the targets themselves (the first iteration, or after the stop)."""
        return self.distance if self.from_pool else None

    @property
    def total_cost(self) -> float:
        """Sum of eq. 6 over the matched pairs: the quantity the matching minimises."""
        return float(self.cost.double().sum())


class HGGGoalGenerator:
    """Picks the intermediate goals of HGG / G-HGG from a trajectory pool (eqs. 6–7).

    Args:
        metric: goal distance ``d`` of eqs. 6–7, any object with ``distance(a, b)`` (goals ``[..., 3]``,
            broadcasting, float32 ``[...]``, ``inf`` allowed): ``GoalGraph`` (G-HGG) or
            ``EuclideanMetric`` (HGG). If it also has ``vertex_index`` and
            ``distance_between_vertices`` (as ``GoalGraph`` does), pool points are deduplicated to
            vertices before the table is read.
        value_fn: ``value(observation [B, obs_dim], goal [B, 3]) -> [B]``, e.g. ``agent.value``;
            may also be given per :meth:`generate` call. It receives tensors on the pool's device
            (CPU with ``GoalGraph``) and is called under ``torch.inference_mode``; its output is
            clipped again to ``[−1/(1 − γ), 0]`` here.

    Keyword Args:
        max_dis: metres, the largest target distance ``d(ĝ0, ĝ)`` over many resets (see
            :func:`estimate_max_distance`); scales the value bonus. Required.
        pool: the trajectory pool; by default ``TrajectoryPool(1000, 0.01)``.
        c: weight of the initial-state distance in eq. 6 (paper default 3.0).
        L: Lipschitz constant of eq. 5 (paper default 5.0).
        gamma: discount factor of the value function (default: the agent's, :class:`~gchgg.ddpg.agent.DDPGConfig`),
            for its clip range and scaling.
        stop_threshold: switch to plain HER once the fraction of intermediate goals within
            ``success_threshold`` of some target exceeds this (``None``: never; the original's
            README uses 0.3 for push, 0.5 for pick without and 0.9 with obstacle).
        success_threshold: metres, the success distance of eq. 23 (0.05).
        infinite_distance: finite metres used in place of an infinite metric distance (9999).
        small_pool: what to do when the pool holds fewer than K trajectories, ``"repeat"`` or
            ``"targets"`` (see the module docstring).
        value_batch_size: pool points per value-function call (4,096 keeps a 3 × 256 MLP's
            activations in cache: about 2× faster on CPU than 32,768).

    Example:
        >>> import torch
        >>> from gchgg.graph import EuclideanMetric
        >>> generator = HGGGoalGenerator(EuclideanMetric(), lambda s, g: torch.zeros(len(g)), max_dis=1.0)
        >>> start, target = torch.zeros(1, 3), torch.tensor([[1.0, 0.0, 0.0]])
        >>> generator.generate(start, target).goals  # empty pool: the targets themselves
        tensor([[1., 0., 0.]])
        >>> path = torch.linspace(0, 0.6, 7)[:, None] * torch.tensor([1.0, 0.0, 0.0])  # [7, 3]
        >>> _ = generator.pool.add(path[None], torch.zeros(1, 4))
        >>> result = generator.generate(start, target)
        >>> result.goals, round(result.d_g, 3)  # the pool point closest to the target
        (tensor([[0.6000, 0.0000, 0.0000]]), 0.4)
    """

    def __init__(
        self,
        metric: Any,
        value_fn: ValueFn | None = None,
        *,
        max_dis: float,
        pool: TrajectoryPool | None = None,
        c: float = 3.0,
        L: float = 5.0,
        gamma: float = DDPGConfig.gamma,
        stop_threshold: float | None = None,
        success_threshold: float = 0.05,
        infinite_distance: float = INFINITE_DISTANCE,
        small_pool: Literal["repeat", "targets"] = "repeat",
        value_batch_size: int = 4096,
    ) -> None:
        if not isinstance(metric, Metric):
            raise TypeError(
                "metric must be a gchgg.graph.Metric (distance(a, b) and lattice: GoalGraph, EuclideanMetric), "
                f"got {metric!r}"
            )
        if value_fn is not None and not callable(value_fn):
            raise TypeError(f"value_fn must be callable value(observation, goal) -> [B], got {value_fn!r}")
        check_number("max_dis", max_dis, low=0, low_open=True)
        check_number("c", c, low=0)
        check_number("L", L, low=0, low_open=True)
        check_number("success_threshold", success_threshold, low=0)
        check_number("infinite_distance", infinite_distance, low=0, low_open=True)
        check_gamma(gamma)  # the agent's one rule for the discount
        if stop_threshold is not None:
            check_number("stop_threshold (a fraction, or None: never stop)", stop_threshold, low=0, high=1)
        check_choice("small_pool", small_pool, _SMALL_POOL_CHOICES)
        check_number("value_batch_size", value_batch_size, integer=True, low=1)
        self.metric = metric
        self.value_fn = value_fn
        self.pool = pool if pool is not None else TrajectoryPool()
        self.max_dis = float(max_dis)
        self.c = float(c)
        self.L = float(L)
        self.gamma = float(gamma)
        self.stop_threshold = None if stop_threshold is None else float(stop_threshold)
        self.success_threshold = float(success_threshold)
        self.infinite_distance = float(infinite_distance)
        self.small_pool = small_pool
        self.value_batch_size = int(value_batch_size)
        self.stopped = False
        self._graph = metric.lattice  # a graph's vertex view (pool points deduplicated to vertices), or None

    # ------------------------------------------------------------------ public API

    def generate(
        self,
        initial_achieved_goals: torch.Tensor,
        target_goals: torch.Tensor,
        value_fn: ValueFn | None = None,
    ) -> GoalGeneration:
        """Intermediate goals for K target tasks (Alg. 2, line 6), and the stop check.

        Args:
            initial_achieved_goals: ``[K, 3]``, the achieved goal ĝ0 at each target task's reset.
            target_goals: ``[K, 3]``, the target goals ĝ.
            value_fn: overrides the constructor's value function for this call.

        Returns:
            A :class:`GoalGeneration`. The targets themselves (``from_pool`` False, D_G 0) if the
            pool is empty or the generator has stopped. Otherwise, if ``from_pool`` and the fraction
            of goals near a target exceeds ``stop_threshold``, :attr:`stopped` becomes True (and
            the result's ``stopped_now``) and every later call returns the targets.

        Raises:
            ValueError: mismatched shapes; non-finite goals; a value function returning the wrong
                shape or non-finite values.
        """
        start = time.perf_counter()
        initial, targets = self._check_tasks(initial_achieved_goals, target_goals)
        if self.stopped or len(self.pool) == 0:
            return self._targets_only(targets, start)

        value_fn = value_fn if value_fn is not None else self.value_fn
        if value_fn is None:
            raise ValueError("no value function: pass value_fn to HGGGoalGenerator(...) or to generate(...)")
        points = self.pool.achieved_goals  # [P, T1, 3]
        timings = {}
        tick = time.perf_counter()

        def lap() -> float:
            nonlocal tick
            now = time.perf_counter()
            elapsed, tick = now - tick, now
            return elapsed

        value = self._values(value_fn, self.pool.initial_observations, points)  # [P, T1]
        timings["value"] = lap()
        distance = self._distances(targets, points)  # [K, P, T1], finite
        timings["distance"] = lap()
        # Eq. 7 inside eq. 6: d(ag_it, ĝʲ) − V_it · max_dis·(1 − γ)/L, minimised over t. V <= 0, so
        # the value term is a penalty of up to max_dis / L metres for points hard to reach.
        value_term = value.mul_(self.max_dis * (1.0 - self.gamma) / self.L)
        best, step = (distance - value_term).min(dim=-1)  # [K, P]
        start_gap = _euclidean(initial, points[:, 0]).clamp_(max=self.infinite_distance)  # [K, P]
        cost = best.add_(start_gap, alpha=self.c)  # eq. 6, [K, P]
        timings["cost"] = lap()
        rows, columns = self._match(cost)
        timings["matching"] = lap()

        k = targets.shape[0]
        device = targets.device
        rows_t = torch.as_tensor(rows, device=device)
        columns_t = torch.as_tensor(columns, device=device)
        matched = torch.zeros(k, dtype=torch.bool, device=device)
        matched[rows_t] = True
        trajectory = torch.full((k,), -1, dtype=torch.long, device=device)
        trajectory[rows_t] = columns_t
        chosen_step = torch.full((k,), -1, dtype=torch.long, device=device)
        chosen_step[rows_t] = step[rows_t, columns_t]
        goals = targets.clone()
        goals[rows_t] = points[columns_t, chosen_step[rows_t]]
        goal_cost = torch.zeros(k, device=device)
        goal_cost[rows_t] = cost[rows_t, columns_t]
        goal_distance = torch.zeros(k, device=device)
        goal_distance[rows_t] = distance[rows_t, columns_t, chosen_step[rows_t]]
        from_pool = bool(matched.all())
        return self._result(goals, matched, trajectory, chosen_step, goal_cost, goal_distance, targets, from_pool,
                            timings, start)

    def state_dict(self) -> dict[str, Any]:
        """Pool contents and the stop flag (for checkpoints)."""
        return {"pool": self.pool.state_dict(), "stopped": self.stopped}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output."""
        self.pool.load_state_dict(state["pool"])
        self.stopped = bool(state["stopped"])

    def __repr__(self) -> str:
        return (
            f"HGGGoalGenerator(metric={self.metric!r}, c={self.c}, L={self.L}, gamma={self.gamma}, "
            f"max_dis={self.max_dis}, stop_threshold={self.stop_threshold}, stopped={self.stopped}, pool={self.pool!r})"
        )

    # ------------------------------------------------------------------ steps

    def _check_tasks(self, initial: torch.Tensor, targets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        device = self.pool.storage_device
        initial = torch.as_tensor(initial).to(device=device, dtype=torch.float32)
        targets = torch.as_tensor(targets).to(device=device, dtype=torch.float32)
        if targets.ndim != 2 or targets.shape[-1] != 3 or targets.shape[0] < 1:
            raise ValueError(f"target_goals must have shape [K, 3] with K >= 1, got {tuple(targets.shape)}")
        if initial.shape != targets.shape:
            raise ValueError(
                f"initial_achieved_goals must have the shape of target_goals {tuple(targets.shape)}, "
                f"got {tuple(initial.shape)}"
            )
        if not (torch.isfinite(initial).all() and torch.isfinite(targets).all()):
            raise ValueError("initial_achieved_goals and target_goals must be finite (found NaN or inf)")
        return initial, targets

    def _values(self, value_fn: ValueFn, observations: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """V(s_i0, ag_it) for every pool point, in batches, clipped: float32 [P, T1]."""
        num_trajectories, length = points.shape[:2]
        goals = points.reshape(-1, 3)
        owner = torch.arange(num_trajectories, device=points.device).repeat_interleave(length)
        chunks = []
        with torch.inference_mode():
            for first in range(0, goals.shape[0], self.value_batch_size):
                batch = slice(first, first + self.value_batch_size)
                size = goals[batch].shape[0]
                value = torch.as_tensor(value_fn(observations[owner[batch]], goals[batch]))
                if value.numel() != size or value.shape not in ((size,), (size, 1)):
                    raise ValueError(
                        f"value_fn must return one value per goal, shape [{size}], got {tuple(value.shape)}"
                    )
                chunks.append(value.reshape(size).to(device=points.device, dtype=torch.float32))
        value = torch.cat(chunks).reshape(num_trajectories, length)
        if not torch.isfinite(value).all():
            raise ValueError("value_fn returned NaN or inf for some pool points; check the critic")
        return value.clamp_(-1.0 / (1.0 - self.gamma), 0.0)

    def _distances(self, targets: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """Metric distance from every target to every pool point, inf replaced: float32 [K, P, T1]."""
        graph = self._graph
        if graph is not None:
            # Many pool points share a vertex: read the table once per (target vertex, pool vertex).
            target_vertex = graph.vertex_index(targets)  # [K]
            vertex, inverse = torch.unique(graph.vertex_index(points.reshape(-1, 3)), return_inverse=True)
            target_unique, target_inverse = torch.unique(target_vertex, return_inverse=True)
            table = graph.distance_between_vertices(target_unique[:, None], vertex[None, :])  # [K', U]
            distance = table[target_inverse][:, inverse]  # [K, P·T1]
        else:
            distance = self.metric.distance(targets[:, None, :], points.reshape(1, -1, 3))
        distance = torch.as_tensor(distance, dtype=torch.float32).reshape(targets.shape[0], *points.shape[:2])
        if torch.isnan(distance).any():
            raise ValueError(f"metric {self.metric!r} returned NaN distances")
        return distance.clamp_(max=self.infinite_distance)

    def _match(self, cost: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """Exact minimum-cost assignment of targets (rows) to trajectories (columns) of ``cost`` [K, P]."""
        k, p = cost.shape
        matrix = cost.detach().cpu().double().numpy()
        if p < k and self.small_pool == "repeat":
            copies = math.ceil(k / p)  # each trajectory may serve up to `copies` targets
            rows, columns = linear_sum_assignment(np.tile(matrix, (1, copies)))
            return rows, columns % p
        return linear_sum_assignment(matrix)  # K <= P: K distinct columns; else the best P rows

    def _targets_only(self, targets: torch.Tensor, start: float) -> GoalGeneration:
        k = targets.shape[0]
        none = torch.full((k,), -1, dtype=torch.long, device=targets.device)
        zeros = torch.zeros(k, device=targets.device)
        unmatched = torch.zeros(k, dtype=torch.bool, device=targets.device)
        return self._result(targets.clone(), unmatched, none, none.clone(), zeros, zeros.clone(), targets, False, {},
                            start)

    def _result(
        self, goals, matched, trajectory, step, cost, distance, targets, from_pool, timings, start
    ) -> GoalGeneration:
        near = _euclidean(goals, targets) <= self.success_threshold  # Euclidean, as the success test
        inside = int(near.any(dim=1).sum()) / goals.shape[0]  # exact fraction: 15 / 50 == 0.3
        stopped_now = (from_pool and self.stop_threshold is not None and inside > self.stop_threshold
                       and not self.stopped)
        self.stopped = self.stopped or stopped_now
        timings = {"value": 0.0, "distance": 0.0, "cost": 0.0, "matching": 0.0, **timings}
        timings["total"] = time.perf_counter() - start
        return GoalGeneration(
            goals=goals,
            matched=matched,
            trajectory_index=trajectory,
            step_index=step,
            cost=cost,
            distance=distance,
            d_g=float(distance.double().mean()),
            inside_fraction=inside,
            from_pool=from_pool,
            stopped_now=stopped_now,
            timings=timings,
        )


def estimate_max_distance(metric: Any, initial_achieved_goals: torch.Tensor, target_goals: torch.Tensor) -> float:
    """``max_dis`` of eq. 6: the largest finite metric distance from initial achieved goal to target.

    The original estimates it over 1,000 environment resets.

    Args:
        metric: any object with ``distance(a, b)``.
        initial_achieved_goals: ``[N, 3]`` achieved goals at reset.
        target_goals: ``[N, 3]`` target goals of the same resets.

    Returns:
        The largest finite distance, in metres.

    Raises:
        ValueError: no pair has a finite, positive distance.

    Example:
        >>> import torch
        >>> from gchgg.graph import EuclideanMetric
        >>> estimate_max_distance(EuclideanMetric(), torch.zeros(2, 3), torch.tensor([[3.0, 4, 0], [1, 0, 0]]))
        5.0
    """
    distance = torch.as_tensor(metric.distance(torch.as_tensor(initial_achieved_goals), torch.as_tensor(target_goals)))
    finite = distance[torch.isfinite(distance)]
    if finite.numel() == 0 or not finite.max() > 0:
        raise ValueError(
            "max_dis needs at least one finite, positive distance between initial achieved goals and "
            "targets; are the goals inside the metric's field?"
        )
    return float(finite.max())


def _euclidean(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """All pairwise distances ``[len(a), len(b)]``, computed exactly (not via a matrix product)."""
    return torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist")


