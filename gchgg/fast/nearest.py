"""Exact nearest-neighbour metric distances within batches of goals (F_div of eq. 19), via a Euclidean shortlist.

The engine behind :class:`~gchgg.samplers.GraphCurriculumSampler`'s diversity term, apart from the
sampler: :class:`NearestNeighbours` (reusable, with its scratch memory) and
:func:`nearest_neighbour_distances` (one-off); the shortlist's integer arithmetic is
:class:`~gchgg.fast.shortlist.Shortlist`. ``tests/test_samplers.py`` checks it against a
brute-force all-pairs minimum, bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from gchgg.common.validation import check_distances, check_number
from gchgg.fast.shortlist import Shortlist

__all__ = [
    "POINT_SIZE", "NearestNeighbours", "check_distances", "check_goals", "nearest_neighbour_distances", "point_size",
]

POINT_SIZE = 6  # values per shortlist point of a 3-D goal: (x, y, z, |p|², 1, id); d + 3 for d-D goals
_GRAPH_TOLERANCE = 1e-3  # metres: slack on a graph's straight-line bounds, besides half its table's resolution
_RELATIVE_TOLERANCE = 1e-5  # slack on straight-line bounds between goals, per metre of their coordinates (>= 1 m)
_REPEATS_FIRST = 8  # goals are reordered heads first when more than 1 in this many repeat another


def point_size(dim: int) -> int:
    """Values per shortlist point of ``dim``-D goals: the position, ``|p|²``, 1 and the vertex id."""
    return dim + 3


def check_goals(goals, name: str, dim: int | None = None) -> torch.Tensor:
    """``goals`` as a tensor of shape ``[..., d]`` (d ≥ 1, and ``d == dim`` when given); a ``ValueError``
    naming ``name``, the shape and what is allowed otherwise."""
    goals = torch.as_tensor(goals)
    if goals.ndim < 1 or goals.shape[-1] < 1 or (dim is not None and goals.shape[-1] != dim):
        allowed = f"[..., {dim}] (the goal space has {dim} dimensions)" if dim is not None else "[..., d] with d >= 1"
        raise ValueError(f"{name} must have shape {allowed}, got shape {tuple(goals.shape)}")
    return goals


def nearest_neighbour_distances(
    goals: torch.Tensor, metric, neighbours: int | str | None = "auto", *, block: int = 32, stats: dict | None = None
) -> torch.Tensor:
    """Metric distance from each goal to its nearest other goal of the same batch: min_{j≠i} d(g_i, g_j).

    A one-off :class:`NearestNeighbours` (which keeps its scratch memory between calls).

    Args:
        goals: ``[K, B, d]``: K batches of B goals (any dimension d ≥ 1).
        metric: object with ``distance(a, b)``.
        neighbours: shortlist length, ``"auto"`` or ``None`` for all pairs (see :class:`NearestNeighbours`).
        block: goals per block of the shortlist search (see :class:`NearestNeighbours`).
        stats: if given, ``stats["rescored"]`` is set to the number of goals the shortlist did not
            prove (for which the goals within the Euclidean bound were read too).

    Returns:
        float32 ``[K, B]``, ``inf`` where a goal has no finite distance to any other (or B = 1).
    """
    return NearestNeighbours(metric, neighbours, block)(goals, stats=stats)


class NearestNeighbours:
    """Exact nearest-neighbour metric distances within batches of goals, via a Euclidean shortlist.

    Goals may have any dimension d ≥ 1 (fixed by the metric's lattice, or by the first goals made
    points). Each goal becomes a *point* once (:meth:`points`, which a sampler can cache per stored row):
    its position relative to a fixed origin (the lattice vertex for a graph metric, whose
    distance never undercuts the straight line between vertices; off-graph goals parked together
    far outside the field), the squared norm, a 1, and its vertex index (graph) or 0.
    :meth:`from_points` then finds each goal's nearest other goal of its batch, reading the metric
    for a shortlist of pairs and proving that no other goal is nearer (see there).

    Cost for K batches of B goals: K·B·3·block·5 multiply-adds and about ten passes over K·B·3·block
    int32 keys (786 KB for K = 8, B = 256, block = 32: in the core's L2 cache, where all K·B² keys
    would not be), K·B·neighbours metric reads, and a few more per unproven goal.

    Args:
        metric: object with ``distance(a, b)`` on goals ``[..., d]``.
        neighbours: shortlist length ≥ 1, ``None`` to score all pairs with the metric, or ``"auto"``
            (default): 3 for a metric with a lattice (graph distances reorder the straight-line
            nearest goals), 1 for one without (the straight line already orders them). The result
            is the same for every length; only the number of metric reads differs.
        block: goals per block (≥ 2); batches of at most ``3 · block`` goals are one block.
    """

    def __init__(self, metric, neighbours: int | str | None = "auto", block: int = 32, span: int = 1) -> None:
        check_number("block", block, integer=True, low=2)
        check_number("span", span, integer=True, low=1)
        if neighbours == "auto":
            neighbours = 3 if metric.lattice is not None else 1
        elif neighbours is not None:
            check_number('neighbours (or None: all pairs, or "auto")', neighbours, integer=True, low=1)
        self.metric = metric
        self.neighbours = neighbours
        self._shortlist = Shortlist(block, span)  # with its scratch memory
        self._graph = metric.lattice  # the graph's vertex view (snap, table lookups), or None: goals as they are
        self._snap = self._graph is not None
        self._origin: torch.Tensor | None = None
        self._axis = 0  # the coordinate goals are sorted by: the field's longest (graph) or widest-spread one
        self._lattice: torch.Tensor | None = None  # graph vertices relative to the origin
        self._park: torch.Tensor | None = None  # where off-graph goals are put
        self._reach = 0.0  # graph: the largest |p| of any point (the parking distance)
        self._scale = 0.0  # no graph: the largest absolute coordinate of any goal made a point
        self._dim: int | None = None if self._graph is None else len(self._graph.field[0])  # goal dimension d

    @property
    def block(self) -> int:
        """Goals per block of the shortlist search."""
        return self._shortlist.block

    @property
    def span(self) -> int:
        """Blocks on either side of a goal's block in its window."""
        return self._shortlist.span

    @property
    def snaps(self) -> bool:
        """Whether the metric has a :class:`~gchgg.graph.Lattice` whose vertices goals are snapped to."""
        return self._snap

    @property
    def dim(self) -> int | None:
        """The goals' dimension d (``None`` until the first goals are made points, for a metric without a lattice)."""
        return self._dim

    def points(self, goals: torch.Tensor) -> torch.Tensor:
        """float32 ``[..., d + 3]`` shortlist points of goals ``[..., d]``: ``(p, |p|², 1, id)``, e.g.
        ``(x, y, z, |p|², 1, id)`` for 3-D goals.

        ``p`` is the goal's lattice vertex (graph metrics; off-graph goals: a parking spot far outside
        the field) or the goal itself, relative to a fixed origin (the field's centre, or the first
        goals' mean); ``id`` is the vertex index (``-1`` off the graph) or 0.
        """
        goals = check_goals(goals, "goals", self._dim)
        if self._dim is None:
            self._dim = goals.shape[-1]
        if self._snap:
            self._setup_graph()
            vertex = self._graph.vertex_index(goals)
            position = torch.where((vertex >= 0).unsqueeze(-1), self._lattice[vertex], self._park)
            ident = vertex.float()  # exact: < 2**24 vertices
        else:
            goals = goals.float()
            if not bool(torch.isfinite(goals).all()):
                raise ValueError("goals must be finite for a metric without a graph (NaN or inf found)")
            if self._origin is None:
                flat = goals.reshape(-1, goals.shape[-1])
                self._origin = flat.mean(0) if len(flat) else torch.zeros(goals.shape[-1])
                self._axis = int(flat.std(0).argmax()) if len(flat) > 1 else 0
            if goals.numel():
                self._scale = max(self._scale, float(goals.abs().amax()))
            position = goals - self._origin
            ident = torch.zeros(goals.shape[:-1])
        norm = position.square().sum(-1, keepdim=True)
        return torch.cat([position, norm, torch.ones_like(norm), ident.unsqueeze(-1)], -1)

    def _setup_graph(self) -> None:
        if self._lattice is not None:
            return
        graph = self._graph
        vertices = torch.as_tensor(graph.vertices, dtype=torch.float32)
        center, half = (torch.as_tensor(v, dtype=torch.float32) for v in graph.field)
        self._origin = center
        self._axis = int(half.argmax())
        self._lattice = vertices - center
        # Parked at 1.5 field diagonals along the sort axis: farther from every vertex than any two
        # vertices are apart, and sorted after all of them.
        diagonal = 2.0 * float(half.norm())
        self._reach = 1.5 * max(diagonal, 1e-3)
        self._park = torch.zeros(len(half))
        self._park[self._axis] = self._reach

    def __call__(self, goals: torch.Tensor, *, stats: dict | None = None) -> torch.Tensor:
        """Nearest-neighbour distances ``[K, B]`` of goals ``[K, B, d]``."""
        goals = check_goals(goals, "goals", self._dim)
        if goals.ndim != 3:
            raise ValueError(f"goals must have shape [K, B, d] (K batches of B goals), got shape {tuple(goals.shape)}")
        return self.from_points(self.points(goals), None if self._snap else goals, stats=stats)

    def from_points(
        self, points: torch.Tensor, goals: torch.Tensor | None = None, *, stats: dict | None = None
    ) -> torch.Tensor:
        """Nearest-neighbour distances ``[K, B]``, min_{j≠i} d(g_i, g_j) per batch, from the goals' points.

        ``points`` ``[K, B, d + 3]`` are the goals' :meth:`points` (made by this object); a metric
        without a graph also needs the goals ``[K, B, d]`` themselves. ``stats``, if given, gets
        ``"rescored"``: the number of goals the shortlist did not prove. ``inf`` where a goal has no
        finite distance to any other (or B = 1).

        What it builds, per batch: (1) the goals sorted along the sort axis, each goal equal to the
        one before it (a *repeat*) grouped behind the first of its run (its *head*), so that only
        heads are searched; (2) for each head, the metric distance to its shortlist (its
        ``neighbours`` straight-line nearest heads in its block window, :class:`Shortlist`) and a
        lower bound in metres on the straight-line distance to every head outside it; (3) each head
        with its repeats (0 apart for any metric, ``inf`` off a graph); (4) the exact distance for
        every head the bound does not prove; (5) the result in the batch's order.

        Why it is exact: the metric is never shorter than the straight line between the points (for
        a graph, between the goals' vertices, up to its table's rounding, which the tolerance
        covers). A goal outside the shortlist is at least the bound away; where the shortlist's best
        metric distance is within the bound, nothing outside can beat it. For the others (beside an
        obstacle, or in a sparse stretch), step 4 reads the metric for every goal nearer in a
        straight line than the best distance found, so the answer is the same minimum of the same
        metric reads as all pairs, bit for bit. A metric shorter than the straight line makes the
        shortlist approximate; ``neighbours=None`` reads all pairs.
        """
        k, b = points.shape[:2]
        if b < 2:
            return torch.full((k, b), math.inf)
        if not self._snap and goals is None:
            raise ValueError("NearestNeighbours.from_points: a metric without a graph needs the goals [K, B, d]")
        m = self.neighbours
        if m is None or m >= b - 1:
            return self._all_pairs(points, goals, stats)
        if self._snap:
            self._setup_graph()
        batch = _search_order(points, goals, self._axis, self._snap, self.block)  # 1. repeats behind heads
        pair = self._pairs(batch.vertex, batch.goals)
        nearest, bound = self._search(batch, m, pair)  # 2. [K, h] each: the heads' shortlists and bounds
        kk, ii = batch.repeat.nonzero(as_tuple=True)  # 3. each repeat with its head
        twin = None  # each repeat with its head: as far as the head is from itself
        if len(kk):
            twin = self._twins(batch, kk, ii, pair)
            flat = nearest.reshape(-1).scatter_reduce(0, kk * batch.h + batch.head[kk, ii], twin, reduce="amin")
            nearest = flat.view(k, batch.h)  # a head with repeats is that far from them
        # 4. Proven where the shortlist beats every goal outside it (a distance of 0, a duplicate goal,
        # always does). For the others, only goals nearer in a straight line than the best distance
        # so far can be nearer: read those (usually a handful) from the metric too.
        excluded = batch.repeat[:, : batch.h]
        unproven = (nearest > bound) & ~excluded
        if self._snap:
            unproven &= batch.vertex[:, : batch.h] >= 0  # an off-graph goal is inf from everything
        if stats is not None:
            stats["rescored"] = int(unproven.sum())
        if bool(unproven.any()):
            h = batch.h
            nearest = _rescore(batch.points[:, :h], excluded, batch.axis[:, :h], unproven, nearest, pair,
                               self._tolerance())
        if twin is not None:  # 5. a repeat: its head's nearest other goal, or the head itself
            nearest = torch.cat([nearest, nearest.new_full((k, b - batch.h), math.inf)], 1)
            nearest = nearest.index_put((kk, ii), torch.minimum(twin, nearest[kk, batch.head[kk, ii]]))
        return torch.empty_like(nearest).scatter_(1, batch.order, nearest)

    def _all_pairs(self, points: torch.Tensor, goals: torch.Tensor | None, stats: dict | None) -> torch.Tensor:
        """:meth:`from_points` from all K·B² metric distances (``neighbours=None``, or few goals)."""
        k, b = points.shape[:2]
        if stats is not None:
            stats["rescored"] = 0
        distance = self._pairs(points[..., -1].long(), goals)(
            torch.arange(b).view(1, b, 1), torch.arange(b).view(1, 1, b), torch.arange(k).view(k, 1, 1)
        ).clone()
        distance.diagonal(dim1=-2, dim2=-1).fill_(math.inf)
        return distance.min(-1).values

    def _search(self, batch: _Sorted, m: int, pair) -> tuple[torch.Tensor, torch.Tensor]:
        """Step 2 of :meth:`from_points`: each searched goal's best metric distance ``[K, h]`` over its
        shortlist, and the lower bound ``[K, h]`` on the straight-line distance to every goal outside it."""
        h, vertex, goals = batch.h, batch.vertex, batch.goals
        k = vertex.shape[0]
        searched, excluded = batch.points[:, :h], batch.repeat[:, :h]
        if h - 1 <= m:  # a few heads: all their pairs
            distance = pair(torch.arange(h).view(1, h, 1), torch.arange(h).view(1, 1, h), torch.arange(k).view(k, 1, 1))
            distance = distance.masked_fill(excluded.unsqueeze(1) | torch.eye(h, dtype=torch.bool), math.inf)
            return distance.amin(-1), torch.full((k, h), math.inf)
        # |p_i − p_j| ≤ 2·max|p|. For a graph max|p| is the parking distance; otherwise it is read from the points.
        reach = self._reach if self._snap else float(searched[..., -3].amax()) ** 0.5
        # sorted positions [K, h, m] (-1: no candidate), lower bound [K, h] on the distance to the rest
        cols, bound = self._shortlist(searched, m, excluded, batch.axis[:, :h], reach, self._tolerance())
        found = cols >= 0
        cols = cols.clamp(min=0)
        if self._snap:  # the same lookup as pair(rows, cols, batch), with fewer index operations
            candidates = vertex.gather(1, cols.reshape(k, h * m)).view(k, h, m)
            nearest = self._lookup(vertex[:, :h].unsqueeze(-1), candidates)  # [K, h, m]
        else:
            goals_h = goals[:, :h]
            others = _take_rows(goals_h, cols.reshape(k, h * m))
            nearest = check_distances(self.metric.distance(goals_h.unsqueeze(2), others.view(k, h, m, -1)),
                                      "diversity metric", (k, h, m))
        return nearest.masked_fill(~found, math.inf).amin(-1), bound  # [K, h]

    def _twins(self, batch: _Sorted, kk: torch.Tensor, ii: torch.Tensor, pair) -> torch.Tensor:
        """Step 3 of :meth:`from_points`: the metric distance of each repeat ``(kk, ii)`` to its head."""
        if batch.reordered:  # fewer reads: each head with itself, once
            positions = torch.arange(batch.h).expand(len(batch.order), batch.h)
            return pair(positions, positions, torch.arange(len(batch.order)).view(-1, 1))[kk, batch.head[kk, ii]]
        return pair(ii, batch.head[kk, ii], kk)

    def _pairs(self, vertex: torch.Tensor, goals: torch.Tensor | None):
        """``pair(rows, cols, batch)``: metric distance of goal ``rows`` to goals ``cols`` (indices within
        candidate ``batch``), broadcasting; from the goals' vertex indices ``[K, B]`` for a graph."""
        b = vertex.shape[1]
        if self._snap:
            flat = vertex.reshape(-1)

            def pair(rows: torch.Tensor, cols: torch.Tensor, batch: torch.Tensor) -> torch.Tensor:
                return self._lookup(flat[batch * b + rows], flat[batch * b + cols])
        else:
            metric = self.metric

            def pair(rows: torch.Tensor, cols: torch.Tensor, batch: torch.Tensor) -> torch.Tensor:
                shape = (rows.shape if rows.shape == cols.shape == batch.shape
                         else torch.broadcast_shapes(rows.shape, cols.shape, batch.shape))
                return check_distances(metric.distance(goals[batch, rows], goals[batch, cols]),
                                       "diversity metric", shape)

        return pair

    def _lookup(self, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
        """Graph distance between vertex indices (the graph's unchecked lookup where it has one)."""
        return self._graph.pair_distance(i, j)  # unchecked: the indices come from the graph

    def _tolerance(self) -> float:
        """Metres the straight-line bounds are lowered by. For a graph 1 mm plus half its table's
        resolution (its distances are rounded to it); otherwise float32 rounding of the goals'
        coordinates (relative error ~6e-8) with a wide margin: 1e-5 per metre of the largest
        coordinate seen (at least 1 m). The squared-distance levels carry their own slack."""
        if self._snap:
            return _GRAPH_TOLERANCE + 0.5 * float(self._graph.resolution)
        return _RELATIVE_TOLERANCE * max(1.0, self._scale)



@dataclass
class _Sorted:
    """K batches of B goals in search order (:func:`_search_order`): sorted along the axis, and
    with many repeats, heads first. Each ``[K, B]`` unless said."""

    order: torch.Tensor  # search position -> the goal's position in its batch
    points: torch.Tensor  # [K, B, d + 3], in search order
    goals: torch.Tensor | None  # [K, B, d] in search order (a metric without a graph), or None
    vertex: torch.Tensor  # vertex index (-1 off the graph; 0 for other metrics)
    repeat: torch.Tensor  # bool: a repeat (equal to the goal before it; reordered: beyond the heads)
    head: torch.Tensor  # search position of each goal's head
    axis: torch.Tensor  # sort-axis coordinate (inf for repeats moved beyond the heads)
    h: int  # positions searched: all B, or the heads rounded up to a block
    reordered: bool  # heads first


def _search_order(points: torch.Tensor, goals: torch.Tensor | None, sort_axis: int, snap: bool, block: int) -> _Sorted:
    """Step 1 of :meth:`NearestNeighbours.from_points`: the batches sorted along coordinate ``sort_axis``,
    repeats grouped behind their heads (equal goals, or equal vertices for a graph: ``snap``); with many
    repeats the heads come first, rounded up to a multiple of ``block``."""
    k, b = points.shape[:2]
    ident = points.shape[-1] - 1  # column of the vertex index
    # Sorted along the axis, neighbours in space are mostly neighbours in the order; equal goals
    # (an object at rest repeats its position; for a graph: goals at one vertex) end up side by side.
    if snap:  # goals at one vertex side by side (many vertices share a coordinate)
        order = _sort_order(points[..., sort_axis], points[..., ident])
    else:  # equal goals have equal coordinates: a plain sort puts them side by side, but for ties on the axis
        axis = points[..., sort_axis]
        order = torch.from_numpy(np.argsort(axis.numpy(), -1))  # faster than torch's here
        dim = points.shape[-1] - 3
        tied = axis.gather(1, order).diff(dim=1) == 0
        if dim > 1 and bool(tied.any()):  # ties between goals that differ (an object at rest jitters):
            # broken by the next coordinate, so that equal goals are side by side and found as repeats
            # (ties between equal goals alone, e.g. a row drawn twice, are side by side already)
            second = points[..., (sort_axis + 1) % dim]
            if bool(tied.logical_and_(second.gather(1, order).diff(dim=1) != 0).any()):
                order = _sort_order(axis, second)
    if goals is not None and not snap:
        goals = _take_rows(goals, order)
    vertex = points[..., ident].gather(1, order).long()  # [K, B]: -1 off the graph (and 0 for other metrics)
    # A goal equal to the goal sorted before it (a *repeat*) is as far from every goal as the first
    # goal of its run (its *head*): only heads are searched (a run would fill shortlists with ties
    # and windows with goals at one spot), and a repeat's pair with its head is read (0 for any
    # metric, inf off a graph).
    repeat = torch.zeros(k, b, dtype=torch.bool)
    if snap:  # the same vertex (or both off the graph): the same distances
        repeat[:, 1:] = vertex[:, 1:] == vertex[:, :-1]
    else:  # the same goal, bit for bit (points are rounded relative positions)
        repeat[:, 1:] = (goals[:, 1:] == goals[:, :-1]).all(-1)
    positions = torch.arange(b).expand(k, b)
    head = torch.where(repeat, 0, positions).cummax(1).values  # sorted position of each goal's head
    h, reordered = b, int(repeat.sum()) * _REPEATS_FIRST > k * b
    if reordered:  # many repeats (an object at rest): heads first (in axis order), then the repeats,
        # and the search covers the heads only (few repeats are just left out of the shortlists)
        distinct = ~repeat
        count = distinct.sum(1, keepdim=True)  # heads per batch
        # old sorted position -> new one: heads in order, then repeats in order (a stable partition)
        rank = torch.where(repeat, repeat.cumsum(1).add_(count - 1), distinct.cumsum(1).sub_(1))
        first = torch.empty_like(rank).scatter_(1, rank, positions)  # new position -> old one
        order = order.gather(1, first)
        if goals is not None and not snap:
            goals = _take_rows(goals, first)
        vertex = vertex.gather(1, first)
        head = rank.gather(1, head.gather(1, first))
        heads = int(count.max())
        repeat = positions >= count
        h = min(b, -(-heads // block) * block)  # rounded up: few distinct block layouts
    points = _take_rows(points, order)  # in the order, once
    axis = points[..., sort_axis]
    if reordered:  # the repeats after the heads count as beyond every head
        axis = axis.masked_fill(repeat, math.inf)
    return _Sorted(order, points, goals, vertex, repeat, head, axis, h, reordered)


def _rescore(
    points: torch.Tensor, repeat: torch.Tensor, axis: torch.Tensor, unproven: torch.Tensor, nearest: torch.Tensor,
    pair, tolerance: float,
) -> torch.Tensor:
    """Step 4 of :meth:`NearestNeighbours.from_points`: ``nearest`` [K, B], its unproven goals' entries
    made exact. Each is read against every goal nearer in a straight line than its best distance so far
    (less ``tolerance``), except ``repeat`` ones (equal to the goal sorted before them, which is read instead).

    Only goals within that distance (plus the tolerance) along the sort axis can be nearer, and
    ``axis`` is sorted, so each unproven goal's candidates are one run of sorted positions, its
    *slab*, as long as it needs to be: a jittering cluster (an object at rest) gives a slab of
    its few members, a goal beside an obstacle one as wide as its graph distance, and no goal
    outside the slab is ever left to a second pass."""
    k, b = unproven.shape
    kk, ii = unproven.nonzero(as_tuple=True)  # [U]
    dim = points.shape[-1] - 3
    best = nearest[kk, ii]
    # The slab: |x_j - x_i| <= best + 2·tol, a superset of the pairs read below (|p - q| < best + tol)
    # that float32 rounding of x ± radius cannot cut into. Its ends are counts of the sorted row's goals
    # at or below x - radius and x + radius (a goal at exactly x - radius is too far to be read).
    x, radius = axis[kk, ii].unsqueeze(1), (best + 2 * tolerance).unsqueeze(1)
    row = axis.index_select(0, kk)  # [U, B]
    first_col = (row <= x - radius).sum(1)
    counts = (row <= x + radius).sum(1) - first_col  # >= 1: the goal itself
    goal = kk * b + ii  # [U] flat index of each unproven goal
    owner = torch.repeat_interleave(counts)  # [C]: the unproven goal of each candidate pair
    # flat index of each candidate: its slab's first one, plus its place in the slab
    other = torch.arange(len(owner)).add_((kk * b + first_col - counts.cumsum(0) + counts).index_select(0, owner))
    coords = points[..., :dim].reshape(k * b, dim).t().contiguous()  # [d, K·B]
    squared = None  # [C]: straight line, squared
    for plane in coords:
        term = plane.index_select(0, other).sub_(plane.index_select(0, goal).index_select(0, owner)).square_()
        squared = term if squared is None else squared.add_(term)
    itself = other == goal.index_select(0, owner)
    squared.masked_fill_(itself.logical_or_(repeat.reshape(-1).index_select(0, other)), math.inf)
    batch, cols = other.div(b, rounding_mode="floor"), other.remainder(b)
    rows = ii.index_select(0, owner)
    # First the straight-line nearest goal of each: for a metric close to the straight line its
    # distance is (almost) the answer and leaves few goals to read below.
    low = squared.new_full((len(goal),), math.inf).scatter_reduce_(0, owner, squared, reduce="amin")
    first = (squared == low.index_select(0, owner)).logical_and_(squared.isfinite())
    read = first.nonzero().view(-1)
    if len(read):
        best = best.scatter_reduce(0, owner[read], pair(rows[read], cols[read], batch[read]), reduce="amin")
    # then every goal nearer in a straight line, less the tolerance, than the best: |p - q| - tol < best
    read = (squared < best.add(tolerance).square_().index_select(0, owner)).logical_and_(~first).nonzero().view(-1)
    if len(read):
        best = best.scatter_reduce(0, owner[read], pair(rows[read], cols[read], batch[read]), reduce="amin")
    return nearest.index_put((kk, ii), best)


def _take_rows(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``x[k, index[k, n]]`` for ``x`` ``[K, B, c]`` and ``index`` ``[K, N]``: ``[K, N, c]``, as
    ``x.gather(1, index[..., None].expand(K, N, c))`` gives it, by one ``index_select`` of whole rows (faster here)."""
    k, b, c = x.shape
    flat = index + torch.arange(0, k * b, b).unsqueeze(1)
    return x.reshape(k * b, c).index_select(0, flat.view(-1)).view(k, index.shape[1], c)


def _sort_order(primary: torch.Tensor, secondary: torch.Tensor) -> torch.Tensor:
    """Indices ``[K, B]`` that sort each row by the float32 ``primary``, ties by ``secondary`` (float32):
    one argsort of int64 keys (the floats' bits made monotone), ~10x faster than ``np.lexsort`` here."""
    def monotone(x: torch.Tensor) -> np.ndarray:  # int32 bits that order as the floats do (-0.0 just below 0.0)
        bits = x.contiguous().numpy().view(np.int32)
        return np.where(bits >= 0, bits, bits ^ np.int32(0x7FFFFFFF)).astype(np.int64)

    keys = (monotone(primary) << 32) | (monotone(secondary) & 0xFFFFFFFF)
    return torch.from_numpy(np.argsort(keys, -1))
