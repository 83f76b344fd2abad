"""Graph-curriculum sampler (Algorithm 1): best of K candidate batches by diversity (eq. 19) + λ·proximity (eq. 15)."""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import Any

import numpy as np
import torch
from tensordict import NestedKey
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

from gchgg.samplers._storage import check_sampleable, dump_state, generator, load_state, read_field
from gchgg.samplers.energy import EnergySampler
from gchgg.samplers.tradeoff import Tradeoff, as_tradeoff

__all__ = ["GraphCurriculumSampler", "NearestNeighbours", "nearest_neighbour_distances"]

_BOUND_TOLERANCE = 1e-3  # metres: slack on the Euclidean lower bound (float32 rounding of |a|² + |b|² − 2a·b)
_LEVEL_SLACK = 2  # levels added to every squared distance so float32 rounding never makes one negative
_TO_TARGET = 6  # column of the goal-to-target distance in the sampler's per-row cache (after the point)
_INT32_MAX = 2**31 - 1


class GraphCurriculumSampler(Sampler):
    """Curriculum-guided sampling (Algorithm 1 of GC-HGG) as a TorchRL ``Sampler``.

    Each ``sample(storage, B)`` draws ``K = num_candidates`` candidate mini-batches A_1 … A_K of B
    stored transitions (with EBP, i.e. ∝ episode energy, when ``energy_key`` is given, uniformly
    otherwise), scores each

        F(A) = F_div(A) + λ · F_prox(A),
        F_div(A)  = Σ_{g_i ∈ A} min_{j ≠ i} d(g_i, g_j)                    (eq. 19)
        F_prox(A) = C − Σ_{g_i ∈ A} d(g_i, g*_i)                          (eq. 15, reported with C = 0)

    with g_i the transition's goal (``goal_key``, the hindsight goal it trains on) and g*_i the
    goal its episode was collected for (``target_key``), and returns the indices of the best
    candidate. ``info`` holds its ``diversity`` (F_div), ``proximity`` (F_prox) and ``tradeoff``
    (λ); a ``TensorDictReplayBuffer`` copies them into every sampled row. C shifts every candidate
    equally and does not change the choice.

    Distances that are ``inf`` (a goal off the graph: outside the field, inside an inflated
    obstacle, or cut off) never produce NaN: in F_prox such a distance counts as
    ``unreachable_distance`` (by default the largest finite goal-to-target distance of the K·B drawn
    transitions, so an unreachable goal is "as far as the farthest one"); in F_div a goal without a
    finite nearest neighbour contributes 0 (an off-graph goal adds no diversity).

    Nearest neighbours (F_div). The K·B² pairs are never all scored with the metric (a full
    256 × 256 graph-table gather per candidate would be random reads into a ~100 MB table). For each
    candidate, one batched matrix product gives the B goals' squared Euclidean distances, and
    ``neighbours + 1`` minimum passes give every goal a shortlist of its ``neighbours``
    Euclidean-nearest goals; the metric is read for those K·B·neighbours pairs only. The shortlist
    is *exact*: for a metric that is never shorter than the straight line, every goal outside the
    shortlist is at least the (neighbours+1)-th Euclidean distance away, so where the shortlist's
    best metric distance is within that bound the nearest neighbour is proven; for the few goals
    where it is not (typically beside an obstacle) the metric is also read for every goal whose
    Euclidean lower bound is below the best distance found. For a :class:`~gchgg.graph.GoalGraph`
    (any metric with ``vertex_index``, ``vertices`` and ``distance_between_vertices``) the straight
    lines are measured between the goals' lattice vertices, which the graph distance never
    undercuts (up to its table's rounding), and each goal is snapped once. A metric shorter than
    the straight line makes the shortlist approximate; ``neighbours=None`` scores all pairs (exact
    for any metric). See :class:`NearestNeighbours`.

    Per-row cache. Each stored row's shortlist point (the goal's lattice vertex relative to the
    field's centre, its squared norm and its vertex index; see :meth:`NearestNeighbours.points`) and
    its goal-to-target distance are computed once, at the first ``sample`` after the row is written
    (rows the buffer reports through ``extend``/``add``/``mark_update``, and rows new to the
    storage), and kept in a float32 ``[n, 7]`` tensor (28 bytes per stored row); ``sample`` then
    reads neither goals nor targets from the storage (except the goals for a diversity metric that
    is not a graph) and snaps no goal. Rows overwritten behind the sampler's back (TorchRL's
    ``buffer[index] = ...``, or another buffer writing into a full shared storage) keep stale
    entries until reported with ``sampler.mark_update(index)``.

    Cost per ``sample``: an EBP or uniform draw of K·B rows (O(K·B log n)), one read of K·B cached
    rows, K·B²·5 multiply-adds (one batched product) and about ten passes over the K·B² int32
    keys, K·B·neighbours unchecked table reads and a few more per unproven goal, and ~60 small
    tensor operations. On push_new (``benchmarks/samplers.py``: 5,000 episodes, graph
    31 × 31 × 11) about 1 % of the goals are unproven and the shortlist always equals the all-pairs
    value; the time is printed there as a ratio to uniform sampling.

    Args:
        metric: object with ``distance(a, b)`` on goals ``[..., 3]`` → ``[...]`` (``GoalGraph`` for
            GC-HGG, ``EuclideanMetric`` for the Euclidean ablation), used for F_prox and F_div.
        num_candidates: K ≥ 1 candidate batches per sample. Default 8.
        tradeoff: λ ≥ 0 as a number or a schedule (:class:`~gchgg.samplers.AdaptiveTradeoff` for
            eq. 20, :class:`~gchgg.samplers.ExponentialTradeoff` for eq. 4), read at every sample.

    Keyword Args:
        goal_key: stored goal each transition trains on. Default ``"desired_goal"``.
        target_key: stored goal proximity is measured to. Default ``"target_goal"`` (eq. 15); the
            original code measured from the transition's achieved goal (``"achieved_goal"``).
        energy_key: stored EBP energy; ``None`` (default) draws candidates uniformly.
        diversity_metric: metric of F_div if it differs from ``metric`` (the original code used
            Euclidean nearest neighbours). Default: ``metric``.
        neighbours: shortlist length (≥ 1) of the nearest-neighbour search, or ``None`` for all pairs.
            Default 3.
        unreachable_distance: metres an unreachable goal counts in F_prox; ``None`` (default) as
            described above.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from gchgg.graph import EuclideanMetric
        >>> g = torch.Generator().manual_seed(0)
        >>> goals = torch.rand(1000, 3, generator=g)
        >>> transitions = TensorDict({"desired_goal": goals, "target_goal": torch.zeros(1000, 3)}, [1000])
        >>> sampler = GraphCurriculumSampler(EuclideanMetric(), num_candidates=8, tradeoff=10.0)
        >>> buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(10_000), sampler=sampler,
        ...                                 batch_size=64, generator=g)
        >>> _ = buffer.extend(transitions)
        >>> batch = buffer.sample()
        >>> batch.batch_size, sorted(k for k in ("diversity", "proximity", "tradeoff") if k in batch)
        (torch.Size([64]), ['diversity', 'proximity', 'tradeoff'])
        >>> batch["tradeoff"][0].item()
        10.0
        >>> uniform = goals.norm(dim=-1).mean()  # the chosen batch is nearer its targets than average
        >>> bool(batch["desired_goal"].norm(dim=-1).mean() < uniform)
        True
    """

    def __init__(
        self,
        metric,
        num_candidates: int = 8,
        tradeoff: Tradeoff | float = 0.0,
        *,
        goal_key: NestedKey = "desired_goal",
        target_key: NestedKey = "target_goal",
        energy_key: NestedKey | None = None,
        diversity_metric=None,
        neighbours: int | None = 3,
        unreachable_distance: float | None = None,
    ) -> None:
        for name, m in (("metric", metric), ("diversity_metric", diversity_metric)):
            if m is not None and not callable(getattr(m, "distance", None)):
                raise TypeError(f"{name} must have a distance(a, b) method (GoalGraph, EuclideanMetric), got {m!r}")
        if isinstance(num_candidates, bool) or not isinstance(num_candidates, int) or num_candidates < 1:
            raise ValueError(f"num_candidates must be an integer >= 1, got {num_candidates!r}")
        if neighbours is not None and (
            isinstance(neighbours, bool) or not isinstance(neighbours, int) or neighbours < 1
        ):
            raise ValueError(f"neighbours must be an integer >= 1 or None (all pairs), got {neighbours!r}")
        if unreachable_distance is not None and not (
            isinstance(unreachable_distance, (int, float))
            and math.isfinite(unreachable_distance)
            and unreachable_distance >= 0
        ):
            raise ValueError(f"unreachable_distance must be a finite number >= 0 or None, got {unreachable_distance!r}")
        self.metric = metric
        self.diversity_metric = metric if diversity_metric is None else diversity_metric
        self.num_candidates = num_candidates
        self.tradeoff = as_tradeoff(tradeoff)
        self.goal_key = goal_key
        self.target_key = target_key
        self.energy_key = energy_key
        self.unreachable_distance = unreachable_distance
        self._energy = EnergySampler(energy_key) if energy_key is not None else None
        self._nearest = NearestNeighbours(self.diversity_metric, neighbours)
        # Per stored row: goal vertex and goal-to-target distance, valid for rows < _known not in _pending.
        self._rows: torch.Tensor | None = None
        self._known = 0
        self._pending: list[torch.Tensor] = []

    @property
    def neighbours(self) -> int | None:
        """Shortlist length of the nearest-neighbour search (``None``: all pairs)."""
        return self._nearest.neighbours

    @neighbours.setter
    def neighbours(self, value: int | None) -> None:
        self._nearest.neighbours = value

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        n = check_sampleable(storage, self)
        rng = generator(self)
        k, b = self.num_candidates, batch_size
        if self._energy is not None:
            self._energy._rng = rng
            index = self._energy.draw(storage, k, b)
        else:
            index = torch.randint(n, (k, b), generator=rng).sort(-1).values  # sorted: cache-friendly reads
        rows = self._stored_rows(storage, index, n)  # [K, B, 7]: shortlist point (6), goal-to-target distance
        lam = float(self.tradeoff.value)
        goals = None if self._nearest.snaps else read_field(storage, self.goal_key, index, self)
        nearest = self._nearest.from_points(rows[..., :_TO_TARGET], goals)
        proximity = -self._finite(rows[..., _TO_TARGET]).sum(-1)  # eq. 15 with C = 0
        diversity = nearest.nan_to_num(posinf=0.0).sum(-1)  # eq. 19: no finite neighbour adds nothing
        best = int(torch.argmax(diversity + lam * proximity))
        info = {
            "diversity": diversity[best],
            "proximity": proximity[best],
            "tradeoff": torch.tensor(lam, dtype=torch.float32),
        }
        return index[best], info

    def _finite(self, distance: torch.Tensor) -> torch.Tensor:
        finite = torch.isfinite(distance)
        if bool(finite.all()):
            return distance
        if self.unreachable_distance is not None:
            fill = self.unreachable_distance
        else:
            fill = distance[finite].max().item() if bool(finite.any()) else 0.0
        return torch.where(finite, distance, fill)

    def _stored_rows(self, storage: Storage, index: torch.Tensor, n: int) -> torch.Tensor:
        """Cached ``[..., 7]`` of rows ``index``: the goal's shortlist point (see
        :meth:`NearestNeighbours.points`) and its goal-to-target distance, computed once per written row."""
        if self._rows is None or n != self._known or self._pending:
            self._refresh(storage, n)
        return self._rows.index_select(0, index.view(-1)).view(*index.shape, _TO_TARGET + 1)

    def _refresh(self, storage: Storage, n: int) -> None:
        """Compute the cache entries of rows written since the last sample (and of rows new to the storage)."""
        cache = self._rows
        fresh = [index[index < min(n, self._known)] for index in self._pending]
        if cache is None or len(cache) < n:
            size = max(n, int(getattr(storage, "max_size", n) or n))
            grown = torch.empty(size, _TO_TARGET + 1)
            if cache is not None:
                grown[: self._known] = cache[: self._known]
            cache, self._known = grown, 0
            fresh = []
        if n > self._known:
            fresh.append(torch.arange(self._known, n))
        self._rows, self._known, self._pending = cache, n, []
        fresh = torch.cat(fresh) if fresh else torch.empty(0, dtype=torch.long)
        if not len(fresh):
            return
        goals = read_field(storage, self.goal_key, fresh, self)
        targets = read_field(storage, self.target_key, fresh, self)
        cache[fresh, :_TO_TARGET] = self._nearest.points(goals)
        cache[fresh, _TO_TARGET] = _check(self.metric.distance(goals, targets), "metric")

    def _forget(self, index) -> None:
        """Mark (re)written rows: their cache entries are recomputed at the next sample."""
        if self._rows is None:
            return
        if isinstance(index, (int, torch.Tensor, np.ndarray)) and not torch.as_tensor(index).is_floating_point():
            self._pending.append(torch.as_tensor(index).reshape(-1).long())
        else:  # a slice or anything else: recompute everything
            self._rows = None

    # Writes invalidate the EBP cache and the rows' cached vertices and distances.
    def extend(self, index: torch.Tensor) -> None:
        self._forget(index)
        if self._energy is not None:
            self._energy.extend(index)

    def add(self, index: int) -> None:
        self._forget(index)
        if self._energy is not None:
            self._energy.add(index)

    def mark_update(self, index, *, storage: Storage | None = None) -> None:
        self._forget(index)
        if self._energy is not None:
            self._energy.mark_update(index)

    def _empty(self) -> None:
        self._rows, self._known, self._pending = None, 0, []
        if self._energy is not None:
            self._energy._empty()

    def state_dict(self) -> dict[str, Any]:
        return OrderedDict(
            num_candidates=self.num_candidates,
            neighbours=self.neighbours,
            unreachable_distance=self.unreachable_distance,
            tradeoff=dict(self.tradeoff.state_dict()),
        )

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.num_candidates = int(state_dict["num_candidates"])
        self.neighbours = None if state_dict["neighbours"] is None else int(state_dict["neighbours"])
        self.unreachable_distance = state_dict["unreachable_distance"]
        self.tradeoff.load_state_dict(state_dict["tradeoff"])
        self._empty()

    def dumps(self, path) -> None:
        dump_state(self.state_dict(), path)

    def loads(self, path) -> None:
        self.load_state_dict(load_state(path))

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(metric={self.metric!r}, num_candidates={self.num_candidates}, "
            f"tradeoff={self.tradeoff!r}, energy_key={self.energy_key!r}, neighbours={self.neighbours})"
        )


