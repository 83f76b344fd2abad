"""Graph-curriculum sampler (Algorithm 1): best of K candidate batches by diversity (eq. 19) + λ·proximity (eq. 15).

The nearest-neighbour search F_div needs lives in :mod:`gchgg.fast.nearest`.
"""

from __future__ import annotations

import base64
import math
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import NestedKey
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

from gchgg.common.validation import check_choice, check_number
from gchgg.fast.nearest import NearestNeighbours, check_distances
from gchgg.graph import Metric
from gchgg.samplers._storage import (
    WrittenRows,
    check_sampleable,
    dump_state,
    generator,
    init_signature,
    load_state,
    one_thread,
    read_field,
)
from gchgg.samplers.energy import EnergySampler
from gchgg.samplers.tradeoff import Tradeoff, as_tradeoff

__all__ = ["ON_WRITE", "SCALES", "GraphCurriculumSampler", "curriculum_objective"]

SCALES = ("raw", "standardized")
ON_WRITE = ("keep", "redraw")  # what a write does to the candidates drawn ahead, see "Drawing ahead"


@dataclass
class _Pool:
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


@init_signature
class GraphCurriculumSampler(Sampler):
    """Curriculum-guided sampling (Algorithm 1 of GC-HGG) as a TorchRL ``Sampler``.

    Each ``sample(storage, B)`` draws ``K = num_candidates`` candidate mini-batches A_1 … A_K of B
    stored transitions (with EBP, i.e. ∝ episode energy, when ``energy_key`` is given, uniformly
    otherwise), scores each

        F(A) = F_div(A) + λ · F_prox(A),
        F_div(A)  = Σ_{g_i ∈ A} min_{j ≠ i} d(g_i, g_j)                    (eq. 19)
        F_prox(A) = C − Σ_{g_i ∈ A} d(g_i, g*_i)                          (eq. 15, reported with C = 0)

    with g_i the transition's goal (``goal_key``, the hindsight goal it trains on) and g*_i the
    target-task goal of its episode (``target_key``), and returns the indices of the best
    candidate. C shifts every candidate equally and does not change the choice. The goals whose
    diversity is scored can be another stored key (``diversity_key``; the authors' code used the
    transitions' achieved goals), and proximity can be measured between any two stored goals (the
    authors' code: ``goal_key="achieved_goal", target_key="desired_goal"``, i.e. closeness to
    success).

    Scale. ``scale="raw"`` is the formula above untouched: both sums grow with B, and their spreads
    across the candidates, not λ's nominal value, decide which term wins (on push_new the F_prox
    spread dwarfs the F_div spread: on a recorded buffer, diversity decides 28 %, 3 % and 0 % of the
    choices at λ = 0.1, 1 and 10; ``tests/test_samplers.py -k standardized`` prints it).
    ``scale="standardized"`` divides F_div and F_prox by their standard deviation across the K
    candidates of the sample (a term that does not vary is left as is), so λ = 1 weighs the two
    equally and a schedule's λ keeps its meaning as a ratio.

    ``info`` (a ``TensorDictReplayBuffer`` copies it into every sampled row) holds the chosen
    candidate's ``diversity`` (F_div) and ``proximity`` (F_prox, raw) and the ``tradeoff`` λ. With
    ``diagnostics=True`` it also holds three diagnostics of the choice: ``diversity_spread`` and
    ``proximity_spread``, the standard deviations across the K candidates of the two terms as they
    enter F (F_div and λ·F_prox, after scaling), and ``diversity_decided``, 1.0 when the chosen
    candidate is not the best-F_prox one (gchgg's training logs them). They are off by default
    because TorchRL's buffer copies every info entry into the batch, one key at a time
    (``benchmarks/samplers.py`` prints a plain buffer's sample with and without them).

    Distances that are ``inf`` (a goal off the graph: outside the field, inside an inflated
    obstacle, or cut off) never produce NaN: in F_prox such a distance counts as
    ``unreachable_distance`` (by default the largest finite goal-to-target distance of the K·B drawn
    transitions, so an unreachable goal is "as far as the farthest one"); in F_div a goal without a
    finite nearest neighbour contributes 0 (an off-graph goal adds no diversity).

    Nearest neighbours (F_div). The K·B² pairs are never all scored with the metric (a full
    256 × 256 graph-table gather per candidate would be random reads into a ~100 MB table). Each
    candidate's goals are sorted along the field's longest axis and compared, in blocks, with
    their 3 · 32 neighbours in that order (one batched matrix product of squared Euclidean
    distances and ``neighbours + 1`` minimum passes), which gives every goal a shortlist of its
    ``neighbours`` Euclidean-nearest goals there; the metric is read for those K·B·neighbours pairs
    only. The shortlist is *exact*: for a metric that is never shorter than the straight line,
    every other goal is at least the next Euclidean distance in the block window, or the gap along
    the axis to the window's edge, away; where the shortlist's best metric distance is within that
    bound the nearest neighbour is proven, and for the few goals where it is not (beside an
    obstacle, or in a sparse stretch) the metric is also read for every goal nearer in a straight
    line than the best distance found. For a metric with a :class:`~gchgg.graph.Lattice` (a
    :class:`~gchgg.graph.GoalGraph`: ``metric.lattice`` is not ``None``) the straight lines are
    measured between the goals' lattice vertices, which the graph distance never undercuts (up to
    its table's rounding), and each goal is snapped once. A metric shorter than the straight line
    makes the shortlist approximate; ``neighbours=None`` scores all pairs (exact for any metric).
    See :class:`NearestNeighbours`.

    Drawing ahead. The candidates of the next ``draw_ahead`` samples are drawn and scored in one
    go (F_div and F_prox do not depend on λ), and each ``sample`` picks its best candidate with the
    λ of that moment. This spreads the fixed cost of the many small tensor operations of a draw
    over the samples; the draws are the same i.i.d. draws, and the same generator seed gives the
    same indices (without ``energy_key``, the candidates of the next ``draw_ahead`` samples are
    exactly ``torch.randint(len(storage), (draw_ahead, K, B), generator=buffer_generator)``).
    A write to the buffer (``extend``/``add``/``mark_update``) between samples does, with
    ``on_write="keep"`` (the default), not throw the candidates away: the candidates drawn ahead
    that hold a row written since their draw are skipped, and each sample takes the next K that
    hold none (a pool is drawn when fewer than K are left). A chosen batch is therefore always
    scored on its rows as they are, a write costs a gather over the pool's indices, and a loop that
    writes before every sample draws a pool every few samples instead of at every one
    (``benchmarks/samplers.py`` prints the loop against uniform sampling). The price: the pool
    comes from the buffer as it was at the draw, so rows written (or new to the storage, or whose
    energy changed) since the draw enter the candidates with the next pool, at most
    ``draw_ahead − 1`` samples later.
    ``on_write="redraw"`` (what gchgg's training uses) drops the candidates drawn before any write,
    so every batch is drawn from the buffer as it is when sampled. The sampler's ``state_dict``
    (and so TorchRL's ``dumps``) keeps the generator state the current candidates were drawn from
    and how many of them were used, so a restored buffer draws them again and continues with the
    same batches (with ``"keep"``, only while no write has happened since the draw; otherwise the
    restored sampler draws afresh).

    Per-row cache. Each stored row's shortlist point (the goal's lattice vertex relative to the
    field's centre, its squared norm and its vertex index; see :meth:`NearestNeighbours.points`) and
    its goal-to-target distance are computed once, at the first ``sample`` after the row is written
    (rows the buffer reports through ``extend``/``add``/``mark_update``, and rows new to the
    storage), and kept in a float32 ``[n, d + 4]`` tensor for d-D goals (28 bytes per stored row
    for 3-D goals; ``[n, 2·d + 4]`` with the goal itself for a diversity metric without a lattice,
    which reads goals; plus one byte per row of scratch for the writes "Drawing ahead" skips; EBP
    candidates add the energies' float64 copy, 8 bytes per row, see :class:`EnergySampler`); ``sample`` then
    reads neither goals nor targets from the storage and snaps no goal. Rows overwritten behind
    the sampler's back (TorchRL's ``buffer[index] = ...``, or another buffer writing into a full
    shared storage) keep stale entries until reported with ``sampler.mark_update(index)``.

    Cost per ``sample`` (amortised over ``draw_ahead``): an EBP or uniform draw of K·B rows (O(1)
    each), one read of K·B cached rows, a sort of K·B goals, K·B·96·5 multiply-adds and about ten
    passes over K·B·96 int32 keys, K·B·neighbours unchecked table reads and a few more per unproven
    goal. On push_new (``benchmarks/samplers.py``: 5,000 episodes, graph 31 × 31 × 11) about 2 %
    of the goals are unproven and the shortlist always equals the all-pairs value; the time is
    printed there as a ratio to uniform sampling.

    Goals. Stored goals are ``[d]`` per transition, any dimension d ≥ 1 (a 2-D maze, 3-D positions,
    a joint configuration); ``goal_key`` and ``target_key`` must have the same d, and a metric with a
    lattice (:class:`~gchgg.graph.GoalGraph`) the d of its field. The first sample checks them and
    names the key and shape that do not fit.

    Args:
        metric: a :class:`~gchgg.graph.Metric`: ``distance(a, b)`` on goals ``[..., d]`` →
            ``[...]`` (any float dtype; cast to float32) and ``lattice`` (``GoalGraph`` for GC-HGG,
            ``EuclideanMetric`` for the Euclidean ablation, or your own), used for F_prox (and F_div
            unless ``diversity_metric`` is given).
        num_candidates: K ≥ 1 candidate batches per sample. Default 8.
        tradeoff: λ ≥ 0 as a number or a schedule (:class:`~gchgg.samplers.AdaptiveTradeoff` for
            eq. 20, :class:`~gchgg.samplers.ExponentialTradeoff` for eq. 4), read at every sample.

    Keyword Args:
        goal_key: stored goal proximity is measured from. Default ``"desired_goal"`` (the goal each
            transition trains on, eq. 15).
        target_key: stored goal proximity is measured to. Default ``"task_goal"`` (eq. 15: the
            target task's goal T* of the transition's episode, as
            :class:`~gchgg.transforms.HindsightRelabel` stores it).
        diversity_key: stored goals whose nearest-neighbour distances make F_div. Default:
            ``goal_key``.
        scale: ``"raw"`` (default) or ``"standardized"``, see "Scale".
        energy_key: stored EBP energy; ``None`` (default) draws candidates uniformly.
        diversity_metric: metric of F_div if it differs from ``metric`` (the original code used
            Euclidean nearest neighbours). Default: ``metric``.
        neighbours: shortlist length (≥ 1) of the nearest-neighbour search, ``None`` for all pairs, or
            ``"auto"`` (default: 3 for a graph metric, 1 for a metric without a lattice; see
            :class:`NearestNeighbours`). The batches chosen do not depend on it.
        unreachable_distance: metres an unreachable goal counts in F_prox; ``None`` (default) as
            described above.
        draw_ahead: samples whose candidates are drawn and scored together (≥ 1; see "Drawing
            ahead"). Default 8.
        on_write: ``"keep"`` (default) or ``"redraw"``: what a buffer write does to the candidates
            drawn ahead (see "Drawing ahead").
        diagnostics: also return the choice's diagnostics in ``info`` (see above). Default ``False``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from gchgg.graph import EuclideanMetric
        >>> g = torch.Generator().manual_seed(0)
        >>> goals = torch.rand(1000, 3, generator=g)
        >>> transitions = TensorDict({"desired_goal": goals, "task_goal": torch.zeros(1000, 3)}, [1000])
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
        target_key: NestedKey = "task_goal",
        diversity_key: NestedKey | None = None,
        scale: str = "raw",
        energy_key: NestedKey | None = None,
        diversity_metric=None,
        neighbours: int | str | None = "auto",
        unreachable_distance: float | None = None,
        draw_ahead: int = 8,
        on_write: str = "keep",
        diagnostics: bool = False,
    ) -> None:
        for name, m in (("metric", metric), ("diversity_metric", diversity_metric)):
            if m is not None and not isinstance(m, Metric):
                raise TypeError(f"{name} must be a gchgg.graph.Metric (distance(a, b) and lattice: GoalGraph, "
                                f"EuclideanMetric), got {m!r}")
        check_number("num_candidates", num_candidates, integer=True, low=1)
        if unreachable_distance is not None:
            check_number("unreachable_distance (or None)", unreachable_distance, low=0)
        check_choice("scale", scale, SCALES)
        check_number("draw_ahead (samples scored together)", draw_ahead, integer=True, low=1)
        check_choice("on_write", on_write, ON_WRITE)
        self.metric = metric
        self.diversity_metric = metric if diversity_metric is None else diversity_metric
        self.num_candidates = num_candidates
        self.tradeoff = as_tradeoff(tradeoff)
        self.goal_key = goal_key
        self.target_key = target_key
        self.diversity_key = goal_key if diversity_key is None else diversity_key
        self.scale = scale
        self.energy_key = energy_key
        self.unreachable_distance = unreachable_distance
        self.draw_ahead = draw_ahead
        self.on_write = on_write
        self.diagnostics = bool(diagnostics)
        self._energy = EnergySampler(energy_key) if energy_key is not None else None
        self._nearest = NearestNeighbours(self.diversity_metric, neighbours)
        # Per-row cache columns for d-D goals: the point (d + 3), the goal-to-target distance, and the
        # diversity goal (d) for a metric without a lattice; set at the first sample, when d is known.
        self._width = self._to_target = 0
        # Per stored row: the goal's shortlist point and goal-to-target distance, valid as _written says.
        self._rows: torch.Tensor | None = None
        self._marks: torch.Tensor | None = None  # one bool per stored row, all False: scratch of _Pool.take
        self._written = WrittenRows()
        self._pool: _Pool | None = None  # scored candidates of the next samples (see "Drawing ahead")
        self._saved_pool: dict | None = None  # a loaded state's pool, drawn again at the next sample

    @property
    def cache_bytes(self) -> int:
        """Bytes of the per-row caches, sized to the storage's capacity at the first sample: 4·(d + 4) + 1 per
        row for d-D goals (29 for 3-D; 4·(2·d + 4) + 1 for a diversity metric without a lattice), and 8 more
        with EBP candidates (their energies)."""
        rows = 0 if self._rows is None else self._rows.numel() * self._rows.element_size() + len(self._marks)
        return rows + (0 if self._energy is None else self._energy.cache_bytes)

    def stop_curriculum(self) -> None:
        """From now on, plain sampling: one candidate per sample (EBP or uniform, as the candidates are
        drawn), as GC-HGG does once HGG's stop condition switches the run to target goals. Kept in
        ``state_dict``."""
        self.num_candidates = 1
        self._pool = self._saved_pool = None

    @property
    def neighbours(self) -> int | None:
        """Shortlist length of the nearest-neighbour search (``None``: all pairs)."""
        return self._nearest.neighbours

    @neighbours.setter
    def neighbours(self, value: int | None) -> None:
        self._nearest.neighbours = value

    @one_thread
    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        n = check_sampleable(storage, self)
        if self._saved_pool is not None:
            self._pool = self._restore_pool(storage, n, batch_size)
        pool, ahead = self._pool, None
        if (
            pool is not None
            and (pool.batch_size, pool.per_sample) == (batch_size, self.num_candidates)
            and (pool.stored == n or (pool.stored < n and pool.notified))  # else: changed without a write we heard of
        ):
            ahead = pool.take(self._marks)
        if ahead is None:  # no pool, or too few usable candidates left in it
            pool = self._pool = self._score(storage, n, batch_size)
            ahead = pool.take(self._marks)
        lam = float(self.tradeoff.value)  # read now: λ may change between samples of one pool
        diversity, proximity = pool.diversity[ahead], pool.proximity[ahead]
        div_term, prox_term = curriculum_objective(diversity, proximity, lam, self.scale)
        best = int(torch.argmax(div_term + prox_term))
        info = {
            "diversity": diversity[best],
            "proximity": proximity[best],
            "tradeoff": torch.tensor(lam, dtype=torch.float32),
        }
        if self.diagnostics:
            info["diversity_spread"] = div_term.std(correction=0)
            info["proximity_spread"] = prox_term.std(correction=0)
            info["diversity_decided"] = torch.tensor(float(best != int(torch.argmax(proximity))))
        chosen = ahead.start + best if isinstance(ahead, slice) else int(ahead[best])
        return pool.index[chosen], info

    def _score(self, storage: Storage, n: int, b: int, rng: torch.Generator | None = None) -> _Pool:
        """Draw and score the candidate batches of the next ``draw_ahead`` samples (with the buffer's
        generator, or ``rng`` to draw a saved pool again)."""
        rng = generator(self) if rng is None else rng
        rng_state = rng.get_state()
        k = self.num_candidates
        index = self._draw(storage, n, (self.draw_ahead * k, b), rng)
        diversity, proximity = self._objectives(storage, index, n)
        return _Pool(index, diversity, proximity, k, b, n, rng_state)

    def _draw(self, storage: Storage, n: int, shape: tuple[int, ...], rng: torch.Generator) -> torch.Tensor:
        """Candidate row indices of ``shape`` (``[C, B]``): EBP with ``energy_key``, else uniform."""
        if self._energy is not None:
            return self._energy.draw(storage, *shape, rng=rng)
        return torch.randint(n, shape, generator=rng)

    def _objectives(self, storage: Storage, index: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """F_div and F_prox ``[C]`` of the candidate batches ``index`` ``[C, B]``."""
        # [C, B, d + 4 (+ d)]: shortlist point, goal-to-target distance (goal)
        rows = self._stored_rows(storage, index, n)
        to_target = rows[..., self._to_target].view(-1, self.num_candidates, index.shape[-1])  # [A, K, B]
        proximity = -self._finite(to_target).sum(-1).view(-1)  # eq. 15 with C = 0
        return self._diversity(rows), proximity

    def _diversity(self, rows: torch.Tensor) -> torch.Tensor:
        """F_div ``[C]`` of C candidate batches from their cached rows ``[C, B, width]``."""
        to_target = self._to_target
        goals = None if self._nearest.snaps else rows[..., to_target + 1 :]
        nearest = self._nearest.from_points(rows[..., :to_target], goals)
        return nearest.nan_to_num(posinf=0.0).sum(-1)  # eq. 19: no finite neighbour adds nothing

    def _restore_pool(self, storage: Storage, n: int, b: int) -> _Pool | None:
        """The pool a loaded state was in the middle of, drawn again from its saved generator state
        (on a private generator: the buffer's own generator is restored by the buffer)."""
        saved, self._saved_pool = self._saved_pool, None
        if (saved["batch_size"], saved["stored"], saved["num_candidates"]) != (b, n, self.num_candidates):
            return None  # the buffer or the request changed since: draw afresh
        rng = torch.Generator()
        rng.set_state(torch.frombuffer(bytearray(base64.b64decode(saved["rng_state"])), dtype=torch.uint8))
        pool = self._score(storage, n, b, rng)
        pool.next = int(saved["next"]) * pool.per_sample
        return pool

    def _finite(self, distance: torch.Tensor) -> torch.Tensor:
        """Goal-to-target distances ``[A, K, B]`` with ``inf`` replaced (per sample: its K·B draws)."""
        finite = torch.isfinite(distance)
        if bool(finite.all()):
            return distance
        if self.unreachable_distance is not None:
            fill = torch.tensor(float(self.unreachable_distance))
        else:  # the largest finite distance of the sample's draws (0 if there is none)
            fill = distance.masked_fill(~finite, -math.inf).amax((1, 2), keepdim=True).clamp_(min=0.0)
        return torch.where(finite, distance, fill)

    def _stored_rows(self, storage: Storage, index: torch.Tensor, n: int) -> torch.Tensor:
        """Cached ``[..., d + 4]`` of rows ``index``: the goal's shortlist point (see
        :meth:`NearestNeighbours.points`) and its goal-to-target distance, computed once per written row."""
        if not self._written.current(n):
            self._refresh(storage, n)
        return self._rows.index_select(0, index.view(-1)).view(*index.shape, self._width)

    def _refresh(self, storage: Storage, n: int) -> None:
        """Compute the cache entries of rows written since the last sample (and of rows new to the storage)."""
        fresh = self._written.take(n, 0 if self._rows is None else len(self._rows))
        rebuild = fresh is None
        if rebuild:  # everything: the cache is sized to the storage's capacity below
            fresh = torch.arange(n)
        if not len(fresh):
            return
        goals = self._goals(storage, self.goal_key, fresh, _lattice_dim(self.metric), "the metric's lattice")
        targets = self._goals(storage, self.target_key, fresh, goals.shape[-1], repr(self.goal_key))
        if self.diversity_key == self.goal_key and self._nearest.dim in (None, goals.shape[-1]):
            diverse = goals
        else:
            diverse = self._goals(storage, self.diversity_key, fresh, self._nearest.dim,
                                  "the diversity metric's lattice")
        points = self._nearest.points(diverse)  # checks the diversity goals' d against the diversity metric
        distance = check_distances(self.metric.distance(goals, targets), "metric", (len(fresh),))
        if rebuild:
            self._to_target = points.shape[-1]
            self._width = self._to_target + 1 + (0 if self._nearest.snaps else diverse.shape[-1])
            self._rows = torch.empty(max(n, int(getattr(storage, "max_size", n) or n)), self._width)
            self._marks = torch.zeros(len(self._rows), dtype=torch.bool)  # scratch of _Pool.take
        cache, to_target = self._rows, self._to_target
        cache[fresh, :to_target] = points
        cache[fresh, to_target] = distance
        if not self._nearest.snaps:  # the goals themselves: the metric reads them
            cache[fresh, to_target + 1 :] = diverse.to(cache.dtype)

    def _goals(self, storage: Storage, key: NestedKey, rows: torch.Tensor, dim: int | None = None, like: str = ""):
        """Stored goals ``[len(rows), d]`` under ``key``, checked: one vector of d ≥ 1 values per row
        (``dim`` of them, as ``like`` has, when given)."""
        goals = read_field(storage, key, rows, self)
        if goals.ndim != 2 or goals.shape[1] < 1 or (dim is not None and goals.shape[1] != dim):
            allowed = f"[{dim}] like {like}" if dim is not None else "[d] with d >= 1 (a 1-D goal is stored as [1])"
            raise ValueError(
                f"{type(self).__name__} reads goals {key!r} from the storage as one vector per transition, "
                f"{allowed}; got {tuple(goals.shape[1:])} per transition"
            )
        return goals

    def _forget(self, index) -> None:
        """Mark (re)written rows: their cache entries are recomputed at the next sample, and candidates
        drawn before the write are dropped (``on_write="redraw"``, or a write not given as row indices)
        or rescored where they hold a written row (``"keep"``)."""
        self._saved_pool = None
        pool = self._pool
        rows = torch.as_tensor(index) if isinstance(index, (int, torch.Tensor)) else None
        if self.on_write == "keep" and pool is not None and rows is not None and not rows.is_floating_point():
            pool.written.append(rows.reshape(-1).long())
            pool.notified = True
        else:
            self._pool = None
        self._written.mark(index)

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
        self._rows = self._pool = self._saved_pool = None
        self._written.reset()
        if self._energy is not None:
            self._energy._empty()

    def state_dict(self) -> dict[str, Any]:
        return OrderedDict(
            num_candidates=self.num_candidates,
            neighbours=self.neighbours,
            unreachable_distance=self.unreachable_distance,
            draw_ahead=self.draw_ahead,
            on_write=self.on_write,
            scale=self.scale,
            tradeoff=dict(self.tradeoff.state_dict()),
            pool=self._pool_state(),
        )

    def _pool_state(self) -> dict | None:
        """Where the candidates drawn ahead stand (not the candidates: the generator state they were
        drawn from), so a restored buffer continues with the same batches."""
        pool = self._pool
        if pool is None or pool.next == len(pool.index):
            return self._saved_pool
        if pool.notified:  # written since the draw: drawing again would not give the candidates to skip
            return None
        return {
            "rng_state": base64.b64encode(pool.rng_state.numpy().tobytes()).decode("ascii"),
            "next": pool.next // pool.per_sample,  # samples taken
            "batch_size": pool.batch_size,
            "stored": pool.stored,
            "num_candidates": pool.per_sample,
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.num_candidates = int(state_dict["num_candidates"])
        self.neighbours = None if state_dict["neighbours"] is None else int(state_dict["neighbours"])
        self.unreachable_distance = state_dict["unreachable_distance"]
        self.draw_ahead = int(state_dict.get("draw_ahead", self.draw_ahead))
        self.on_write = state_dict.get("on_write", self.on_write)
        self.scale = state_dict.get("scale", self.scale)
        self.tradeoff.load_state_dict(state_dict["tradeoff"])
        self._empty()
        self._saved_pool = state_dict.get("pool")

    def dumps(self, path) -> None:
        dump_state(self.state_dict(), path)

    def loads(self, path) -> None:
        self.load_state_dict(load_state(path))

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(metric={self.metric!r}, num_candidates={self.num_candidates}, "
            f"tradeoff={self.tradeoff!r}, scale={self.scale!r}, energy_key={self.energy_key!r}, "
            f"neighbours={self.neighbours})"
        )


def _lattice_dim(metric) -> int | None:
    """The goal dimension of a metric's lattice (its field's), ``None`` without one."""
    lattice = metric.lattice
    return None if lattice is None else len(lattice.field[0])


def curriculum_objective(
    diversity: torch.Tensor, proximity: torch.Tensor, tradeoff: float, scale: str = "raw"
) -> tuple[torch.Tensor, torch.Tensor]:
    """The two terms of F(A) = F_div(A) + λ·F_prox(A) (Alg. 1, eq. 3) for K candidates ``[..., K]``.

    ``scale="raw"`` returns ``(F_div, λ·F_prox)``; ``"standardized"`` first divides each term by its
    standard deviation across the K candidates (population std; a term with zero spread is left as
    it is, so the result is never NaN). The chosen candidate is ``argmax`` of their sum.

    >>> div, prox = torch.tensor([1.0, 2.0, 3.0]), torch.tensor([-30.0, -20.0, -10.0])
    >>> [t.tolist() for t in curriculum_objective(div, prox, 0.5)]
    [[1.0, 2.0, 3.0], [-15.0, -10.0, -5.0]]
    >>> d, p = curriculum_objective(torch.tensor([1.0, 2.0]), torch.tensor([-4.0, -8.0]), 1.0, "standardized")
    >>> d.tolist(), p.tolist()
    ([2.0, 4.0], [-2.0, -4.0])
    """
    if scale == "standardized":
        diversity = diversity / _spread(diversity)
        proximity = proximity / _spread(proximity)
    else:
        check_choice("scale", scale, SCALES)
    return diversity, tradeoff * proximity


def _spread(x: torch.Tensor) -> torch.Tensor:
    """Standard deviation across the last dimension, 1 where it is 0 (or not finite)."""
    std = x.std(-1, correction=0, keepdim=True)
    return torch.where(torch.isfinite(std) & (std > 0), std, torch.ones_like(std))
