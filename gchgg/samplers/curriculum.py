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
_FAR = 10.0  # metres: off-graph goals are moved this far (and further) from the field for the shortlist
_CAP_SQUARED = 4.0  # m²: squared distances are capped here in the shortlist keys (a cap keeps a lower bound)
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

    Per-row cache. Each stored row's goal vertex (graph metrics) and goal-to-target distance are
    computed once, at the first ``sample`` after the row is written (rows the buffer reports through
    ``extend``/``add``/``mark_update``, and rows new to the storage), and kept in a float32 ``[n, 2]``
    tensor (8 bytes per stored row); ``sample`` then reads neither goals nor targets from the
    storage (except the goals for a diversity metric that is not a graph). Rows overwritten behind
    the sampler's back (TorchRL's ``buffer[index] = ...``, or another buffer writing into a full
    shared storage) keep stale entries until reported with ``sampler.mark_update(index)``.

    Cost per ``sample``: an EBP or uniform draw of K·B rows (O(K·B log n)), one read of K·B cached
    rows, K·B²·5 multiply-adds (one batched product) and ``neighbours + 1`` value-only passes
    over them, K·B·neighbours unchecked table reads and a few more per unproven goal. On push_new
    (``benchmarks/samplers.py``: 5,000 episodes, graph 31 × 31 × 11) about 1 % of the goals are
    unproven and the shortlist always equals the all-pairs value; the time, dominated by random
    memory reads (storage rows, graph table), is printed there as a ratio to uniform sampling.

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
        rows = self._stored_rows(storage, index, n)  # [K, B, 2]: goal vertex, goal-to-target distance
        to_target = rows[..., 1]
        lam = float(self.tradeoff.value)
        if self._nearest.snaps:
            nearest = self._nearest(vertex=rows[..., 0].long())
        else:
            nearest = self._nearest(read_field(storage, self.goal_key, index, self))
        proximity = -self._finite(to_target).sum(-1)  # eq. 15 with C = 0
        diversity = torch.where(torch.isfinite(nearest), nearest, 0.0).sum(-1)  # eq. 19
        best = torch.argmax(diversity + lam * proximity)
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
        """Cached ``[..., 2]`` of rows ``index``: goal vertex (as float, -1 off the graph; 0 without a
        graph) and goal-to-target distance, computed once per written row (see :meth:`_refresh`)."""
        if self._rows is None or n != self._known or self._pending:
            self._refresh(storage, n)
        return self._rows.index_select(0, index.view(-1)).view(*index.shape, 2)

    def _refresh(self, storage: Storage, n: int) -> None:
        """Compute the cache entries of rows written since the last sample (and of rows new to the storage)."""
        cache = self._rows
        fresh = [index[index < min(n, self._known)] for index in self._pending]
        if cache is None or len(cache) < n:
            size = max(n, int(getattr(storage, "max_size", n) or n))
            grown = torch.empty(size, 2)
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
        if self._nearest.snaps:
            cache[fresh, 0] = self.diversity_metric.vertex_index(goals).float()  # exact: < 2**24 vertices
        else:
            cache[fresh, 0] = 0.0
        cache[fresh, 1] = _check(self.metric.distance(goals, targets), "metric")

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
    ``[K, B, B]`` squared-distance matrix (a batched matrix product) and only those pairs are read
    from the metric. The (neighbours+1)-th Euclidean distance bounds every other pair from below,
    so a shortlist minimum within that bound is the exact nearest neighbour for any metric never
    shorter than the straight line; the other goals are re-scored against their whole batch. Graph
    metrics (with ``vertex_index``, ``vertices`` and ``distance_between_vertices``) are measured
    between the goals' lattice vertices, which their distance never undercuts (up to the table's
    rounding, ``resolution / 2``), and each goal is snapped to its vertex once.

    Speed: the squared distances come from one ``[K, B, 5] × [K, 5, B]`` product (the norms ride
    along as extra coordinates) into a scratch matrix reused between calls (fresh multi-megabyte
    tensors cost more in page faults than the arithmetic) and are turned into int32 keys in place,
    packing the (floored, so still a lower bound) squared distance above the column index; the
    shortlist is found with ``neighbours + 1`` value-only minimum passes over them (``topk`` would
    be ~10× slower). Graph distances are read with the graph's unchecked vertex lookup
    (``_pair_distance_unchecked`` where it has one): the indices come from ``vertex_index``.

    Args:
        metric: object with ``distance(a, b)`` on goals ``[..., 3]``.
        neighbours: shortlist length ≥ 1, or ``None`` to score all pairs with the metric.
    """

    def __init__(self, metric, neighbours: int | None = 3) -> None:
        self.metric = metric
        self.neighbours = neighbours
        self._snap = all(hasattr(metric, name) for name in ("vertex_index", "vertices", "distance_between_vertices"))
        self._lattice: torch.Tensor | None = None
        self._scratch: dict[str, torch.Tensor] = {}

    @property
    def snaps(self) -> bool:
        """Whether the metric is a graph whose goals are snapped to vertices (``vertex_index`` etc.)."""
        return self._snap

    def __call__(
        self, goals: torch.Tensor | None = None, *, vertex: torch.Tensor | None = None, stats: dict | None = None
    ) -> torch.Tensor:
        """Nearest-neighbour distances ``[K, B]`` of goals ``[K, B, 3]``.

        For a graph metric the goals' ``vertex_index`` ``[K, B]`` may be given instead of (or with)
        the goals; it must hold valid indices in ``[-1, num_vertices)`` (they are not checked).
        """
        if goals is None and vertex is None:
            raise ValueError("NearestNeighbours needs goals [K, B, 3] or (for a graph metric) their vertex indices")
        k, b = vertex.shape if vertex is not None else goals.shape[:2]
        if b < 2:
            return torch.full((k, b), math.inf)
        metric = self.metric
        if self._snap:
            if vertex is None:
                vertex = metric.vertex_index(goals)  # [K, B], -1 off the graph
            if self._lattice is None:
                lattice = torch.as_tensor(metric.vertices, dtype=torch.float32)
                self._lattice = lattice - lattice.mean(0)
            off = vertex < 0
            positions = self._lattice[vertex]  # -1 wraps to the last vertex; moved away just below
            # Off-graph goals are inf away from everything: park them far apart, out of every shortlist.
            far = _FAR * torch.arange(1, b + 1, dtype=positions.dtype)
            positions[..., 0] = torch.where(off, far.expand(k, b), positions[..., 0])
            lookup = getattr(metric, "_pair_distance_unchecked", metric.distance_between_vertices)
            flat = vertex.view(-1)

            def pair(rows: torch.Tensor, cols: torch.Tensor, batch: torch.Tensor) -> torch.Tensor:
                # Goal ``rows`` to goals ``cols`` (indices within candidate ``batch``), broadcasting.
                return lookup(flat[batch * b + rows], flat[batch * b + cols])

            tolerance = _BOUND_TOLERANCE + 0.5 * float(getattr(metric, "resolution", 0.0))
        else:
            if goals is None:
                raise ValueError("NearestNeighbours: vertex indices need a graph metric; pass the goals [K, B, 3]")
            positions = goals.float() - goals.float().mean(1, keepdim=True)
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

        cols, lower, keys, quantum = self._shortlist(positions, m)
        if self._snap:  # the same lookup as pair(rows, cols, batch), with fewer index operations
            candidates = vertex.gather(1, cols.view(k, b * m)).view(k, b, m)
            nearest = lookup(vertex.unsqueeze(-1), candidates).min(-1).values  # [K, B]
        else:
            nearest = pair(rows, cols, batch).min(-1).values  # [K, B]
        # Proven where the shortlist beats every goal outside it (a distance of 0, a duplicate goal,
        # always does). For the others, only goals whose Euclidean lower bound is below the best
        # distance so far can be nearer: score those (usually a handful) with the metric.
        unproven = nearest > (lower - tolerance).clamp_(min=0.0)
        if off is not None:
            unproven &= ~off
        if stats is not None:
            stats["rescored"] = int(unproven.sum())
        if bool(unproven.any()):
            kk, ii = unproven.nonzero(as_tuple=True)
            best = nearest[kk, ii]
            row = keys[kk, ii]  # [U, B]; the goal itself and its shortlist hold int32 max
            bound = ((row // b).float() * quantum).sqrt_().sub_(tolerance)
            bound.masked_fill_(row == _INT32_MAX, math.inf)
            uu, jj = (bound < best.unsqueeze(-1)).nonzero(as_tuple=True)
            if len(uu):
                distance = pair(ii[uu], jj, kk[uu])
                best = best.scatter_reduce(0, uu, distance, reduce="amin")
                nearest[kk, ii] = best
        return nearest

    def _shortlist(
        self, points: torch.Tensor, m: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
        """Each point's m Euclidean-nearest others ``[K, B, m]``, a lower bound on the distance to the rest
        ``[K, B]``, and the int32 keys ``[K, B, B]`` (level · B + column; shortlisted and self: int32 max)
        with the squared metres per level."""
        k, b, _ = points.shape
        # Squared-distance levels: exact integers in float32 (< 2**24) that fit above the column index in int32.
        levels = min((2**31 - 1) // b - 1, 2**24 - 1)
        quantum = _CAP_SQUARED / levels  # m² per level
        # Squared distances in levels from one product: [q_i, |q_i|², 1] · [-2 q_j, 1, |q_j|²] with q = p / √quantum.
        scaled = points * (1.0 / math.sqrt(quantum))
        norms = scaled.square().sum(-1, keepdim=True)
        ones = torch.ones_like(norms)
        left = torch.cat([scaled, norms, ones], -1)
        right = torch.cat([scaled * -2.0, ones, norms], -1).transpose(1, 2).contiguous()  # bmm is faster so
        squared = self._buffer("squared", (k, b, b), torch.float32)
        torch.bmm(left, right, out=squared).clamp_(0.0, levels)  # capped at _CAP_SQUARED: still a lower bound
        # In place (same 4-byte slots, element by element: one scratch matrix, half the cache footprint).
        keys = squared.view(torch.int32)
        keys.copy_(squared)  # truncation = floor for values >= 0: stays a lower bound
        torch.add(self._columns(b), keys, alpha=b, out=keys)  # key = level · B + column
        keys.diagonal(dim1=-2, dim2=-1).fill_(_INT32_MAX)
        cols = torch.empty(k, b, m, dtype=torch.long)
        for r in range(m):
            nearest = keys.amin(-1)  # [K, B]
            cols[..., r] = nearest % b
            keys.scatter_(-1, cols[..., r : r + 1], _INT32_MAX)
        level = keys.amin(-1) // b
        return cols, (level.float() * quantum).sqrt_(), keys, quantum  # levels < 2**24: exact in float32

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


def _check(distance: torch.Tensor, name: str) -> torch.Tensor:
    distance = torch.as_tensor(distance)
    if bool(torch.isnan(distance).any()):
        raise ValueError(f"the {name} returned NaN distances; goals must be finite")
    return distance
