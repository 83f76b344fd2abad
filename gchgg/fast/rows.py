"""Per-row caches of replay samplers: values computed once per stored row, again only for the rows written since.

- :class:`WrittenRows`: which rows a cache must (re)compute, from the writes the buffer reports
  (``extend``/``add``/``mark_update``); EBP's energy copy and :class:`RowCache` use it;
- :class:`RowCache`: Alg. 1's per-row cache, each stored row's shortlist point (the
  :class:`~gchgg.fast.nearest.NearestNeighbours` input) and goal-to-target distance, so that
  scoring a candidate batch reads neither goals nor targets from the storage and snaps no goal.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import torch

from gchgg.fast.nearest import NearestNeighbours

__all__ = ["RowCache", "RowReader", "WrittenRows"]


class WrittenRows:
    """Which stored rows a sampler's per-row cache must (re)compute: those written since it last caught up.

    The sampler calls :meth:`mark` from ``extend``/``add``/``mark_update`` with the written index,
    and :meth:`take` before it reads its cache. ``take(n, size)`` returns the rows below ``n`` (the
    storage's length) to recompute: rows rewritten since, and rows new to the storage; or ``None``
    when the whole cache must be built anew (nothing cached yet, ``size`` (the cache's rows) below
    ``n``, or a write given as something other than row indices, e.g. a slice).

    >>> rows = WrittenRows()
    >>> rows.take(4, size=10) is None  # the first time: build everything
    True
    >>> rows.mark(torch.tensor([1])); rows.current(6)
    False
    >>> rows.take(6, size=10).tolist()  # row 1 rewritten, rows 4 and 5 new
    [1, 4, 5]
    >>> rows.current(6)
    True
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget everything: the next :meth:`take` asks for a full build."""
        self._known, self._pending, self._all = 0, [], True

    def mark(self, index) -> None:
        """Rows just written: a row index, an integer tensor or array of them, or anything else (all rows)."""
        if isinstance(index, (int, torch.Tensor, np.ndarray)) and not torch.as_tensor(index).is_floating_point():
            self._pending.append(torch.as_tensor(index).reshape(-1).long())
        else:
            self.reset()

    def current(self, n: int) -> bool:
        """Whether a cache that caught up at the last :meth:`take` holds every row of a storage of length ``n``."""
        return not self._all and not self._pending and n == self._known

    def take(self, n: int, size: int) -> torch.Tensor | None:
        """The rows to recompute now (``None``: all ``n``); afterwards the cache counts as current for ``n``."""
        full = self._all or size < n
        fresh = [] if full else [index[index < min(n, self._known)] for index in self._pending]
        if not full and n > self._known:
            fresh.append(torch.arange(self._known, n))
        self._known, self._pending, self._all = n, [], False
        if full:
            return None
        return torch.cat(fresh) if fresh else torch.empty(0, dtype=torch.long)


class RowReader(Protocol):
    """What :class:`RowCache` reads a stored row with (:class:`~gchgg.samplers.GraphCurriculumSampler`)."""

    def read_rows(self, storage, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The diversity goals ``[N, d]`` and the goal-to-target distances ``[N]`` (float32) of stored ``rows``."""
        ...


class RowCache:
    """Alg. 1's per-row cache: each stored row's shortlist point and goal-to-target distance, computed once.

    Each entry (see :meth:`NearestNeighbours.points`) is computed at the first :meth:`gather` after
    its row is written (rows reported to :meth:`mark`, and rows new to the storage) and kept in a
    float32 ``[capacity, d + 4]`` tensor for d-D goals: the point ``(p, |p|², 1, id)``, then the
    distance (28 bytes per row for 3-D goals; ``[capacity, 2·d + 4]`` with the goal itself for a
    diversity metric without a lattice, which reads goals), sized to the storage's capacity at the
    first build, plus one byte per row of scratch (:attr:`marks`). Rows overwritten behind the
    sampler's back (TorchRL's ``buffer[index] = ...``) keep stale entries until reported.
    """

    def __init__(self, nearest: NearestNeighbours) -> None:
        self.nearest = nearest
        self.rows: torch.Tensor | None = None  # [capacity, width], valid as self.written says
        self.marks: torch.Tensor | None = None  # one bool per row, all False: scratch for the pool's skips
        self.written = WrittenRows()
        self.width = self.to_target = 0  # columns per row; the goal-to-target distance's column (set at a build)

    @property
    def nbytes(self) -> int:
        """Bytes of the cache and its scratch (0 before the first build)."""
        return 0 if self.rows is None else self.rows.numel() * self.rows.element_size() + len(self.marks)

    def reset(self) -> None:
        """Forget every entry: the next :meth:`gather` builds the cache anew."""
        self.rows = None
        self.written.reset()

    def gather(self, reader: RowReader, storage, index: torch.Tensor, n: int) -> torch.Tensor:
        """The entries ``[..., width]`` of rows ``index`` of a storage of length ``n``, brought up to date first."""
        if not self.written.current(n):
            self._refresh(reader, storage, n)
        return self.rows.index_select(0, index.view(-1)).view(*index.shape, self.width)

    def split(self, entries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Entries ``[..., width]`` as (shortlist points ``[..., d + 3]``, goal-to-target distances ``[...]``,
        the goals ``[..., d]`` for a metric without a lattice or ``None``)."""
        t = self.to_target
        return entries[..., :t], entries[..., t], None if self.nearest.snaps else entries[..., t + 1 :]

    def _refresh(self, reader: RowReader, storage, n: int) -> None:
        """Compute the entries of rows written since the last gather (and of rows new to the storage)."""
        fresh = self.written.take(n, 0 if self.rows is None else len(self.rows))
        rebuild = fresh is None
        if rebuild:  # everything: the cache is sized to the storage's capacity below
            fresh = torch.arange(n)
        if not len(fresh):
            return
        goals, distance = reader.read_rows(storage, fresh)
        points = self.nearest.points(goals)  # checks the goals' d against the diversity metric
        if rebuild:
            self.to_target = points.shape[-1]
            self.width = self.to_target + 1 + (0 if self.nearest.snaps else goals.shape[-1])
            self.rows = torch.empty(max(n, int(getattr(storage, "max_size", n) or n)), self.width)
            self.marks = torch.zeros(len(self.rows), dtype=torch.bool)
        cache, t = self.rows, self.to_target
        cache[fresh, :t] = points
        cache[fresh, t] = distance
        if not self.nearest.snaps:  # the goals themselves: the metric reads them
            cache[fresh, t + 1 :] = goals.to(cache.dtype)
