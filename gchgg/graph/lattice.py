"""The obstacle-aware lattice graph :class:`GoalGraph` and its distance table d_G (Sec. III-C, IV-B, eqs. 8–14).

A :class:`GoalGraph` lays an orthorhombic lattice over a box-shaped goal-space field (eqs. 9–10; a
3-D box, or a 2-D rectangle for a planar goal space), removes the vertices inside every obstacle
inflated by a safety margin ε (Sec. IV-B), joins each remaining vertex to its 26 neighbours (8 in
2-D) with edges weighted by their length (eq. 11) and holds all
pairwise shortest-path distances in a compact table. :meth:`GoalGraph.distance` maps goals to
vertices (eq. 14) and reads the table (eq. 13) with vectorised torch ops; it is ``inf`` where a goal
lies outside the field or on a removed vertex. :class:`EuclideanMetric` offers the same
``distance(a, b)``, so every algorithm switches metric by configuration.

Decisions where the paper is silent (the README's graph section repeats them):

* **Goal → vertex (eq. 14).** The paper writes ⌊·⌋ but defines it as rounding to the closest
  integer, and the original code rounds: the default ``snap="nearest"`` maps a goal to its nearest
  lattice vertex; ``snap="floor"`` is the literal floor (the vertex below-left of the goal).
* **Obstacles.** An obstacle ``(center, half)`` becomes the closed box ``center ± (half + margin)``;
  a vertex on its surface is removed. Obstacles that miss the field are ignored (with a warning).
* **Density criterion (eq. 12).** For every inflated obstacle, the part inside the field must be
  longer than the lattice spacing ``2·half_field/(n − 1)`` on each axis, strictly. That guarantees a
  removed vertex on every lattice line through the obstacle, so no edge jumps across it.
* **Table.** Distances between free vertices are stored once per unordered pair (the upper
  triangle) as ``int16`` multiples of a per-table ``resolution``, with ``32767`` for "unreachable".
  The resolution is chosen from a bound on the graph's diameter, so the rounding error is at most
  ``resolution / 2`` (about 0.04 mm for the KUKA fields; an error over 1 mm is refused).
* **Cache.** The table is cached on disk under :func:`default_cache_dir`, keyed by a hash of the
  field, the obstacles, ``n``, the margin and the file format; files are written atomically and
  checked before use (the project's checkpoint format: magic, SHA-256, length; then the graph it
  describes and the table's shape): a damaged file is rebuilt, never used.
  A lock file lets one process build while others constructing the same graph wait and load.

"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import logging
import math
import numbers
import os
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from gchgg.common import files

__all__ = ["DEFAULT_MARGIN", "DEFAULT_N", "USER_CACHE_DIR", "GoalGraph", "check_density_criterion", "default_cache_dir"]

_log = logging.getLogger(__name__)

DEFAULT_N: tuple[int, int, int] = (31, 31, 11)  # lattice vertices per axis (the G-HGG and GC-HGG runs)
DEFAULT_MARGIN = 0.02  # metres: the original G-HGG code's inflation of every obstacle half-size

_UNREACHABLE = 32767  # int16 table code for "no path" (and for any pair with the void slot 0)
_MAX_CODE = _UNREACHABLE - 1  # largest code of a finite distance
_MAX_ERROR = 1e-3  # metres: largest rounding error the 2-byte table may have
_BOUNDARY_TOLERANCE = 1e-5  # metres: goals this close outside the field (or below a plane) are on it
_MAX_TABLE_BYTES = 4 * 2**30  # refuse lattices whose table would not fit comfortably in memory
_CHUNK_ROWS = 256  # Dijkstra source rows per chunk: bounds the float64 scratch at 256 × V × 8 bytes
_FORMAT = 2  # bump when the table's layout or encoding changes: old cache files then miss (2: checkpoint format)
_AXES = "xyz"


def default_cache_dir() -> Path:
    """Per-user folder for graph tables.

    Returns:
        ``$GCHGG_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/gchgg``, else ``~/.cache/gchgg``.
    """
    if os.environ.get("GCHGG_CACHE_DIR"):
        return Path(os.environ["GCHGG_CACHE_DIR"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "gchgg"


class _UserCacheDir:
    """Sentinel default of ``cache_dir``: resolve :func:`default_cache_dir` at construction."""

    def __repr__(self) -> str:
        return "default_cache_dir()"


USER_CACHE_DIR = _UserCacheDir()


class _CorruptCache(Exception):
    """A cache file that must not be used; the message says why."""


class GoalGraph:
    """Obstacle-aware lattice graph over a box-shaped goal space, with all-pairs graph distances.

    The field is 3-D (``(x, y, z)`` goals) or 2-D (``(x, y)`` goals of a planar task: a 2-D lattice,
    8-connected; its obstacles are rectangles). The lattice has ``n[k]`` vertices along axis ``k``,
    spaced ``2·field.half[k] / (n[k] − 1)`` and spanning the field's faces (eqs. 9–10). Vertices
    inside an obstacle inflated by ``margin`` are removed; the others are joined to their (up to) 26
    (2-D: 8) neighbours by edges weighted by their
    Euclidean length (eq. 11). Shortest-path distances between every pair of free vertices come
    from Dijkstra and are kept in a 2-byte-per-pair table (see the module docstring), cached on
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
        center, half, self.n, self.margin, self.obstacles = _settings(field, obstacles, n, margin)
        if snap not in ("nearest", "floor"):
            raise ValueError(f"snap must be 'nearest' or 'floor', got {snap!r}")
        self.field = (tuple(center.tolist()), tuple(half.tolist()))
        self.snap = snap

        self.low = center - half  # float64 [3]
        self.high = center + half
        self.spacing = 2.0 * half / (np.asarray(self.n) - 1)  # eq. 9
        # eq. 12; each inflated obstacle meeting the field as (low, high), clipped to the field
        self.inflated_obstacles = _inflate(
            self.low, self.high, self.spacing, self.obstacles, self.margin
        )
        self._free = self._free_vertices()  # bool [n_x, n_y, n_z]
        if not self._free.any():
            raise ValueError("every lattice vertex lies inside an inflated obstacle: the graph is empty")
        self.num_vertices = int(self._free.sum())
        table_bytes = (self.num_vertices + 1) * (self.num_vertices + 2)  # 2 bytes per entry
        if table_bytes > _MAX_TABLE_BYTES:
            raise ValueError(
                f"n={self.n} gives {self.num_vertices} free vertices, whose distance table would take "
                f"{table_bytes / 2**30:.1f} GiB (more than {_MAX_TABLE_BYTES / 2**30:g} GiB): use a "
                f"smaller n"
            )
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
        slots = self.num_vertices + 1
        rows = torch.arange(slots, dtype=torch.int64)
        # The upper triangle row by row: entry (r, c), r <= c, lives at _row_offset[r] + c.
        self._row_offset = rows * slots - rows * (rows + 1) // 2
        self._adjacency: csr_matrix | None = None

        self._vertex_lookup: tuple[torch.Tensor, torch.Tensor] | None = None  # see pair_distance
        self.cache_path: Path | None = None
        self.loaded_from_cache = False
        if cache_dir is not None:
            if isinstance(cache_dir, _UserCacheDir):
                folder = default_cache_dir()
            else:
                folder = Path(cache_dir).expanduser()
            self.cache_path = folder / f"goalgraph-{self._cache_key()}.bin"
        if self.cache_path is None:
            table = self._build()
        else:
            # One builder at a time per table: processes started together (a multirun) wait
            # for the first one's file instead of all building it.
            with _file_lock(self.cache_path.with_suffix(".lock")):
                table = self._load()
                self.loaded_from_cache = table is not None
                if table is None:
                    table = self._build()
                    self._save(table)
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
            decoded = torch.arange(_UNREACHABLE + 1, dtype=torch.float32).mul_(self._scale)
            decoded[_UNREACHABLE] = math.inf
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
            self._adjacency = self._edges()
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
        return distance.masked_fill_(code == _UNREACHABLE, math.inf)

    # ------------------------------------------------------------------ construction

    def _free_vertices(self) -> np.ndarray:
        d = len(self.n)
        axes = [self.low[k] + self.spacing[k] * np.arange(self.n[k]) for k in range(d)]
        free = np.ones(self.n, dtype=bool)
        tol = 1e-9  # metres: a vertex on an inflated obstacle's surface is removed despite float noise
        for low, high in self.inflated_obstacles:
            inside = [(axes[k] >= low[k] - tol) & (axes[k] <= high[k] + tol) for k in range(d)]
            box = inside[0].reshape([-1] + [1] * (d - 1))
            for k in range(1, d):  # the box's vertices: the outer product of its axes' memberships
                box = box & inside[k].reshape([1] * k + [-1] + [1] * (d - 1 - k))
            free &= ~box
        return free

    def _edges(self) -> csr_matrix:
        """26-connected (2-D: 8-connected) edges between free vertices weighted by length (eq. 11), both directions."""
        compact = np.full(self.n, -1, dtype=np.int64)
        compact[self._free] = np.arange(self.num_vertices)
        rows, cols, weights = [], [], []
        d = len(self.n)
        for step in itertools.product((-1, 0, 1), repeat=d):
            if step <= (0,) * d:  # each undirected edge once: the 13 (2-D: 4) "forward" neighbours
                continue
            source = tuple(slice(max(0, -d), k - max(0, d)) for d, k in zip(step, self.n, strict=True))
            target = tuple(slice(max(0, d), k - max(0, -d)) for d, k in zip(step, self.n, strict=True))
            a, b = compact[source].reshape(-1), compact[target].reshape(-1)
            keep = (a >= 0) & (b >= 0)
            rows.append(a[keep])
            cols.append(b[keep])
            weights.append(np.full(int(keep.sum()), np.linalg.norm(np.asarray(step) * self.spacing)))
        row, col, weight = (np.concatenate(x) for x in (rows + cols, cols + rows, weights + weights))
        return csr_matrix((weight, (row, col)), shape=(self.num_vertices, self.num_vertices))

    def _build(self) -> np.ndarray:
        """All-pairs Dijkstra in chunks of source rows, rounded into the int16 upper-triangle table."""
        start = time.perf_counter()
        graph = self.adjacency
        vertices = self.num_vertices
        # Diameter bound: d(u, w) <= d(u, r) + d(r, w) <= 2 ecc(r) for any r in u's component.
        _, label = connected_components(graph, directed=False)
        representative = np.unique(label, return_index=True)[1]
        reach = dijkstra(graph, directed=True, indices=representative)
        eccentricity = max(reach[c][label == c].max() for c in range(len(representative)))
        self._scale = max(2.0 * eccentricity, float(self.spacing.min())) / _MAX_CODE
        if self._scale / 2 >= _MAX_ERROR:
            raise ValueError(
                f"graph distances up to {2 * eccentricity:.1f} m cannot be held in 2 bytes to within "
                f"{_MAX_ERROR * 1e3:g} mm; use a smaller field"
            )
        slots = vertices + 1
        table = np.empty(slots * (slots + 1) // 2, dtype=np.int16)
        table[:slots] = _UNREACHABLE  # row of the void slot 0
        column = np.arange(vertices)
        for first in range(0, vertices, _CHUNK_ROWS):
            sources = np.arange(first, min(first + _CHUNK_ROWS, vertices))
            dist = dijkstra(graph, directed=True, indices=sources)  # float64 [chunk, V]
            dist *= 1.0 / self._scale
            code = np.rint(dist, out=dist)  # in place: one float64 [chunk, V] buffer per chunk
            code[~np.isfinite(code)] = _UNREACHABLE
            upper = code[column[None, :] >= sources[:, None]]  # row by row, each row's part j >= i
            begin = int(self._row_offset[first + 1]) + first + 1
            table[begin : begin + upper.size] = np.minimum(upper, _UNREACHABLE)
        _log.info("built %d-vertex distance table in %.1f s", vertices, time.perf_counter() - start)
        return table

    # ------------------------------------------------------------------ cache

    def _cache_key(self) -> str:
        params = self._params()
        params["format"] = _FORMAT
        return hashlib.blake2b(json.dumps(params, sort_keys=True).encode(), digest_size=16).hexdigest()

    def _params(self) -> dict[str, Any]:
        """Everything that changes the table (``snap`` does not)."""
        return {
            "field": self.field,
            "obstacles": sorted(self.obstacles),
            "n": self.n,
            "margin": self.margin,
        }

    def _load(self) -> np.ndarray | None:
        """The cached table, or ``None`` if absent or damaged (a damaged file gets a warning)."""
        path = self.cache_path
        if not path.is_file():
            _log.debug("no graph cache file %s", path)
            return None
        try:
            table = self._check_cached(files.load(path))
        except (files.CorruptCheckpointError, _CorruptCache, OSError, ValueError, RuntimeError) as error:
            warnings.warn(
                f"ignoring damaged graph cache file {path} ({error}); rebuilding it",
                RuntimeWarning,
                stacklevel=3,
            )
            return None
        _log.info("loaded graph distance table from %s", path)
        return table

    def _check_cached(self, state: Any) -> np.ndarray:
        """The table of a cache file's state (the project's checksummed checkpoint format), checked
        against this graph."""
        slots = self.num_vertices + 1
        expected = {"format": _FORMAT, "key": self.cache_path.stem.removeprefix("goalgraph-"),
                    "vertices": self.num_vertices}
        if not isinstance(state, dict) or any(state.get(k) != v for k, v in expected.items()):
            raise _CorruptCache("the file does not describe this graph")
        table = state.get("table")
        entries = slots * (slots + 1) // 2
        if not isinstance(table, torch.Tensor) or table.dtype != torch.int16 or table.shape != (entries,):
            raise _CorruptCache(f"the table is not int16 [{entries}]")
        scale = state.get("scale")
        if not isinstance(scale, float) or not 0 < scale < 2 * _MAX_ERROR:
            raise _CorruptCache(f"bad resolution {scale!r}")
        self._scale = scale
        return table.numpy()

    def _save(self, table: np.ndarray) -> None:
        """Write the table with the project's atomic, checksummed writer (:func:`gchgg.common.files.save`)."""
        path = self.cache_path
        state = {
            "format": _FORMAT,
            "key": path.stem.removeprefix("goalgraph-"),
            "vertices": self.num_vertices,
            "scale": self._scale,
            "params": self._params(),
            "table": torch.from_numpy(table),
        }
        try:
            files.save(state, path, mode=0o644)  # readable like any cache file
        except OSError as error:
            warnings.warn(
                f"could not write graph cache file {path} ({error}); continuing without it",
                RuntimeWarning,
                stacklevel=3,
            )


@contextlib.contextmanager
def _file_lock(path: Path):
    """Hold an exclusive advisory lock on ``path`` (POSIX ``flock``); a no-op where impossible."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        file = open(path, "a")
    except OSError:  # read-only or missing folder: the cache write will warn
        yield
        return
    with file:
        try:
            import fcntl

            fcntl.flock(file, fcntl.LOCK_EX)
        except (ImportError, OSError):  # no flock on this platform or file system
            pass
        yield  # closing the file releases the lock, also if the holder dies


# ---------------------------------------------------------------------- validation helpers


def check_density_criterion(
    field: tuple[Sequence[float], Sequence[float]],
    obstacles: Sequence[tuple[Sequence[float], Sequence[float]]] = (),
    n: Sequence[int] = DEFAULT_N,
    margin: float = DEFAULT_MARGIN,
) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Check a graph's settings and the density criterion (eq. 12) without building the graph.

    Args:
        field, obstacles, n, margin: as for :class:`GoalGraph`.

    Returns:
        Each inflated obstacle that meets the field, as ``(low, high)`` corners clipped to the field.

    Raises:
        ValueError: as :class:`GoalGraph` does for bad settings or a violated criterion.
    """
    center, half, n, margin, obstacles = _settings(field, obstacles, n, margin)
    return _inflate(center - half, center + half, 2.0 * half / (np.asarray(n) - 1), obstacles, margin)


def _inflate(field_low, field_high, spacing, obstacles, margin):
    """Inflate and clip every obstacle; raise if one breaks the density criterion (eq. 12)."""
    inflated = []
    for i, (center, half) in enumerate(obstacles):
        low = np.maximum(np.asarray(center) - np.asarray(half) - margin, field_low)
        high = np.minimum(np.asarray(center) + np.asarray(half) + margin, field_high)
        if (low > high).any():
            warnings.warn(
                f"obstacle {i} (center={center}, half={half}) does not meet the field "
                f"{tuple(field_low.tolist())}..{tuple(field_high.tolist())} and is ignored",
                stacklevel=3,
            )
            continue
        edge = high - low
        bad = [k for k in range(len(spacing)) if not spacing[k] < edge[k]]
        if bad:
            fixes = "; ".join(
                f"along {_AXES[k]} it spans {edge[k]:.6g} m inside the field but the spacing is "
                f"{spacing[k]:.6g} m: the spacing must be below {edge[k]:.6g} m, "
                f"i.e. n_{_AXES[k]} >= {math.floor((field_high[k] - field_low[k]) / edge[k]) + 2}"
                for k in bad
            )
            raise ValueError(
                f"graph density criterion (eq. 12) violated by obstacle {i} "
                f"(center={center}, half={half}) inflated by margin {margin} m: {fixes} "
                f"(or enlarge the margin). Each inflated obstacle must be longer than the lattice "
                f"spacing 2*half/(n-1) on every axis, or edges could cross it."
            )
        inflated.append((low, high))
    return tuple(inflated)


def _settings(field, obstacles, n, margin):
    """Validated ``(center, half, n, margin, obstacles)`` of a graph."""
    center, half = _box("field", field)
    dim = len(center)
    if not (half > 0).all():
        raise ValueError(
            f"field half-sizes must be > 0 on every axis (a field of zero size has no lattice), "
            f"got half={tuple(half.tolist())}"
        )
    n = _lattice_size(n, dim)
    if isinstance(margin, bool) or not isinstance(margin, numbers.Real) or not math.isfinite(margin):
        raise ValueError(f"margin must be a finite number of metres >= 0, got {margin!r}")
    if margin < 0:
        raise ValueError(f"margin must be >= 0 metres (it inflates every obstacle), got {margin!r}")
    obstacles = tuple(
        tuple(tuple(v.tolist()) for v in _box(f"obstacles[{i}]", box, dim)) for i, box in enumerate(obstacles)
    )
    return center, half, n, float(margin), obstacles


def _box(name: str, box: Any, dim: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(center, half)`` as two finite float64 arrays of shape [d]: d = 3 or 2 (``dim`` when given)."""
    try:
        center, half = box
        center = np.asarray(center, dtype=np.float64)
        half = np.asarray(half, dtype=np.float64)
    except (TypeError, ValueError):
        center = half = None
    if (
        center is None
        or center.shape not in ((3,), (2,))
        or half.shape != center.shape
        or (dim is not None and center.shape != (dim,))
        or not (np.isfinite(center).all() and np.isfinite(half).all())
    ):
        allowed = {None: "two finite (x, y, z) triples (3-D) or (x, y) pairs (2-D)",
                   3: "two finite (x, y, z) triples, like the 3-D field",
                   2: "two finite (x, y) pairs, like the 2-D field"}[dim]
        raise ValueError(f"{name} must be a box (center, half) of {allowed} in metres, got {box!r}")
    if (half < 0).any():
        raise ValueError(f"{name} half-sizes must be >= 0, got half={tuple(half.tolist())}")
    return center, half


def _lattice_size(n: Any, dim: int = 3) -> tuple[int, ...]:
    try:
        values = list(n)
    except TypeError:
        values = None
    if values is None or len(values) != dim or not all(
        isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= 2 for v in values
    ):
        names = "(n_x, n_y, n_z)" if dim == 3 else "(n_x, n_y), for the 2-D field"
        raise ValueError(
            f"n must be {'three' if dim == 3 else 'two'} integers {names}, each >= 2 (vertices per axis), got {n!r}"
        )
    return tuple(int(v) for v in values)


# ---------------------------------------------------------------------- picture and CLI
