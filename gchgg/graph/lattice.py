"""The obstacle-aware lattice graph :class:`GoalGraph`: goals to vertices (eq. 14) and d_G from its table (eq. 13).

A :class:`GoalGraph` lays an orthorhombic lattice over a box-shaped goal-space field (eqs. 9–10; a
3-D box, or a 2-D rectangle for a planar goal space), removes the vertices inside every obstacle
inflated by a safety margin ε (Sec. IV-B), joins each remaining vertex to its 26 neighbours (8 in
2-D) with edges weighted by their length (eqs. 11–12: :mod:`gchgg.graph.grid`) and holds all
pairwise shortest-path distances in a compact table, cached on disk (:mod:`gchgg.graph.table`).
:meth:`GoalGraph.distance` maps goals to vertices (eq. 14) and reads the table (eq. 13) with
vectorised torch ops; it is ``inf`` where a goal lies outside the field or on a removed vertex.
:class:`EuclideanMetric` offers the same ``distance(a, b)``, so every algorithm switches metric by
configuration.

Decisions where the paper is silent (``docs/graph.md`` repeats them; the obstacles' and the density
criterion's are in :mod:`gchgg.graph.grid`, the table's and the cache's in :mod:`gchgg.graph.table`):

* **Goal → vertex (eq. 14).** The paper writes ⌊·⌋ but defines it as rounding to the closest
  integer, and the original code rounds: the default ``snap="nearest"`` maps a goal to its nearest
  lattice vertex; ``snap="floor"`` is the literal floor (the vertex below-left of the goal).
* **Boundary.** A goal up to 0.01 mm outside the field (or below a lattice plane, for ``"floor"``)
  counts as on it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Literal

import numpy as np
import torch
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from gchgg.graph.grid import (
    DEFAULT_MARGIN,
    DEFAULT_N,
    check_density_criterion,
    checked_settings,
    edges,
    free_vertices,
    inflate,
)
from gchgg.graph.table import (
    UNREACHABLE,
    USER_CACHE_DIR,
    _UserCacheDir,
    build_table,
    cache_file,
    check_size,
    default_cache_dir,
    load_or_build,
    row_offsets,
)

__all__ = ["DEFAULT_MARGIN", "DEFAULT_N", "USER_CACHE_DIR", "GoalGraph", "check_density_criterion", "default_cache_dir"]

_BOUNDARY_TOLERANCE = 1e-5  # metres: goals this close outside the field (or below a plane) are on it


class GoalGraph:
    """Obstacle-aware lattice graph over a box-shaped goal space, with all-pairs graph distances.

    The field is 3-D (``(x, y, z)`` goals) or 2-D (``(x, y)`` goals of a planar task: a 2-D lattice,
    8-connected; its obstacles are rectangles). The lattice has ``n[k]`` vertices along axis ``k``,
    spaced ``2·field.half[k] / (n[k] − 1)`` and spanning the field's faces (eqs. 9–10). Vertices
    inside an obstacle inflated by ``margin`` are removed; the others are joined to their (up to) 26
    (2-D: 8) neighbours by edges weighted by their
    Euclidean length (eq. 11). Shortest-path distances between every pair of free vertices come
    from Dijkstra and are kept in a 2-byte-per-pair table (:mod:`gchgg.graph.table`), cached on
    disk. ``distance(a, b)`` is eq. 13: the table entry of the vertices of ``a`` and ``b`` (eq. 14),
    ``inf`` if either goal is outside the field, on a removed vertex, or out of reach. Everything
    works on CPU tensors.

    Args:
        field: the goal-space box ``(center, half)``, each ``(x, y, z)`` in metres, e.g.
            ``envs.geometry("push_new").field``, or ``(x, y)`` for a planar goal space; every
            half-size must be positive.
        obstacles: obstacle boxes ``(center, half)`` in metres, un-inflated, of the field's dimension.
        n: vertices per axis ``(n_x, n_y, n_z)`` (``(n_x, n_y)`` for a 2-D field), each an integer ≥ 2.
        margin: safety margin ε in metres (≥ 0) added to every obstacle half-size (Sec. IV-B).

    Keyword Args:
        snap: goal → vertex map of eq. 14: ``"nearest"`` (default, as the paper's text and the
            original code) or ``"floor"`` (the lattice vertex at or below the goal on every axis).
        cache_dir: folder of the distance-table cache; by default :func:`default_cache_dir`;
            ``None`` builds the table in memory without touching the disk.

    Raises:
        ValueError: bad ``field``, ``obstacles``, ``n``, ``margin`` or ``snap``; the density
            criterion (eq. 12) is violated (the message names the obstacle and the spacing that
            would be allowed); every vertex is removed.

    Example:
        >>> import torch
        >>> from gchgg.graph import EuclideanMetric
        >>> wall = ((-0.3, 0.0, 0.0), (0.7, 0.1, 0.2))  # x from -1.0 to 0.4: pass it at x > 0.4
        >>> graph = GoalGraph(((0.0, 0.0, 0.0), (1.0, 1.0, 0.1)), [wall], n=(21, 21, 3), margin=0.0,
        ...                   cache_dir=None)
        >>> a, b = torch.tensor([0.0, -0.5, 0.0]), torch.tensor([0.0, 0.5, 0.0])
        >>> round(graph.distance(a, b).item(), 2), round(EuclideanMetric().distance(a, b).item(), 2)
        (1.53, 1.0)
        >>> graph.distance(a, torch.tensor([0.0, 0.0, 0.0]))  # inside the wall
        tensor(inf)
        >>> graph.shortest_path(a, b).shape  # 13 vertices from a around the wall's end to b
        torch.Size([13, 3])
    """

    def __init__(
        self,
        field: tuple[Sequence[float], Sequence[float]],
        obstacles: Sequence[tuple[Sequence[float], Sequence[float]]] = (),
        n: Sequence[int] = DEFAULT_N,
        margin: float = DEFAULT_MARGIN,
        *,
        snap: Literal["nearest", "floor"] = "nearest",
        cache_dir: str | os.PathLike | None | _UserCacheDir = USER_CACHE_DIR,
    ) -> None:
        center, half, self.n, self.margin, self.obstacles = checked_settings(field, obstacles, n, margin)
        if snap not in ("nearest", "floor"):
            raise ValueError(f"snap must be 'nearest' or 'floor', got {snap!r}")
        self.field = (tuple(center.tolist()), tuple(half.tolist()))
        self.snap = snap

        self.low = center - half  # float64 [3]
        self.high = center + half
        self.spacing = 2.0 * half / (np.asarray(self.n) - 1)  # eq. 9
        # eq. 12; each inflated obstacle meeting the field as (low, high), clipped to the field
        self.inflated_obstacles = inflate(self.low, self.high, self.spacing, self.obstacles, self.margin)
        self._free = free_vertices(self.low, self.spacing, self.n, self.inflated_obstacles)  # bool [n_x, n_y, n_z]
        if not self._free.any():
            raise ValueError("every lattice vertex lies inside an inflated obstacle: the graph is empty")
        self.num_vertices = int(self._free.sum())
        check_size(self.n, self.num_vertices)
        positions = self.low + np.argwhere(self._free) * self.spacing  # C order, like the slots
        self._vertices = torch.from_numpy(positions).to(torch.float32)

        # Slot 0 is a void vertex standing for "outside the field or removed"; free vertex v (in
        # C order over the lattice) is slot v + 1. The table row of slot 0 is all unreachable, so
        # out-of-graph goals read inf without a mask. The lattice → slot map has one extra entry
        # (0) at its end, where goals outside the field are sent.
        slot = np.zeros(math.prod(self.n) + 1, dtype=np.int64)
        slot[:-1][self._free.reshape(-1)] = np.arange(1, self.num_vertices + 1)
        self._slot_of_lattice = torch.from_numpy(slot)
        # Lattice coordinates u = goal * _scale_u + _shift_u. A goal is in the field (its faces
        # widened by _BOUNDARY_TOLERANCE) where |goal * _scale_w + _shift_w| <= 1 on every axis.
        tolerance = _BOUNDARY_TOLERANCE / self.spacing
        self._scale_u = torch.from_numpy(1.0 / self.spacing)
        self._shift_u = torch.from_numpy(-self.low / self.spacing)
        reach = half + _BOUNDARY_TOLERANCE
        self._scale_w = torch.from_numpy(1.0 / reach)
        self._shift_w = torch.from_numpy(-center / reach)
        self._floor_shift = torch.from_numpy(tolerance)  # floor(u + tolerance): planes are "at or below"
        self._strides = torch.tensor([math.prod(self.n[k + 1 :]) for k in range(len(self.n))], dtype=torch.float64)
        self._row_offset = row_offsets(self.num_vertices + 1)  # table entry (r, c), r <= c: _row_offset[r] + c
        self._adjacency: csr_matrix | None = None
        self._vertex_lookup: tuple[torch.Tensor, torch.Tensor] | None = None  # see pair_distance

        # Everything that changes the table (snap does not) names its cache file.
        params = {"field": self.field, "obstacles": sorted(self.obstacles), "n": self.n, "margin": self.margin}
        self.cache_path = cache_file(cache_dir, params)
        table, self._scale, self.loaded_from_cache = load_or_build(
            self.cache_path, self.num_vertices, params, lambda: build_table(self.adjacency, self.spacing)
        )
        self._table = torch.from_numpy(table)

    # ------------------------------------------------------------------ public API

    def distance(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Graph distance d_G between goals (eq. 13).

        Args:
            a: goals ``[..., d]`` in metres (CPU), d = 3 (or 2 for a 2-D field).
            b: goals ``[..., d]``, broadcastable against ``a``.

        Returns:
            float32 ``[...]``: shortest-path length between the goals' vertices (eq. 14), ``inf`` where
            either goal is outside the field, non-finite, on a removed vertex, or cut off from the other.
        """
        return self._slot_distance(self._slots(a), self._slots(b))

    def vertex_index(self, goals: torch.Tensor) -> torch.Tensor:
        """Index of each goal's vertex (eq. 14) in :attr:`vertices`; ``-1`` if it is not in the graph.

        Callers that score many goals against many others can dedupe goals to vertices first and
        read distances with :meth:`distance_between_vertices`.

        Args:
            goals: ``[..., d]`` in metres (d: the field's dimension).

        Returns:
            int64 ``[...]`` in ``[-1, num_vertices)``: ``-1`` outside the field or on a removed vertex.
        """
        return self._slots(goals) - 1

    def distance_between_vertices(self, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
        """Table lookup for vertex indices from :meth:`vertex_index` (``-1`` gives ``inf``).

        Args:
            i: int64 vertex indices ``[...]`` in ``[-1, num_vertices)``.
            j: int64 vertex indices, broadcastable against ``i``.

        Returns:
            float32 ``[...]`` graph distances.

        Raises:
            IndexError: an index outside ``[-1, num_vertices)``.
        """
        i, j = torch.as_tensor(i), torch.as_tensor(j)
        for name, index in (("i", i), ("j", j)):
            if index.is_floating_point() or index.dtype == torch.bool:
                raise TypeError(f"vertex indices {name} must be an integer tensor, got {index.dtype}")
            if index.numel() and (index.min() < -1 or index.max() >= self.num_vertices):
                raise IndexError(
                    f"vertex indices {name} must lie in [-1, {self.num_vertices}), "
                    f"got values in [{index.min().item()}, {index.max().item()}]"
                )
        return self._slot_distance(i.long() + 1, j.long() + 1)

    @property
    def lattice(self) -> GoalGraph:
        """The graph itself: it is its own :class:`Lattice` (vertices, eq. 14, table lookups)."""
        return self

    def pair_distance(self, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
        """:meth:`distance_between_vertices` without its checks, for hot loops (samplers).

        Args:
            i: int64 vertex indices ``[...]``, which the caller guarantees lie in ``[-1, num_vertices)``
                (anything else reads a wrong entry or raises).
            j: int64 vertex indices, broadcastable against ``i``.

        Returns:
            float32 ``[...]`` graph distances, ``inf`` where either index is ``-1`` or no path exists.
        """
        if self._vertex_lookup is None:
            # Row offsets indexed by vertex (slot - 1; -1, the void slot, wraps to the last entry) with
            # the slot shift folded in, and the decoded distance of every int16 code.
            offset = self._row_offset + 1
            decoded = torch.arange(UNREACHABLE + 1, dtype=torch.float32).mul_(self._scale)
            decoded[UNREACHABLE] = math.inf
            self._vertex_lookup = (torch.cat([offset[1:], offset[:1]]), decoded)
        offset, decoded = self._vertex_lookup
        code = torch.take(self._table, torch.take(offset, torch.minimum(i, j)) + torch.maximum(i, j))
        return torch.take(decoded, code.long())

    def shortest_path(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Vertex positions along one shortest path from the vertex of goal ``a`` to that of goal ``b``.

        Args:
            a: one goal ``[d]`` in metres (d: the field's dimension).
            b: one goal ``[d]``.

        Returns:
            float32 ``[L, d]``, starting at a's vertex and ending at b's (``L = 1`` when they share a
            vertex); ``[0, d]`` when either goal is outside the graph or no path joins them.
        """
        a, b = torch.as_tensor(a), torch.as_tensor(b)
        d = len(self.n)
        if a.shape != (d,) or b.shape != (d,):
            raise ValueError(
                f"shortest_path takes two goals of shape [{d}], got {tuple(a.shape)} and {tuple(b.shape)}"
            )
        source, target = (int(s) - 1 for s in (self._slots(a), self._slots(b)))
        if source < 0 or target < 0:
            return torch.empty(0, d)
        _, predecessors = dijkstra(
            self.adjacency, directed=True, indices=source, return_predecessors=True
        )
        if source != target and predecessors[target] < 0:
            return torch.empty(0, d)
        path = [target]
        while path[-1] != source:  # walk back along the predecessor tree (at most V steps)
            path.append(int(predecessors[path[-1]]))
        return self.vertices[path[::-1]]

    @property
    def vertices(self) -> torch.Tensor:
        """Positions ``[num_vertices, d]`` (float32, metres) of the free vertices, in lattice C order."""
        return self._vertices

    @property
    def free_mask(self) -> torch.Tensor:
        """Bool ``[n_x, n_y, n_z]`` (``[n_x, n_y]`` in 2-D): which lattice vertices were kept."""
        return torch.from_numpy(self._free.copy())

    @property
    def lattice_axes(self) -> tuple[torch.Tensor, ...]:
        """Lattice coordinates along x, y and z (x and y in 2-D) (float64, metres), eq. 10."""
        return tuple(
            torch.from_numpy(self.low[k] + self.spacing[k] * np.arange(self.n[k])) for k in range(len(self.n))
        )

    @property
    def adjacency(self) -> csr_matrix:
        """Sparse ``[V, V]`` edge lengths between free vertices (both directions stored), eq. 11."""
        if self._adjacency is None:
            self._adjacency = edges(self._free, self.spacing)
        return self._adjacency

    @property
    def resolution(self) -> float:
        """Metres per table unit: entries are within ``resolution / 2`` of Dijkstra's float64 result."""
        return self._scale

    @property
    def table_bytes(self) -> int:
        """Size of the distance table in memory (and on disk, less a small header)."""
        return self._table.numel() * self._table.element_size()

    def __repr__(self) -> str:
        spacing = tuple(round(s, 5) for s in self.spacing.tolist())
        return (
            f"GoalGraph(n={self.n}, margin={self.margin}, "
            f"vertices={self.num_vertices}/{math.prod(self.n)}, spacing={spacing}, "
            f"table={self.table_bytes / 2**20:.1f} MiB)"
        )

    # ------------------------------------------------------------------ lookups

    def _slots(self, goals: torch.Tensor) -> torch.Tensor:
        """Slot of each goal's vertex (eq. 14): free vertex v is slot v + 1, 0 is "not in the graph"."""
        g = torch.as_tensor(goals)
        if g.shape[-1:] != (len(self.n),):
            raise ValueError(
                f"goals must have shape [..., {len(self.n)}] (the graph's field is {len(self.n)}-D), "
                f"got {tuple(g.shape)}"
            )
        if g.dtype not in (torch.float32, torch.float64):
            g = g.to(torch.float32)
        if g.dtype == torch.float32 and self._strides[0] * self.n[0] >= 2**24:
            g = g.to(torch.float64)  # lattice indices beyond float32's exact integers
        dtype = g.dtype
        u = torch.addcmul(self._shift_u.to(dtype), g, self._scale_u.to(dtype))  # lattice units
        w = torch.addcmul(self._shift_w.to(dtype), g, self._scale_w.to(dtype)).abs_()
        inside = w.amax(-1) <= 1.0  # a NaN propagates through amax and compares False: outside
        if self.snap == "nearest":
            u.round_()
        else:
            u.add_(self._floor_shift.to(dtype)).floor_()
        # Inside the field the rounded u lies in [0, n - 1] on every axis, so the C-order lattice
        # index is exact (integers below 2**24); outside it points at the extra entry, slot 0.
        flat = u @ self._strides.to(dtype)
        flat.masked_fill_(~inside, len(self._slot_of_lattice) - 1)
        return self._slot_of_lattice[flat.long()]

    def _slot_distance(self, s: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        # Entry (r, c), r <= c, lives at off[r] + c. (Out of place: a 0-d index gives a view.)
        index = self._row_offset[torch.minimum(s, t)] + torch.maximum(s, t)
        code = self._table[index]
        distance = code.to(torch.float32).mul_(self._scale)
        return distance.masked_fill_(code == UNREACHABLE, math.inf)
