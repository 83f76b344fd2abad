"""Alg. 1's candidates drawn ahead and scored from per-row caches: the plain path's batches at a fraction of its cost.

:class:`CandidatePool` is the seam between :class:`~gchgg.samplers.GraphCurriculumSampler` (the
algorithm: how candidates are drawn, what a stored row holds, F_div and F_prox) and its speed
devices, which change *when* those steps run, never what they compute:

- **Drawing ahead.** The candidates of the next ``draw_ahead`` samples are drawn and scored in one
  go (F_div and F_prox do not depend on λ), and each sample picks its best candidate with the λ of
  that moment. This spreads the fixed cost of the many small tensor operations of a draw over the
  samples; the draws are the same i.i.d. draws, and the same generator seed gives the same indices
  (without EBP, the candidates of the next ``draw_ahead`` samples are exactly
  ``torch.randint(len(storage), (draw_ahead, K, B), generator=buffer_generator)``).
- **Per-row cache** (:class:`~gchgg.fast.rows.RowCache`): each stored row's shortlist point and
  goal-to-target distance are computed once per write, so a draw reads neither goals nor targets
  from the storage and snaps no goal.
- **Nearest neighbours** (:class:`~gchgg.fast.nearest.NearestNeighbours`): F_div's K·B² pairs are
  never all read from the metric; a Euclidean shortlist proves each goal's nearest neighbour.

A write to the buffer between samples (``extend``/``add``/``mark_update``, reported to
:meth:`CandidatePool.written`) either drops the candidates drawn before it (``on_write="redraw"``,
what gchgg's training uses: every batch is drawn from the buffer as it is when sampled) or, with
``"keep"``, skips only the candidates that hold a row written since their draw: each sample takes
the next K that hold none (a pool is drawn when fewer than K are left). A chosen batch is therefore
always scored on its rows as they are, a write costs a gather over the pool's indices, and a loop
that writes before every sample draws a pool every few samples instead of at every one
(``benchmarks/samplers.py`` prints both policies against uniform sampling). The price of "keep":
rows written (or new to the storage, or whose energy changed) since the draw enter the candidates
with the next pool, at most ``draw_ahead − 1`` samples later.

Where no candidate drawn ahead goes unused (``draw_ahead=1``, or no write between samples) the pool
gives the plain path's indices and info bit for bit; ``tests/test_samplers.py`` holds the two equal.
The sampler's ``state_dict`` keeps :meth:`CandidatePool.state`: the generator state the current
candidates were drawn from and how many were used, so a restored buffer draws them again and
continues with the same batches (with ``"keep"``, only while no write has happened since the draw).
"""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from typing import Protocol

import torch

from gchgg.fast.nearest import NearestNeighbours
from gchgg.fast.rows import RowCache, RowReader

__all__ = ["ON_WRITE", "CandidatePool", "Steps"]

ON_WRITE = ("keep", "redraw")  # what a write does to the candidates drawn ahead (see the module's docstring)


class Steps(RowReader, Protocol):
    """What the pool asks of the algorithm (:class:`~gchgg.samplers.GraphCurriculumSampler`): its settings
    ``num_candidates`` (K) and ``draw_ahead``, and its steps."""

    num_candidates: int
    draw_ahead: int

    def draw_candidates(self, storage, n: int, shape: tuple[int, ...], rng: torch.Generator) -> torch.Tensor:
        """Candidate row indices of ``shape`` (``[C, B]``) among ``n`` stored rows, drawn with ``rng``."""
        ...

    def f_div(self, nearest: torch.Tensor) -> torch.Tensor:
        """F_div ``[...]`` (eq. 19) from each goal's nearest-neighbour distance ``[..., B]``."""
        ...

    def f_prox(self, distance: torch.Tensor) -> torch.Tensor:
        """F_prox ``[..., K]`` (eq. 15) from the goal-to-target distances ``[..., K, B]`` of K candidates."""
        ...


@dataclass
class _Drawn:
    """Scored candidate batches of the next samples, in draw order: indices ``[C, B]``, F_div and F_prox
    ``[C]`` (C = draw_ahead · K). Without writes, sample j gets candidates j·K … j·K + K − 1."""

    index: torch.Tensor
    diversity: torch.Tensor
    proximity: torch.Tensor
    per_sample: int  # K
    batch_size: int
    stored: int  # len(storage) when drawn
    rng_state: torch.Tensor  # the generator's state before the draw: the pool can be drawn again from it
    next: int = 0  # candidates before this position are used or skipped
    written: list = field(default_factory=list)  # rows written since the last sample (on_write="keep")
    notified: bool = False  # a write was reported since the draw
    usable: torch.Tensor | None = None  # [C] bool: holds no row written since the draw (None: all do)

    def take(self, marks: torch.Tensor) -> slice | torch.Tensor | None:
        """Positions of the next K candidates that hold no row written since the draw, a slice while no
        candidate was skipped (``None`` if fewer than K are left). ``marks``: all-False bool scratch,
        one per storage row (left all False)."""
        if self.written:  # skip the candidates the writes reached
            rows, self.written = torch.cat(self.written), []
            marks[rows] = True
            touched = marks[self.index[self.next :]].any(-1)  # a gather: faster than isin here
            marks[rows] = False
            if bool(touched.any()):
                if self.usable is None:
                    self.usable = torch.ones(len(self.index), dtype=torch.bool)
                self.usable[self.next :] &= ~touched
        k = self.per_sample
        if self.usable is None:
            if self.next + k > len(self.index):
                return None
            self.next += k
            return slice(self.next - k, self.next)
        ahead = self.usable[self.next :].nonzero().view(-1)[:k].add_(self.next)
        if len(ahead) < k:
            return None
        self.next = int(ahead[-1]) + 1
        return ahead


