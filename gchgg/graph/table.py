"""The all-pairs distance table of a goal graph: Dijkstra's distances packed in int16, and their on-disk cache.

:class:`gchgg.graph.GoalGraph` reads d_G (eq. 13) from this table; this module builds it and keeps it.

* **Table.** Distances between free vertices are stored once per unordered pair (the upper
  triangle) as ``int16`` multiples of a per-table ``resolution``, with ``32767`` for "unreachable".
  Slot 0 is a void vertex whose row is all unreachable; free vertex v is slot v + 1, and entry
  ``(r, c)``, ``r <= c``, lives at ``row_offsets(slots)[r] + c``. The resolution is chosen from a
  bound on the graph's diameter, so the rounding error is at most ``resolution / 2`` (about 0.04 mm
  for the KUKA fields; an error over 1 mm is refused).
* **Cache.** The table is cached on disk under :func:`default_cache_dir`, keyed by a hash of the
  field, the obstacles, ``n``, the margin and the file format; files are written atomically and
  checked before use (the project's checkpoint format, :mod:`gchgg.common.files`: magic, SHA-256,
  length; then the graph it describes and the table's shape): a damaged file is rebuilt, never used.
  A lock file lets one process build while others constructing the same graph wait and load.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from gchgg.common import files

__all__ = ["UNREACHABLE", "USER_CACHE_DIR", "build_table", "cache_file", "check_size", "default_cache_dir",
           "load_or_build", "row_offsets"]

_log = logging.getLogger(__name__)

UNREACHABLE = 32767  # int16 table code for "no path" (and for any pair with the void slot 0)
_MAX_CODE = UNREACHABLE - 1  # largest code of a finite distance
_MAX_ERROR = 1e-3  # metres: largest rounding error the 2-byte table may have
_MAX_TABLE_BYTES = 4 * 2**30  # refuse lattices whose table would not fit comfortably in memory
_CHUNK_ROWS = 256  # Dijkstra source rows per chunk: bounds the float64 scratch at 256 × V × 8 bytes
_FORMAT = 2  # bump when the table's layout or encoding changes: old cache files then miss (2: checkpoint format)


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


# ---------------------------------------------------------------------- the table


def row_offsets(slots: int) -> torch.Tensor:
    """int64 ``[slots]``: where each row of the upper triangle starts, less its first column.

    Entry ``(r, c)``, ``r <= c``, of a table over ``slots`` slots lives at ``row_offsets(slots)[r] + c``.
    """
    rows = torch.arange(slots, dtype=torch.int64)
    return rows * slots - rows * (rows + 1) // 2


def check_size(n: tuple[int, ...], vertices: int) -> None:
    """Refuse a graph whose table would take more than 4 GiB.

    Raises:
        ValueError: naming ``n``, the free vertices and the table's size.
    """
    table_bytes = (vertices + 1) * (vertices + 2)  # 2 bytes per entry
    if table_bytes > _MAX_TABLE_BYTES:
        raise ValueError(
            f"n={n} gives {vertices} free vertices, whose distance table would take "
            f"{table_bytes / 2**30:.1f} GiB (more than {_MAX_TABLE_BYTES / 2**30:g} GiB): use a "
            f"smaller n"
        )


def build_table(graph: csr_matrix, spacing: np.ndarray) -> tuple[np.ndarray, float]:
    """All-pairs Dijkstra in chunks of source rows, rounded into the int16 upper-triangle table.

    Args:
        graph: sparse ``[V, V]`` edge lengths (:func:`gchgg.graph.grid.edges`).
        spacing: the lattice spacing ``[d]``: the resolution is at least its smallest value / 32766.

    Returns:
        ``(table, resolution)``: int16 ``[(V + 1)(V + 2) / 2]`` and metres per table unit.

    Raises:
        ValueError: the graph's diameter is too large for a 2-byte table within 1 mm.
    """
    start = time.perf_counter()
    vertices = graph.shape[0]
    # Diameter bound: d(u, w) <= d(u, r) + d(r, w) <= 2 ecc(r) for any r in u's component.
    _, label = connected_components(graph, directed=False)
    representative = np.unique(label, return_index=True)[1]
    reach = dijkstra(graph, directed=True, indices=representative)
    eccentricity = max(reach[c][label == c].max() for c in range(len(representative)))
    scale = max(2.0 * eccentricity, float(spacing.min())) / _MAX_CODE
    if scale / 2 >= _MAX_ERROR:
        raise ValueError(
            f"graph distances up to {2 * eccentricity:.1f} m cannot be held in 2 bytes to within "
            f"{_MAX_ERROR * 1e3:g} mm; use a smaller field"
        )
    slots = vertices + 1
    table = np.empty(slots * (slots + 1) // 2, dtype=np.int16)
    table[:slots] = UNREACHABLE  # row of the void slot 0
    column = np.arange(vertices)
    for first in range(0, vertices, _CHUNK_ROWS):
        sources = np.arange(first, min(first + _CHUNK_ROWS, vertices))
        dist = dijkstra(graph, directed=True, indices=sources)  # float64 [chunk, V]
        dist *= 1.0 / scale
        code = np.rint(dist, out=dist)  # in place: one float64 [chunk, V] buffer per chunk
        code[~np.isfinite(code)] = UNREACHABLE
        upper = code[column[None, :] >= sources[:, None]]  # row by row, each row's part j >= i
        row = first + 1  # the slot of vertex `first`: its row starts at its diagonal entry
        begin = row * slots - row * (row + 1) // 2 + row
        table[begin : begin + upper.size] = np.minimum(upper, UNREACHABLE)
    _log.info("built %d-vertex distance table in %.1f s", vertices, time.perf_counter() - start)
    return table, scale


# ---------------------------------------------------------------------- the cache


def cache_file(cache_dir: str | os.PathLike | None | _UserCacheDir, params: dict[str, Any]) -> Path | None:
    """The cache file of the graph ``params`` describe (everything that changes its table), in ``cache_dir``
    (:data:`USER_CACHE_DIR`: :func:`default_cache_dir`); ``None`` for ``cache_dir=None``."""
    if cache_dir is None:
        return None
    folder = default_cache_dir() if isinstance(cache_dir, _UserCacheDir) else Path(cache_dir).expanduser()
    key = hashlib.blake2b(json.dumps({**params, "format": _FORMAT}, sort_keys=True).encode(), digest_size=16)
    return folder / f"goalgraph-{key.hexdigest()}.bin"


def load_or_build(
    path: Path | None, vertices: int, params: dict[str, Any], build: Callable[[], tuple[np.ndarray, float]]
) -> tuple[np.ndarray, float, bool]:
    """The table of a graph from its cache file, else from ``build()`` (then written to the file).

    One builder at a time per table: processes started together (a multirun) wait for the first
    one's file instead of all building it.

    Args:
        path: the cache file (:func:`cache_file`), or ``None`` to build in memory without touching the disk.
        vertices: the graph's free vertices, which the file must describe.
        params: the graph's settings, stored in the file beside the table.
        build: makes ``(table, resolution)``, e.g. with :func:`build_table`.

    Returns:
        ``(table, resolution, loaded)``; ``loaded`` says whether the table came from the file.
    """
    if path is None:
        return (*build(), False)
    with _file_lock(path.with_suffix(".lock")):
        cached = _load(path, vertices)
        if cached is not None:
            return (*cached, True)
        table, scale = build()
        _save(path, table, scale, vertices, params)
        return table, scale, False


def _load(path: Path, vertices: int) -> tuple[np.ndarray, float] | None:
    """The cached ``(table, resolution)``, or ``None`` if absent or damaged (a damaged file gets a warning)."""
    if not path.is_file():
        _log.debug("no graph cache file %s", path)
        return None
    try:
        cached = _check_cached(files.load(path), path, vertices)
    except (files.CorruptCheckpointError, _CorruptCache, OSError, ValueError, RuntimeError) as error:
        warnings.warn(
            f"ignoring damaged graph cache file {path} ({error}); rebuilding it",
            RuntimeWarning,
            stacklevel=4,  # GoalGraph's caller
        )
        return None
    _log.info("loaded graph distance table from %s", path)
    return cached


def _check_cached(state: Any, path: Path, vertices: int) -> tuple[np.ndarray, float]:
    """The table and resolution of a cache file's state (the project's checksummed checkpoint format),
    checked against the graph of ``vertices`` free vertices whose cache file is ``path``."""
    slots = vertices + 1
    expected = {"format": _FORMAT, "key": path.stem.removeprefix("goalgraph-"), "vertices": vertices}
    if not isinstance(state, dict) or any(state.get(k) != v for k, v in expected.items()):
        raise _CorruptCache("the file does not describe this graph")
    table = state.get("table")
    entries = slots * (slots + 1) // 2
    if not isinstance(table, torch.Tensor) or table.dtype != torch.int16 or table.shape != (entries,):
        raise _CorruptCache(f"the table is not int16 [{entries}]")
    scale = state.get("scale")
    if not isinstance(scale, float) or not 0 < scale < 2 * _MAX_ERROR:
        raise _CorruptCache(f"bad resolution {scale!r}")
    return table.numpy(), scale


def _save(path: Path, table: np.ndarray, scale: float, vertices: int, params: dict[str, Any]) -> None:
    """Write the table with the project's atomic, checksummed writer (:func:`gchgg.common.files.save`)."""
    state = {
        "format": _FORMAT,
        "key": path.stem.removeprefix("goalgraph-"),
        "vertices": vertices,
        "scale": scale,
        "params": params,
        "table": torch.from_numpy(table),
    }
    try:
        files.save(state, path, mode=0o644)  # readable like any cache file
    except files.DiskFullError:  # the run stops, naming the file: it would find the disk full again soon
        raise
    except OSError as error:
        warnings.warn(
            f"could not write graph cache file {path} ({error}); continuing without it",
            RuntimeWarning,
            stacklevel=4,  # GoalGraph's caller
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
