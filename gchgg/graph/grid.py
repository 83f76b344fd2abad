"""The lattice of a goal graph (eqs. 9–12): checked settings, inflated obstacles, free vertices, 26-connected edges.

:class:`gchgg.graph.GoalGraph` builds itself from these parts; :func:`check_density_criterion` runs the
settings' checks and the density criterion alone, e.g. to validate a config.

* **Obstacles.** An obstacle ``(center, half)`` becomes the closed box ``center ± (half + margin)``;
  a vertex on its surface is removed. Obstacles that miss the field are ignored (with a warning).
* **Density criterion (eq. 12).** For every inflated obstacle, the part inside the field must be
  longer than the lattice spacing ``2·half_field/(n − 1)`` on each axis, strictly. That guarantees a
  removed vertex on every lattice line through the obstacle, so no edge jumps across it.
"""

from __future__ import annotations

import itertools
import math
import numbers
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.sparse import csr_matrix

__all__ = [
    "DEFAULT_MARGIN", "DEFAULT_N", "check_density_criterion", "checked_settings", "edges", "free_vertices", "inflate"
]

DEFAULT_N: tuple[int, int, int] = (31, 31, 11)  # lattice vertices per axis (the G-HGG and GC-HGG runs)
DEFAULT_MARGIN = 0.02  # metres: the original G-HGG code's inflation of every obstacle half-size

_AXES = "xyz"


def check_density_criterion(
    field: tuple[Sequence[float], Sequence[float]],
    obstacles: Sequence[tuple[Sequence[float], Sequence[float]]] = (),
    n: Sequence[int] = DEFAULT_N,
    margin: float = DEFAULT_MARGIN,
) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Check a graph's settings and the density criterion (eq. 12) without building the graph.

    Args:
        field, obstacles, n, margin: as for :class:`gchgg.graph.GoalGraph`.

    Returns:
        Each inflated obstacle that meets the field, as ``(low, high)`` corners clipped to the field.

    Raises:
        ValueError: as :class:`gchgg.graph.GoalGraph` does for bad settings or a violated criterion.
    """
    center, half, n, margin, obstacles = checked_settings(field, obstacles, n, margin)
    return inflate(center - half, center + half, 2.0 * half / (np.asarray(n) - 1), obstacles, margin)


def free_vertices(low: np.ndarray, spacing: np.ndarray, n: tuple[int, ...], inflated_obstacles) -> np.ndarray:
    """Bool ``[n_x, n_y, n_z]`` (``[n_x, n_y]`` in 2-D): the lattice vertices outside every inflated obstacle.

    Args:
        low: the field's lowest corner ``[d]`` (metres), the lattice's first vertex.
        spacing: the lattice spacing ``[d]`` (eq. 9).
        n: vertices per axis.
        inflated_obstacles: ``(low, high)`` corners of the inflated obstacles (:func:`check_density_criterion`).
    """
    d = len(n)
    axes = [low[k] + spacing[k] * np.arange(n[k]) for k in range(d)]
    free = np.ones(n, dtype=bool)
    tol = 1e-9  # metres: a vertex on an inflated obstacle's surface is removed despite float noise
    for box_low, box_high in inflated_obstacles:
        inside = [(axes[k] >= box_low[k] - tol) & (axes[k] <= box_high[k] + tol) for k in range(d)]
        box = inside[0].reshape([-1] + [1] * (d - 1))
        for k in range(1, d):  # the box's vertices: the outer product of its axes' memberships
            box = box & inside[k].reshape([1] * k + [-1] + [1] * (d - 1 - k))
        free &= ~box
    return free


def edges(free: np.ndarray, spacing: np.ndarray) -> csr_matrix:
    """26-connected (2-D: 8-connected) edges between free vertices weighted by length (eq. 11), both directions.

    Args:
        free: the lattice's free vertices (:func:`free_vertices`); they are numbered in C order.
        spacing: the lattice spacing ``[d]``.

    Returns:
        Sparse ``[V, V]`` edge lengths, V the number of free vertices.
    """
    n = free.shape
    vertices = int(free.sum())
    compact = np.full(n, -1, dtype=np.int64)
    compact[free] = np.arange(vertices)
    rows, cols, weights = [], [], []
    d = len(n)
    for step in itertools.product((-1, 0, 1), repeat=d):
        if step <= (0,) * d:  # each undirected edge once: the 13 (2-D: 4) "forward" neighbours
            continue
        source = tuple(slice(max(0, -d), k - max(0, d)) for d, k in zip(step, n, strict=True))
        target = tuple(slice(max(0, d), k - max(0, -d)) for d, k in zip(step, n, strict=True))
        a, b = compact[source].reshape(-1), compact[target].reshape(-1)
        keep = (a >= 0) & (b >= 0)
        rows.append(a[keep])
        cols.append(b[keep])
        weights.append(np.full(int(keep.sum()), np.linalg.norm(np.asarray(step) * spacing)))
    row, col, weight = (np.concatenate(x) for x in (rows + cols, cols + rows, weights + weights))
    return csr_matrix((weight, (row, col)), shape=(vertices, vertices))


# ---------------------------------------------------------------------- checks


def inflate(field_low, field_high, spacing, obstacles, margin):
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


def checked_settings(field, obstacles, n, margin):
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
