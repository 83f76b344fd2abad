"""Exact nearest-neighbour metric distances within batches of goals (F_div of eq. 19), via a Euclidean shortlist.

The engine behind :class:`~gchgg.samplers.GraphCurriculumSampler`'s diversity term, apart from the
sampler: :class:`NearestNeighbours` (reusable, with its scratch memory) and
:func:`nearest_neighbour_distances` (one-off). ``tests/test_samplers.py`` checks it against a
brute-force all-pairs minimum.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from gchgg.common.validation import check_number

__all__ = [
    "POINT_SIZE", "NearestNeighbours", "check_distances", "check_goals", "nearest_neighbour_distances", "point_size",
]

POINT_SIZE = 6  # values per shortlist point of a 3-D goal: (x, y, z, |p|², 1, id); d + 3 for d-D goals
_GRAPH_TOLERANCE = 1e-3  # metres: slack on a graph's straight-line bounds, besides half its table's resolution
_RELATIVE_TOLERANCE = 1e-5  # slack on straight-line bounds between goals, per metre of their coordinates (>= 1 m)
_LEVEL_SLACK = 2  # levels added to every squared distance so float32 rounding never makes one negative
_INT32_MAX = 2**31 - 1
_MIN_STRIDE = 128  # the levels of narrower windows are those of a 128-wide one (see _levels)
_REPEATS_FIRST = 8  # goals are reordered heads first when more than 1 in this many repeat another
_SWAP = torch.tensor([0, 1, 2, 4, 3])  # point columns (x, y, z, |p|², 1) -> (x, y, z, 1, |p|²), 3-D goals


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

    Per batch of B goals: the goals are sorted along the field's longest axis and cut into blocks
    of ``block`` consecutive goals; each block is compared with itself and its two neighbouring
    blocks (a window of ``3 · block`` goals; all B goals when B ≤ 3 · block). One batched matrix
    product ``[p, |p|², 1] · [-2p, 1, |p|² + 2q]ᵀ / q`` gives the window's squared distances in
    levels of q = (2·max|p|)² / levels (the +2 keeps float32 rounding above 0); they are truncated
    to int32 in place with the window column packed below (``key = level · W + column``), so
    ``neighbours + 1`` value-only ``amin`` passes give each goal its ``neighbours`` nearest goals in
    the window and the level of the next one (faster than ``topk`` here). Only those pairs are read
    from the metric. A goal outside the shortlist is at least ``min(next level, gap)`` away, where
    the gap is the distance along the sort axis to the nearest goal outside the window; where the
    shortlist's best metric distance is within that bound it is the exact nearest neighbour (for
    any metric never shorter than the straight line), and for the few other goals the metric is
    also read for every goal whose straight-line distance is below the best distance found.

    Cost for K batches: K·B·3·block·5 multiply-adds and about ten passes over K·B·3·block int32
    keys (786 KB for K = 8, B = 256, block = 32: in the core's L2 cache, where all K·B² keys
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
        self.span = span
        if neighbours == "auto":
            neighbours = 3 if metric.lattice is not None else 1
        elif neighbours is not None:
            check_number('neighbours (or None: all pairs, or "auto")', neighbours, integer=True, low=1)
        self.metric = metric
        self.neighbours = neighbours
        self.block = block
        self._graph = metric.lattice  # the graph's vertex view (snap, table lookups), or None: goals as they are
        self._snap = self._graph is not None
        self._origin: torch.Tensor | None = None
        self._axis = 0  # the coordinate goals are sorted by: the field's longest (graph) or widest-spread one
        self._lattice: torch.Tensor | None = None  # graph vertices relative to the origin
        self._park: torch.Tensor | None = None  # where off-graph goals are put
        self._reach = 0.0  # graph: the largest |p| of any point (the parking distance)
        self._scale = 0.0  # no graph: the largest absolute coordinate of any goal made a point
        self._dim: int | None = None if self._graph is None else len(self._graph.field[0])  # goal dimension d
        self._scratch: dict[Any, Any] = {}

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
        """Nearest-neighbour distances ``[K, B]`` from the goals' :meth:`points` ``[K, B, d + 3]`` (made by
        this object). A metric without a graph also needs the goals ``[K, B, d]`` themselves."""
        k, b = points.shape[:2]
        ident = points.shape[-1] - 1  # column of the vertex index
        if b < 2:
            return torch.full((k, b), math.inf)
        if not self._snap and goals is None:
            raise ValueError("NearestNeighbours.from_points: a metric without a graph needs the goals [K, B, d]")
        m = self.neighbours
        if m is None or m >= b - 1:  # all pairs
            if stats is not None:
                stats["rescored"] = 0
            distance = self._pairs(points[..., ident].long(), goals)(
                torch.arange(b).view(1, b, 1), torch.arange(b).view(1, 1, b), torch.arange(k).view(k, 1, 1)
            ).clone()
            distance.diagonal(dim1=-2, dim2=-1).fill_(math.inf)
            return distance.min(-1).values

        if self._snap:
            self._setup_graph()
        # Sorted along the axis, neighbours in space are mostly neighbours in the order; equal goals
        # (an object at rest repeats its position; for a graph: goals at one vertex) end up side by side.
        if self._snap:  # goals at one vertex side by side (many vertices share a coordinate)
            order = _sort_order(points[..., self._axis], points[..., ident])
        else:  # equal goals have equal coordinates: a plain sort puts them side by side, but for ties on the axis
            axis = points[..., self._axis]
            order = torch.from_numpy(np.argsort(axis.numpy(), -1))  # faster than torch's here
            dim = points.shape[-1] - 3
            tied = axis.gather(1, order).diff(dim=1) == 0
            if dim > 1 and bool(tied.any()):  # ties between goals that differ (an object at rest jitters):
                # broken by the next coordinate, so that equal goals are side by side and found as repeats
                # (ties between equal goals alone, e.g. a row drawn twice, are side by side already)
                second = points[..., (self._axis + 1) % dim]
                if bool(tied.logical_and_(second.gather(1, order).diff(dim=1) != 0).any()):
                    order = _sort_order(axis, second)
        if goals is not None and not self._snap:
            goals = _take_rows(goals, order)
        vertex = points[..., ident].gather(1, order).long()  # [K, B]: -1 off the graph (and 0 for other metrics)
        # A goal equal to the goal sorted before it (a *repeat*) is as far from every goal as the first
        # goal of its run (its *head*): only heads are searched (a run would fill shortlists with ties
        # and windows with goals at one spot), and a repeat's pair with its head is read (0 for any
        # metric, inf off a graph).
        repeat = torch.zeros(k, b, dtype=torch.bool)
        if self._snap:  # the same vertex (or both off the graph): the same distances
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
            if goals is not None and not self._snap:
                goals = _take_rows(goals, first)
            vertex = vertex.gather(1, first)
            head = rank.gather(1, head.gather(1, first))
            heads = int(count.max())
            repeat = positions >= count
            h = min(b, -(-heads // self.block) * self.block)  # rounded up: few distinct block layouts
        points = _take_rows(points, order)  # in the order, once
        axis = points[..., self._axis]
        if reordered:  # the repeats after the heads count as beyond every head
            axis = axis.masked_fill(repeat, math.inf)
        pair = self._pairs(vertex, goals)
        searched, excluded, axis_h = points[:, :h], repeat[:, :h], axis[:, :h]
        if h - 1 <= m:  # a few heads: all their pairs
            distance = pair(torch.arange(h).view(1, h, 1), torch.arange(h).view(1, 1, h), torch.arange(k).view(k, 1, 1))
            distance = distance.masked_fill(excluded.unsqueeze(1) | torch.eye(h, dtype=torch.bool), math.inf)
            nearest, bound = distance.amin(-1), torch.full((k, h), math.inf)
        else:
            # sorted positions [K, h, m] (-1: no candidate), lower bound [K, h] on the distance to the rest
            cols, bound = self._shortlist(searched, m, excluded, axis_h)
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
            nearest = nearest.masked_fill(~found, math.inf).amin(-1)  # [K, h]
        kk, ii = repeat.nonzero(as_tuple=True)
        twin = None  # each repeat with its head: as far as the head is from itself
        if len(kk) and reordered:  # fewer reads: each head with itself, once
            twin = pair(positions[:, :h], positions[:, :h], torch.arange(k).view(k, 1))[kk, head[kk, ii]]
        elif len(kk):
            twin = pair(ii, head[kk, ii], kk)
        if twin is not None:  # a head with repeats is that far from them
            flat = nearest.reshape(-1).scatter_reduce(0, kk * h + head[kk, ii], twin, reduce="amin")
            nearest = flat.view(k, h)
        # Proven where the shortlist beats every goal outside it (a distance of 0, a duplicate goal,
        # always does). For the others, only goals nearer in a straight line than the best distance
        # so far can be nearer: read those (usually a handful) from the metric too.
        unproven = (nearest > bound) & ~excluded
        if self._snap:
            unproven &= vertex[:, :h] >= 0  # an off-graph goal is inf from everything
        if stats is not None:
            stats["rescored"] = int(unproven.sum())
        if bool(unproven.any()):
            nearest = self._rescore(searched, excluded, axis_h, unproven, nearest, pair)
        if twin is not None:  # a repeat: its head's nearest other goal, or the head itself
            nearest = torch.cat([nearest, nearest.new_full((k, b - h), math.inf)], 1)
            nearest = nearest.index_put((kk, ii), torch.minimum(twin, nearest[kk, head[kk, ii]]))
        return torch.empty_like(nearest).scatter_(1, order, nearest)

    def _rescore(
        self, points: torch.Tensor, repeat: torch.Tensor, axis: torch.Tensor, unproven: torch.Tensor,
        nearest: torch.Tensor, pair,
    ) -> torch.Tensor:
        """``nearest`` [K, B] with the unproven goals' entries made exact: each is read against every goal
        nearer in a straight line than its best distance so far, except ``repeat`` ones (equal to the
        goal sorted before them, which is read instead).

        Only goals within that distance (plus the tolerance) along the sort axis can be nearer, and
        ``axis`` is sorted, so each unproven goal's candidates are one run of sorted positions, its
        *slab*, as long as it needs to be: a jittering cluster (an object at rest) gives a slab of
        its few members, a goal beside an obstacle one as wide as its graph distance, and no goal
        outside the slab is ever left to a second pass."""
        k, b = unproven.shape
        kk, ii = unproven.nonzero(as_tuple=True)  # [U]
        dim, tolerance = points.shape[-1] - 3, self._tolerance()
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

    def _shortlist(
        self, points: torch.Tensor, m: int, repeat: torch.Tensor, axis: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """For points sorted along the axis ``[K, B, d + 3]``: each one's m nearest others in its window
        that are not ``repeat`` ones (``[K, B]``, equal to the goal sorted before them), as sorted
        positions ``[K, B, m]`` (-1 where the window has fewer candidates), and a lower bound in metres
        ``[K, B]`` on its straight-line distance to every other non-repeat goal (outside the window:
        the gap along the axis)."""
        k, b, size_of_point = points.shape
        dim = size_of_point - 3  # goal dimension d; columns (p, |p|², 1, id)
        layout = self._layout(b, m)
        size, pad, blocks, width, stride = (layout[key] for key in ("size", "pad", "blocks", "width", "stride"))
        levels = _levels(stride)
        # |p_i − p_j| ≤ 2·max|p|: no pair is above the top level, so no clamp is needed. For a graph
        # max|p| is the parking distance; otherwise it is read from the points.
        reach = self._reach if self._snap else float(points[..., dim].amax()) ** 0.5
        quantum = max(4.0 * reach * reach, 1e-12) / levels
        left = points[..., : dim + 2]  # [p, |p|², 1]
        rows = blocks * size
        if rows != b:  # padding rows (zeros, masked below) after the sorted goals
            padded = left.new_zeros(k, rows, dim + 2)
            padded[:, :b] = left
        else:
            padded = left
        own = padded.reshape(k * blocks, size, dim + 2)
        # The right operand with its columns as rows, [K, d + 2, pad + rows + pad]: [p, |p|², 1] ->
        # [-2p, 1, |p|² + slack·q] / q for each goal, [0, 0, slack] for padding. In this layout the map and
        # the windows' copy below run along rows of goals, not along rows of d + 2 values.
        scale, shift, swap = self._product_map(quantum, dim)  # [d + 2, 1] each
        right = self._buffer("right", (k, dim + 2, rows + 2 * pad), torch.float32)
        right[..., :pad] = shift
        right[..., pad + b :] = shift
        torch.addcmul(shift, left.transpose(1, 2).index_select(1, swap), scale, out=right[..., pad : pad + b])
        windows = right.unfold(2, width, size).transpose(1, 2).reshape(k * blocks, dim + 2, width)
        squared = self._buffer("squared", (k * blocks, size, width), torch.float32)
        torch.bmm(own, windows, out=squared)  # squared distance in levels, + _LEVEL_SLACK
        # In place (same 4-byte slots, element by element: one scratch matrix, half the cache footprint).
        keys = squared.view(torch.int32)
        keys.copy_(squared)  # truncation: level + slack - 1 <= key level <= level + slack (float32 rounding < 1 level)
        # key = level · S + column (S: a power of two >= W), above every pair's key for the goal itself
        # and padding columns.
        blocked = keys.view(k, blocks, size, width)
        torch.add(layout["offset"], blocked, alpha=stride, out=blocked)
        excluded = layout["excluded"]  # the key of an excluded column: above every pair's
        if bool(repeat.any()):  # repeat columns are excluded too
            flags = repeat.new_zeros(k, rows + 2 * pad)
            flags[:, pad : pad + b] = repeat
            bump = flags.unfold(1, width, size).unsqueeze(2) * excluded  # [K, blocks, 1, W]: 0 or the excluded key
            torch.maximum(blocked, bump, out=blocked)  # an excluded key keeps its column bits
        flat, mask = keys.view(-1), stride - 1
        starts = self._row_starts(k * blocks * size, width).view(k * blocks, size, 1)  # flat index of each row
        nearest = []
        for _ in range(m):
            low = keys.amin(-1, keepdim=True)  # [K·blocks, size, 1]
            nearest.append(low)
            flat.index_fill_(0, torch.add(starts, low.bitwise_and(mask)).view(-1), _INT32_MAX)
        low = torch.cat(nearest, -1)
        cols = low.bitwise_and(mask).long().view(k, rows, m)
        cols = cols[:, :b].add_(layout["first"])  # window column -> sorted position
        cols.masked_fill_(low.view(k, rows, m)[:, :b] >= excluded[0], -1)  # the window ran out of candidates
        bound = _distance(keys.amin(-1).view(k, rows)[:, :b].bitwise_right_shift_(stride.bit_length() - 1), quantum)
        # Goals outside the window are at least the gap along the axis away (``axis``: +inf for repeats).
        ends = torch.cat([axis.new_full((k, 1), -math.inf), axis, axis.new_full((k, 1), math.inf)], 1)
        gap = torch.minimum(axis - ends[:, layout["before"]], ends[:, layout["after"]] - axis).masked_fill_(repeat, 0.0)
        return cols, torch.minimum(bound, gap).sub_(self._tolerance()).clamp_(min=0.0)

    def _layout(self, b: int, m: int) -> dict[str, Any]:
        """Block geometry for B goals, kept per (B, m): block size, padding, number of blocks, window
        width, the keys' column numbers, the mask of excluded keys (a goal itself, padding), each
        sorted position's first window position, and its nearest goals outside the window (indices
        into the axis values with -inf / +inf put at both ends)."""
        cached = self._scratch.get(("layout", b, m))
        if cached is not None:
            return cached
        size, span = self.block, self.span
        if b > (2 * span + 1) * size and size > m:
            pad, blocks, width = span * size, -(-b // size), (2 * span + 1) * size
        else:  # one window holds every goal
            size, pad, blocks, width = b, 0, 1, b
        block = torch.arange(blocks).view(blocks, 1, 1)
        row = torch.arange(size).view(1, size, 1)
        column = torch.arange(width).view(1, 1, width)
        padded = block * size + column  # padded position of each window column
        excluded = (padded < pad) | (padded >= pad + b) | (column == row + pad)
        # Keys are level · S + offset. A pair's level is at most levels + slack, so its key is below
        # (levels + slack + 1) · S; excluded entries (level <= slack + 1: the goal itself, padding) get
        # (levels + 2·slack + 2) · S more, which keeps them above every pair and below int32 max.
        stride = 1 << (width - 1).bit_length()
        exclusion = (_levels(stride) + 2 * _LEVEL_SLACK + 2) * stride
        offset = column.expand(blocks, size, width) + excluded * exclusion
        position = torch.arange(b)
        start = (position // size) * size - pad  # sorted position of the window's first column
        if pad:
            before = (start - 1).clamp(min=-1) + 1
            after = torch.where(start + width < b, start + width + 1, b + 1)
        else:
            before, after = torch.zeros(b, dtype=torch.long), torch.full((b,), b + 1)
        layout = self._scratch[("layout", b, m)] = {
            "size": size,
            "pad": pad,
            "blocks": blocks,
            "width": width,
            "stride": stride,
            "offset": offset.to(torch.int32).contiguous(),
            "excluded": (exclusion + column.view(width)).to(torch.int32),  # an excluded column's key
            "first": start.view(1, b, 1),
            "before": before,
            "after": after,
        }
        return layout

    def _row_starts(self, rows: int, width: int) -> torch.Tensor:
        """Flat index of the first key of each of ``rows`` rows of ``width`` keys (kept per shape)."""
        cached = self._scratch.get(("starts", rows, width))
        if cached is None:
            cached = self._scratch[("starts", rows, width)] = torch.arange(0, rows * width, width)
        return cached

    def _product_map(self, quantum: float, dim: int = 3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``scale, shift, swap`` with ``[p, |p|², 1][swap] · scale + shift = [-2p, 1, |p|² + slack·q] / q``
        for ``dim``-D points, ``scale`` and ``shift`` as columns ``[d + 2, 1]`` (kept per quantum and dimension)."""
        cached = self._scratch.get("map")
        if cached is None or cached[0] != (quantum, dim):
            scale = (torch.tensor([-2.0] * dim + [1.0, 1.0]) / quantum).unsqueeze(-1)
            shift = torch.tensor([0.0] * (dim + 1) + [float(_LEVEL_SLACK)]).unsqueeze(-1)
            swap = _SWAP if dim == 3 else torch.tensor([*range(dim), dim + 1, dim])
            cached = self._scratch["map"] = ((quantum, dim), (scale, shift, swap))
        return cached[1]

    def _buffer(self, name: str, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        buffer = self._scratch.get(name)
        if buffer is None or buffer.shape != shape:
            buffer = self._scratch[name] = torch.empty(shape, dtype=dtype)
        return buffer


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


def _levels(stride: int) -> int:
    """Squared-distance levels for keys ``level · stride + column`` (room is left for excluded entries).

    At most ~2**24 (what a stride of 128 gives): a float32 product holds levels exactly only up to
    there, and beyond it the rounding of a goal's distance to itself could exceed the room left for
    excluded entries (narrow windows, stride < 128, would otherwise get up to 2**28 levels)."""
    return _INT32_MAX // max(stride, _MIN_STRIDE) - 4 * _LEVEL_SLACK - 4


def _distance(level: torch.Tensor, quantum: float) -> torch.Tensor:
    """A lower bound in metres on the distance of a pair whose key has this level: the level less the
    slack and one more for float32 rounding (at least 0), times the quantum, square-rooted."""
    return (level - (_LEVEL_SLACK + 1)).clamp_(min=0).float().mul_(quantum).sqrt_()


def check_distances(distance: torch.Tensor, name: str, shape: torch.Size | tuple | None = None) -> torch.Tensor:
    """``distance`` as a float32 tensor (a metric returning another dtype, e.g. float64, is cast); a
    ``ValueError`` naming the metric if it holds NaN or, when ``shape`` is given, has another shape."""
    distance = torch.as_tensor(distance)
    if shape is not None and distance.shape != torch.Size(shape):
        raise ValueError(
            f"the {name} must return one distance per pair of goals, shape {tuple(shape)} here "
            f"(goals [..., d] -> [...]), got shape {tuple(distance.shape)}"
        )
    if distance.dtype != torch.float32:
        distance = distance.to(torch.float32)
    if bool(torch.isnan(distance).any()):
        raise ValueError(f"the {name} returned NaN distances; goals must be finite")
    return distance
