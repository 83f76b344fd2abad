"""Energy-based prioritisation (EBP): draws stored transitions with probability ∝ their episode's energy."""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import NestedKey
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

from gchgg.common.validation import check_number
from gchgg.fast.rows import WrittenRows
from gchgg.samplers._storage import (
    check_sampleable,
    dump_state,
    generator,
    init_signature,
    load_state,
    one_thread,
    read_field,
)

__all__ = ["EnergySampler"]


_GUIDE_STEPS = 2  # forward steps from the guide table's entry before falling back to a binary search


@dataclass(frozen=True)
class _Runs:
    """Runs of equal consecutive positive energies (an episode's (k+1)·T rows), for drawing.

    ``cdf`` ``[R]``: cumulative weights (energy × length); ``table`` ``[R, 4]``: per run (weight
    before it, its weight, first row, length), float64; ``guide`` ``[2R]``: for each of 2R equal
    bins of [0, total), the run holding the bin's left edge. One entry per episode instead of one
    per transition keeps them small and in cache (2.5 M rows of 5,000 episodes: 5,000 runs).
    """

    cdf: torch.Tensor
    table: torch.Tensor
    guide: torch.Tensor
    total: float
    below_total: float  # the largest float64 below total: where draws are clamped

    @staticmethod
    def starts(energy: torch.Tensor) -> torch.Tensor:
        """First row of every run of equal consecutive energies (zero-energy runs too), in order: O(n)."""
        change = torch.ones(len(energy), dtype=torch.bool)
        change[1:] = energy[1:] != energy[:-1]
        return change.nonzero().squeeze(-1)

    @staticmethod
    def moved_starts(starts: torch.Tensor, energy: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """:meth:`starts` of ``energy`` after ``rows`` were written (or appended), from the starts before:
        only a written row and the row after it can open or stop opening a run. O(len(rows) + runs)."""
        n = len(energy)
        touched = torch.cat([rows, rows + 1]).unique()  # sorted
        touched = touched[touched < n]
        if not len(touched):
            return starts
        opens = (touched == 0) | (energy[touched] != energy[(touched - 1).clamp_(min=0)])
        at = torch.searchsorted(touched, starts).clamp_(max=len(touched) - 1)
        kept = starts[touched[at] != starts]  # the starts of untouched rows (a sorted lookup: faster than isin)
        return torch.cat([kept, touched[opens]]).sort().values

    @staticmethod
    def of(energy: torch.Tensor, start: torch.Tensor | None = None) -> _Runs | None:
        """The drawable runs of ``energy`` (``None`` if no row has energy), from its run starts when given."""
        n = len(energy)
        if start is None:
            start = _Runs.starts(energy)
        length = torch.diff(start, append=torch.tensor([n]))
        weight = energy[start] * length
        drawable = weight > 0  # zero-energy runs are never drawn
        start, length, weight = start[drawable], length[drawable], weight[drawable]
        if not len(weight):
            return None
        cdf = weight.cumsum(0)
        total = float(cdf[-1])
        table = torch.stack([cdf - weight, weight, start.double(), length.double()], -1)
        edges = torch.arange(2 * len(cdf), dtype=torch.float64).mul_(total / (2 * len(cdf)))
        guide = torch.searchsorted(cdf, edges, right=True).clamp_(max=len(cdf) - 1)
        return _Runs(cdf, table, guide, total, math.nextafter(total, 0.0))


@init_signature
class EnergySampler(Sampler):
    """Draws transitions with probability proportional to the energy stored beside them (EBP).

    Every stored transition carries its episode's trajectory energy (see
    :class:`gchgg.transforms.EpisodeEnergy`), and every episode stores the same number of
    transitions ((k+1)·T after :class:`~gchgg.transforms.HindsightRelabel`), so drawing rows in
    proportion to ``energy`` draws episodes in proportion to their energy and then a transition
    uniformly within the episode, as the original EBP buffer does.

    Cost: consecutive rows of equal energy (an episode's copies) are merged into runs; the runs'
    cumulative energies are cached and rebuilt on the first ``sample`` after the buffer writes
    (``extend``/``add``; O(written rows + runs): only a written row and the one after it can start or
    end a run), with a guide table (Chen & Asau's indexed search): each draw is
    then two table reads and two forward steps, O(1) (a binary search over the few draws whose
    bin holds more than two run boundaries). The rows' energies are kept in a float64 copy (8 bytes
    per row of the storage's capacity, :attr:`cache_bytes`): a rebuild reads from the storage only
    the rows written since the last one (``benchmarks/samplers.py`` prints what that saves).
    Works before the storage is full (only the first ``len(storage)`` rows) and after it wraps.

    Args:
        energy_key: stored entry holding the energy (one value per transition, ≥ 0). Default ``"energy"``.
        epsilon: added to every energy (≥ 0), giving zero-energy episodes a chance. Default 0: as in
            the original, they are never drawn while some episode has energy; if all energies are 0
            the draw is uniform.
        fast: keep the per-row energy copy above, its rows read again as written
            (:class:`gchgg.fast.rows.WrittenRows`; default), or ``False``: the plain path, which reads every
            stored energy again at the first sample after a write and calls no speed device. The same draws.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(100), sampler=EnergySampler(),
        ...                                 batch_size=1000, generator=torch.Generator().manual_seed(0))
        >>> _ = buffer.extend(TensorDict({"energy": torch.tensor([0.0, 1.0, 3.0])}, [3]))
        >>> buffer.sample()["index"].bincount(minlength=3).tolist()  # about 0 : 250 : 750
        [0, 254, 746]
    """

    def __init__(self, energy_key: NestedKey = "energy", epsilon: float = 0.0, *, fast: bool = True) -> None:
        check_number("epsilon", epsilon, low=0)
        self.energy_key = energy_key
        self.epsilon = float(epsilon)
        self._energy: torch.Tensor | None = None  # float64 energy + epsilon per stored row, valid as _written says
        self._written = WrittenRows() if fast else None  # None: the plain path
        self._cached_runs: _Runs | None = None  # valid while self._written.current(len(storage))
        self._starts: torch.Tensor | None = None  # first row of every run of equal energies (_Runs.starts)
        self._plain: tuple[int, _Runs | None] | None = None  # the plain path's (len(storage), runs), until a write

    @property
    def cache_bytes(self) -> int:
        """Bytes of the per-row energy copy (8 per row of the storage's capacity, from the first sample)."""
        return 0 if self._energy is None else self._energy.numel() * self._energy.element_size()

    @one_thread
    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        return self.draw(storage, batch_size), {}

    def draw(self, storage: Storage, *shape: int, rng: torch.Generator | None = None) -> torch.Tensor:
        """Row indices of the given shape drawn with probability ∝ energy (i.i.d., with replacement), with
        ``rng`` (default: the buffer's generator)."""
        n = check_sampleable(storage, self)
        rng = generator(self) if rng is None else rng
        u = torch.rand(shape, dtype=torch.float64, generator=rng)
        runs = self._runs(storage, n)
        if runs is None:  # no episode has energy yet: uniform
            return u.mul_(n).long().clamp_(max=n - 1)
        cdf, table, guide = runs.cdf, runs.table, runs.guide
        # The run whose cumulative energy first exceeds u: start at the guide table's entry for u's
        # bin and step forward while the run ends at or below u (a bin holds < 1 run boundary on
        # average). No binary search: on fresh random queries its branches mispredict.
        bins = len(guide)
        run = guide.take(u.mul(bins).long().clamp_(max=bins - 1))
        u.mul_(runs.total).clamp_(max=runs.below_total)
        for _ in range(_GUIDE_STEPS):
            run.add_(cdf.take(run) <= u)
        behind = cdf.take(run) <= u  # a bin with more boundaries than steps: search the rest
        if bool(behind.any()):
            run[behind] = torch.searchsorted(cdf, u[behind], right=True)
        # A row of that run by where u falls inside it: uniform, as the run's rows weigh the same.
        below, weight, start, length = table.index_select(0, run.view(-1)).view(*shape, 4).unbind(-1)
        within = torch.minimum(u.sub_(below).div_(weight).mul_(length).clamp_(min=0), length - 1, out=u)
        return start.add_(within).long()

    def _runs(self, storage: Storage, n: int) -> _Runs | None:
        """The drawable runs (``None`` if no row has energy), rebuilt after writes from the rows' energies,
        of which only the rows written since the last rebuild are read from the storage."""
        if self._written is None:  # the plain path: every stored energy read again after a write
            if self._plain is None or self._plain[0] != n:
                self._plain = (n, _Runs.of(self._read(storage, None, n)))
            return self._plain[1]
        if self._written.current(n):
            return self._cached_runs
        rows = self._written.take(n, 0 if self._energy is None else len(self._energy))
        energy = None if self._energy is None else self._energy[:n]
        if rows is None:  # everything: size the copy to the storage's capacity
            self._energy = torch.empty(max(n, int(getattr(storage, "max_size", n) or n)), dtype=torch.float64)
            energy = self._energy[:n]
            energy[:] = self._read(storage, None, n)
            self._starts = _Runs.starts(energy)
        elif len(rows):
            energy[rows] = self._read(storage, rows, len(rows))
            self._starts = _Runs.moved_starts(self._starts, energy, rows)
        self._cached_runs = _Runs.of(energy, self._starts)
        return self._cached_runs

    def _read(self, storage: Storage, rows: torch.Tensor | None, count: int) -> torch.Tensor:
        """``energy + epsilon`` (float64) of the stored ``rows`` (``None``: the first ``count``), checked."""
        energy = read_field(storage, self.energy_key, rows, self).reshape(count, -1)
        if energy.shape[1] != 1:
            raise ValueError(
                f"{self.energy_key!r} must hold one energy per transition, got {energy.shape[1]} values per row"
            )
        energy = energy[:, 0].to(torch.float64)
        if not torch.isfinite(energy).all() or (energy < 0).any():
            raise ValueError(f"energies under {self.energy_key!r} must be finite and >= 0")
        return energy + self.epsilon

    # Writes mark the rows whose energies are read again at the next rebuild of the runs (the plain path: all).
    def extend(self, index: torch.Tensor) -> None:
        self.mark_update(index)

    def add(self, index: int) -> None:
        self.mark_update(index)

    def mark_update(self, index, *, storage: Storage | None = None) -> None:
        if self._written is None:
            self._plain = None
        else:
            self._written.mark(index)

    def _empty(self) -> None:
        self._energy = self._cached_runs = self._starts = self._plain = None
        if self._written is not None:
            self._written.reset()

    def state_dict(self) -> dict[str, Any]:
        return OrderedDict(energy_key=self.energy_key, epsilon=self.epsilon)

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        key = state_dict["energy_key"]
        self.energy_key = tuple(key) if isinstance(key, list) else key
        self.epsilon = float(state_dict["epsilon"])
        self._plain = None
        if self._written is not None:
            self._written.reset()

    def dumps(self, path) -> None:
        dump_state(self.state_dict(), path)

    def loads(self, path) -> None:
        self.load_state_dict(load_state(path))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(energy_key={self.energy_key!r}, epsilon={self.epsilon})"