def nearest_neighbour_distances(
    goals: torch.Tensor, metric, neighbours: int | None = 3, *, stats: dict | None = None
) -> torch.Tensor:
    """Metric distance from each goal to its nearest other goal of the same batch: min_{j≠i} d(g_i, g_j).

    A one-off :class:`NearestNeighbours` (which keeps its scratch memory between calls).

    Args:
        goals: ``[K, B, 3]``: K batches of B goals.
        metric: object with ``distance(a, b)``.
        neighbours: shortlist length, ``None`` for all pairs.
        stats: if given, ``stats["rescored"]`` is set to the number of goals the shortlist did not
            prove (for which the goals within the Euclidean bound were read too).

    Returns:
        float32 ``[K, B]``, ``inf`` where a goal has no finite distance to any other (or B = 1).
    """
    return NearestNeighbours(metric, neighbours)(goals, stats=stats)


class NearestNeighbours:
    """Exact nearest-neighbour metric distances within batches of goals, via a Euclidean shortlist.

    For each goal the ``neighbours`` Euclidean-nearest goals of its batch are found from one
    ``[K, B, B]`` matrix of squared distances (a batched matrix product) and only those pairs are
    read from the metric. The (neighbours+1)-th Euclidean distance bounds every other pair from
    below, so a shortlist minimum within that bound is the exact nearest neighbour for any metric
    never shorter than the straight line; for the other goals, every goal whose bound is below the
    best distance found is read too. Graph metrics (with ``vertex_index``, ``vertices`` and
    ``distance_between_vertices``) are measured between the goals' lattice vertices, which their
    distance never undercuts (up to the table's rounding, ``resolution / 2``).

    Each goal becomes a *point* once (:meth:`points`, which a sampler can cache per stored row):
    its position relative to a fixed origin (the lattice vertex for a graph; off-graph goals parked
    together far outside the field, out of every on-graph shortlist), the squared norm, a 1, and
    its vertex index (graph) or 0. The product ``[p, |p|², 1] · [-2p, 1, |p|² + 2q]ᵀ / q`` then gives
    every pair's squared distance in levels of q = (2·max|p|)² / levels (no pair exceeds the top
    level, and the +2 keeps float32 rounding from going below 0) in one ``bmm`` into a scratch matrix
    reused between calls. The levels are truncated to int32 in place and the column index is packed
    below them (``key = level · B + column``), so ``neighbours + 1`` value-only ``amin`` passes find
    the shortlist and the bound (``topk`` is ~10× slower). About ten passes over K·B² int32 values
    in all; graph distances are read with the graph's unchecked vertex lookup.

    Args:
        metric: object with ``distance(a, b)`` on goals ``[..., 3]``.
        neighbours: shortlist length ≥ 1, or ``None`` to score all pairs with the metric.
    """

    def __init__(self, metric, neighbours: int | None = 3) -> None:
        self.metric = metric
        self.neighbours = neighbours
        self._snap = all(hasattr(metric, name) for name in ("vertex_index", "vertices", "distance_between_vertices"))
        self._origin: torch.Tensor | None = None
        self._lattice: torch.Tensor | None = None  # graph vertices relative to the origin
        self._park: torch.Tensor | None = None  # where off-graph goals are put
        self._reach = 0.0  # graph: the largest |p| of any point (the parking distance)
        self._scratch: dict[str, torch.Tensor] = {}

    @property
    def snaps(self) -> bool:
        """Whether the metric is a graph whose goals are snapped to vertices (``vertex_index`` etc.)."""
        return self._snap

    def points(self, goals: torch.Tensor) -> torch.Tensor:
        """float32 ``[..., 6]`` shortlist points of goals ``[..., 3]``: ``(x, y, z, |p|², 1, id)``.

        ``p`` is the goal's lattice vertex (graph metrics; off-graph goals: a parking spot far outside
        the field) or the goal itself, relative to a fixed origin (the field's centre, or the first
        goals' mean); ``id`` is the vertex index (``-1`` off the graph) or 0.
        """
        goals = torch.as_tensor(goals)
        if self._snap:
            self._setup_graph()
            vertex = self.metric.vertex_index(goals)
            position = torch.where((vertex >= 0).unsqueeze(-1), self._lattice[vertex], self._park)
            ident = vertex.float()  # exact: < 2**24 vertices
        else:
            goals = goals.float()
            if not bool(torch.isfinite(goals).all()):
                raise ValueError("goals must be finite for a metric without a graph (NaN or inf found)")
            if self._origin is None:
                self._origin = goals.reshape(-1, 3).mean(0) if goals.numel() else torch.zeros(3)
            position = goals - self._origin
            ident = torch.zeros(goals.shape[:-1])
        norm = position.square().sum(-1, keepdim=True)
        return torch.cat([position, norm, torch.ones_like(norm), ident.unsqueeze(-1)], -1)

    def _setup_graph(self) -> None:
        if self._lattice is not None:
            return
        metric = self.metric
        vertices = torch.as_tensor(metric.vertices, dtype=torch.float32)
        field = getattr(metric, "field", None)
        if field is not None:
            center, half = (torch.as_tensor(v, dtype=torch.float32) for v in field)
        else:
            low, high = vertices.min(0).values, vertices.max(0).values
            center, half = (low + high) / 2, (high - low) / 2
        self._origin = center
        self._lattice = vertices - center
        # Parked at 1.5 field diagonals: farther from every vertex than any two vertices are apart.
        diagonal = 2.0 * float(half.norm())
        self._reach = 1.5 * max(diagonal, 1e-3)
        self._park = torch.tensor([self._reach, 0.0, 0.0])

    def __call__(self, goals: torch.Tensor, *, stats: dict | None = None) -> torch.Tensor:
        """Nearest-neighbour distances ``[K, B]`` of goals ``[K, B, 3]``."""
        goals = torch.as_tensor(goals)
        return self.from_points(self.points(goals), None if self._snap else goals, stats=stats)

    def from_points(
        self, points: torch.Tensor, goals: torch.Tensor | None = None, *, stats: dict | None = None
    ) -> torch.Tensor:
        """Nearest-neighbour distances ``[K, B]`` from the goals' :meth:`points` ``[K, B, 6]`` (made by this
        object). A metric without a graph also needs the goals ``[K, B, 3]`` themselves."""
        k, b = points.shape[:2]
        if b < 2:
            return torch.full((k, b), math.inf)
        metric = self.metric
        if self._snap:
            self._setup_graph()
            vertex = points[..., 5].long()  # [K, B], -1 off the graph
            off = vertex < 0
            lookup = getattr(metric, "_pair_distance_unchecked", metric.distance_between_vertices)
            flat = vertex.view(-1)

            def pair(rows: torch.Tensor, cols: torch.Tensor, batch: torch.Tensor) -> torch.Tensor:
                # Goal ``rows`` to goals ``cols`` (indices within candidate ``batch``), broadcasting.
                return lookup(flat[batch * b + rows], flat[batch * b + cols])

            tolerance = _BOUND_TOLERANCE + 0.5 * float(getattr(metric, "resolution", 0.0))
        else:
            if goals is None:
                raise ValueError("NearestNeighbours.from_points: a metric without a graph needs the goals [K, B, 3]")
            off = None

            def pair(rows: torch.Tensor, cols: torch.Tensor, batch: torch.Tensor) -> torch.Tensor:
                return _check(metric.distance(goals[batch, rows], goals[batch, cols]), "diversity metric")

            tolerance = _BOUND_TOLERANCE

        batch = torch.arange(k).view(k, 1, 1)
        rows = torch.arange(b).view(1, b, 1)
        m = self.neighbours
        if m is None or m >= b - 1:  # all pairs
            if stats is not None:
                stats["rescored"] = 0
            distance = pair(rows, torch.arange(b).view(1, 1, b), batch).clone()
            distance.diagonal(dim1=-2, dim2=-1).fill_(math.inf)
            return distance.min(-1).values

        cols, level, keys, quantum = self._shortlist(points, m)
        if self._snap:  # the same lookup as pair(rows, cols, batch), with fewer index operations
            candidates = vertex.gather(1, cols.view(k, b * m)).view(k, b, m)
            nearest = lookup(vertex.unsqueeze(-1), candidates).amin(-1)  # [K, B]
        else:
            nearest = pair(rows, cols, batch).amin(-1)  # [K, B]
        # Proven where the shortlist beats every goal outside it (a distance of 0, a duplicate goal,
        # always does). For the others, only goals whose Euclidean lower bound is below the best
        # distance so far can be nearer: score those (usually a handful) with the metric.
        unproven = nearest > _distance(level, quantum).sub_(tolerance).clamp_(min=0.0)
        if off is not None:
            unproven &= ~off
        if stats is not None:
            stats["rescored"] = int(unproven.sum())
        if bool(unproven.any()):
            kk, ii = unproven.nonzero(as_tuple=True)
            best = nearest[kk, ii]
            row = keys[kk, ii]  # [U, B]; the goal itself and its shortlist hold int32 max
            bound = _distance(row // b, quantum).sub_(tolerance).masked_fill_(row == _INT32_MAX, math.inf)
            uu, jj = (bound < best.unsqueeze(-1)).nonzero(as_tuple=True)
            if len(uu):
                distance = pair(ii[uu], jj, kk[uu])
                best = best.scatter_reduce(0, uu, distance, reduce="amin")
                nearest[kk, ii] = best
        return nearest

    def _shortlist(
        self, points: torch.Tensor, m: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
        """Each point's m Euclidean-nearest others ``[K, B, m]``, the level of the nearest of the rest
        ``[K, B]`` (a lower bound on the squared distance to every goal outside the shortlist, see
        :func:`_distance`), the int32 keys ``[K, B, B]`` (level · B + column; shortlisted and self: int32 max)
        and the squared metres per level."""
        k, b, _ = points.shape
        levels = _INT32_MAX // b - 2 * _LEVEL_SLACK  # key = level · B + column stays below int32 max
        # |p_i − p_j| ≤ 2·max|p|: no pair is above the top level, so no clamp is needed. For a graph
        # max|p| is the parking distance; otherwise it is read from the points.
        reach = self._reach if self._snap else float(points[..., 3].amax()) ** 0.5
        quantum = max(4.0 * reach * reach, 1e-12) / levels
        left = points[..., :5]  # [p, |p|², 1]
        right = torch.matmul(self._product_map(quantum), left.transpose(1, 2))  # [K, 5, B]: [-2p, 1, |p|² + 2q] / q
        squared = self._buffer("squared", (k, b, b), torch.float32)
        torch.bmm(left, right, out=squared)  # squared distance in levels, + _LEVEL_SLACK
        # In place (same 4-byte slots, element by element: one scratch matrix, half the cache footprint).
        keys = squared.view(torch.int32)
        keys.copy_(squared)  # truncation: level + slack - 1 <= key level <= level + slack (float32 rounding < 1 level)
        torch.add(self._columns(b), keys, alpha=b, out=keys)  # key = level · B + column
        keys.diagonal(dim1=-2, dim2=-1).fill_(_INT32_MAX)
        cols = torch.empty(k, b, m, dtype=torch.long)
        for r in range(m):
            column = torch.remainder(keys.amin(-1, keepdim=True), b).long()  # [K, B, 1]
            cols[..., r : r + 1] = column
            keys.scatter_(-1, column, _INT32_MAX)
        return cols, keys.amin(-1) // b, keys, quantum

    def _product_map(self, quantum: float) -> torch.Tensor:
        """``M`` with ``M · [p, |p|², 1]ᵀ = [-2p, 1, |p|² + slack·q]ᵀ / q`` (a 5 × 5 matrix, kept per quantum)."""
        cached = self._scratch.get("map")
        if cached is None or cached[0] != quantum:
            product = torch.zeros(5, 5)
            product[[0, 1, 2], [0, 1, 2]] = -2.0 / quantum
            product[3, 4] = product[4, 3] = 1.0 / quantum
            product[4, 4] = float(_LEVEL_SLACK)
            cached = self._scratch["map"] = (quantum, product)
        return cached[1]

    def _columns(self, b: int) -> torch.Tensor:
        columns = self._scratch.get("columns")
        if columns is None or len(columns) != b:
            columns = self._scratch["columns"] = torch.arange(b, dtype=torch.int32)
        return columns

    def _buffer(self, name: str, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        buffer = self._scratch.get(name)
        if buffer is None or buffer.shape != shape:
            buffer = self._scratch[name] = torch.empty(shape, dtype=dtype)
        return buffer


def _distance(level: torch.Tensor, quantum: float) -> torch.Tensor:
    """A lower bound in metres on the distance of a pair whose key has this level: the level less the
    slack and one more for float32 rounding (at least 0), times the quantum, square-rooted."""
    return (level - (_LEVEL_SLACK + 1)).clamp_(min=0).float().mul_(quantum).sqrt_()


def _check(distance: torch.Tensor, name: str) -> torch.Tensor:
    distance = torch.as_tensor(distance)
    if bool(torch.isnan(distance).any()):
        raise ValueError(f"the {name} returned NaN distances; goals must be finite")
    return distance