class CandidatePool:
    """Alg. 1's step 1 on the fast path: the K scored candidates of each sample, drawn ahead, from caches.

    :meth:`next` returns what the plain path computes for a sample (candidate indices ``[K, B]``,
    F_div and F_prox ``[K]``); the algorithm reports writes to :meth:`written`. Memory: the
    :class:`~gchgg.fast.rows.RowCache` (:attr:`nbytes`) and one drawn pool (C·B indices).
    """

    def __init__(self, nearest: NearestNeighbours) -> None:
        self.nearest = nearest
        self.cache = RowCache(nearest)
        self.drawn: _Drawn | None = None  # scored candidates of the next samples
        self.saved: dict | None = None  # a loaded state's pool, drawn again at the next sample

    @property
    def nbytes(self) -> int:
        """Bytes of the per-row cache (see :class:`~gchgg.fast.rows.RowCache`)."""
        return self.cache.nbytes

    def next(
        self, steps: Steps, storage, n: int, batch_size: int, rng: torch.Generator
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Candidate indices ``[K, B]`` and their F_div and F_prox ``[K]`` for the next sample of ``batch_size``
        from a storage of length ``n``, from the candidates drawn ahead, or from a pool drawn now with ``rng``."""
        if self.saved is not None:
            self.drawn = self._restore(steps, storage, n, batch_size)
        drawn, ahead = self.drawn, None
        if (
            drawn is not None
            and (drawn.batch_size, drawn.per_sample) == (batch_size, steps.num_candidates)
            and (drawn.stored == n or (drawn.stored < n and drawn.notified))  # else: changed without a write heard of
        ):
            ahead = drawn.take(self.cache.marks)
        if ahead is None:  # no pool, or too few usable candidates left in it
            drawn = self.drawn = self._score(steps, storage, n, batch_size, rng)
            ahead = drawn.take(self.cache.marks)
        return drawn.index[ahead], drawn.diversity[ahead], drawn.proximity[ahead]

    def _score(self, steps: Steps, storage, n: int, b: int, rng: torch.Generator) -> _Drawn:
        """Draw and score the candidate batches of the next ``draw_ahead`` samples."""
        rng_state = rng.get_state()
        k = steps.num_candidates
        index = steps.draw_candidates(storage, n, (steps.draw_ahead * k, b), rng)
        points, to_target, goals = self.cache.split(self.cache.gather(steps, storage, index, n))  # [C, B, ...]
        proximity = steps.f_prox(to_target.view(-1, k, b)).view(-1)
        diversity = steps.f_div(self.nearest.from_points(points, goals))
        return _Drawn(index, diversity, proximity, k, b, n, rng_state)

    def _restore(self, steps: Steps, storage, n: int, b: int) -> _Drawn | None:
        """The pool a loaded state was in the middle of, drawn again from its saved generator state
        (on a private generator: the buffer's own generator is restored by the buffer)."""
        saved, self.saved = self.saved, None
        if (saved["batch_size"], saved["stored"], saved["num_candidates"]) != (b, n, steps.num_candidates):
            return None  # the buffer or the request changed since: draw afresh
        rng = torch.Generator()
        rng.set_state(torch.frombuffer(bytearray(base64.b64decode(saved["rng_state"])), dtype=torch.uint8))
        drawn = self._score(steps, storage, n, b, rng)
        drawn.next = int(saved["next"]) * drawn.per_sample
        return drawn

    def written(self, index, on_write: str) -> None:
        """Rows (re)written: their cache entries are recomputed at the next draw, and candidates drawn
        before the write are dropped (``on_write="redraw"``, or a write not given as row indices) or
        skipped where they hold a written row (``"keep"``)."""
        self.saved = None
        drawn = self.drawn
        rows = torch.as_tensor(index) if isinstance(index, (int, torch.Tensor)) else None
        if on_write == "keep" and drawn is not None and rows is not None and not rows.is_floating_point():
            drawn.written.append(rows.reshape(-1).long())
            drawn.notified = True
        else:
            self.drawn = None
        self.cache.written.mark(index)

    def drop(self) -> None:
        """Forget the candidates drawn ahead (and a loaded state's): the next sample draws afresh."""
        self.drawn = self.saved = None

    def reset(self) -> None:
        """Forget everything: the candidates and the per-row cache (the buffer was emptied or loaded)."""
        self.cache.reset()
        self.drop()

    def state(self) -> dict | None:
        """Where the candidates drawn ahead stand (not the candidates: the generator state they were
        drawn from), so a restored buffer continues with the same batches; ``None`` for a fresh draw."""
        drawn = self.drawn
        if drawn is None or drawn.next == len(drawn.index):
            return self.saved
        if drawn.notified:  # written since the draw: drawing again would not give the candidates to skip
            return None
        return {
            "rng_state": base64.b64encode(drawn.rng_state.numpy().tobytes()).decode("ascii"),
            "next": drawn.next // drawn.per_sample,  # samples taken
            "batch_size": drawn.batch_size,
            "stored": drawn.stored,
            "num_candidates": drawn.per_sample,
        }

    def load(self, state: dict | None) -> None:
        """Start from a saved :meth:`state`: its pool is drawn again at the next sample."""
        self.reset()
        self.saved = state
