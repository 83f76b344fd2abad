"""Graph-curriculum sampler (Algorithm 1): best of K candidate batches by diversity (eq. 19) + λ·proximity (eq. 15)."""

from __future__ import annotations

import base64
import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tensordict import NestedKey
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

from gchgg.graph import Metric
from gchgg.samplers._storage import check_sampleable, dump_state, generator, load_state, read_field
from gchgg.samplers.energy import EnergySampler
from gchgg.samplers.tradeoff import Tradeoff, as_tradeoff
from gchgg.validation import check_choice, check_number

__all__ = ["SCALES", "GraphCurriculumSampler", "NearestNeighbours", "curriculum_objective", "nearest_neighbour_distances"]

SCALES = ("raw", "standardized")

_BOUND_TOLERANCE = 1e-3  # metres: slack on the Euclidean lower bound (float32 rounding of |a|² + |b|² − 2a·b)
_LEVEL_SLACK = 2  # levels added to every squared distance so float32 rounding never makes one negative
_TO_TARGET = 6  # column of the goal-to-target distance in the sampler's per-row cache (after the point)
_INT32_MAX = 2**31 - 1
_SWAP = torch.tensor([0, 1, 2, 4, 3])  # point columns (x, y, z, |p|², 1) -> (x, y, z, 1, |p|²)


@dataclass
class _Pool:
    """Scored candidate batches of the next samples: indices ``[A, K, B]``, F_div and F_prox ``[A, K]``."""

    index: torch.Tensor
    diversity: torch.Tensor
    proximity: torch.Tensor
    batch_size: int
    stored: int  # len(storage) when drawn
    rng_state: torch.Tensor  # the generator's state before the draw: the pool can be drawn again from it
    next: int = 0


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
    spread is ~40x the F_div spread, so any λ above ~0.03 picks the best-proximity candidate).
    ``scale="standardized"`` divides F_div and F_prox by their standard deviation across the K
    candidates of the sample (a term that does not vary is left as is), so λ = 1 weighs the two
    equally and a schedule's λ keeps its meaning as a ratio.

    ``info`` (a ``TensorDictReplayBuffer`` copies it into every sampled row) holds the chosen
    candidate's ``diversity`` (F_div) and ``proximity`` (F_prox, raw), the ``tradeoff`` λ, and
    three diagnostics of the choice: ``diversity_spread`` and ``proximity_spread``, the standard
    deviations across the K candidates of the two terms as they enter F (F_div and λ·F_prox, after
    scaling), and ``diversity_decided``, 1.0 when the chosen candidate is not the best-F_prox one.

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
    λ of that moment; any write to the buffer (``extend``/``add``/``mark_update``) drops the
    candidates drawn before it, so every batch comes from the buffer as it is when sampled. This
    spreads the fixed cost of the many small tensor operations of a draw over the samples; the
    draws are the same i.i.d. draws, and the same generator seed gives the same indices (without
    ``energy_key``, the candidates of the next ``draw_ahead`` samples are exactly
    ``torch.randint(len(storage), (draw_ahead, K, B), generator=buffer_generator)``). The
    sampler's ``state_dict`` (and so TorchRL's ``dumps``) keeps the generator state the current
    candidates were drawn from and how many of them were used, so a restored buffer draws them
    again and continues with the same batches.

    Per-row cache. Each stored row's shortlist point (the goal's lattice vertex relative to the
    field's centre, its squared norm and its vertex index; see :meth:`NearestNeighbours.points`) and
    its goal-to-target distance are computed once, at the first ``sample`` after the row is written
    (rows the buffer reports through ``extend``/``add``/``mark_update``, and rows new to the
    storage), and kept in a float32 ``[n, 7]`` tensor (28 bytes per stored row); ``sample`` then
    reads neither goals nor targets from the storage (except the goals for a diversity metric that
    is not a graph) and snaps no goal. Rows overwritten behind the sampler's back (TorchRL's
    ``buffer[index] = ...``, or another buffer writing into a full shared storage) keep stale
    entries until reported with ``sampler.mark_update(index)``.

    Cost per ``sample`` (amortised over ``draw_ahead``): an EBP or uniform draw of K·B rows (O(1)
    each), one read of K·B cached rows, a sort of K·B goals, K·B·96·5 multiply-adds and about ten
    passes over K·B·96 int32 keys, K·B·neighbours unchecked table reads and a few more per unproven
    goal. On push_new (``benchmarks/samplers.py``: 5,000 episodes, graph 31 × 31 × 11) about 2 %
    of the goals are unproven and the shortlist always equals the all-pairs value; the time is
    printed there as a ratio to uniform sampling.

    Args:
        metric: object with ``distance(a, b)`` on goals ``[..., 3]`` → ``[...]`` (``GoalGraph`` for
            GC-HGG, ``EuclideanMetric`` for the Euclidean ablation), used for F_prox (and F_div
            unless ``diversity_metric`` is given).
        num_candidates: K ≥ 1 candidate batches per sample. Default 8.
        tradeoff: λ ≥ 0 as a number or a schedule (:class:`~gchgg.samplers.AdaptiveTradeoff` for
            eq. 20, :class:`~gchgg.samplers.ExponentialTradeoff` for eq. 4), read at every sample.

    Keyword Args:
        goal_key: stored goal proximity is measured from. Default ``"desired_goal"`` (the goal each
            transition trains on, eq. 15).
        target_key: stored goal proximity is measured to. Default ``"target_goal"`` (eq. 15: the
            episode's target-task goal; with HGG store T* under its own key and name it here).
        diversity_key: stored goals whose nearest-neighbour distances make F_div. Default:
            ``goal_key``.
        scale: ``"raw"`` (default) or ``"standardized"``, see "Scale".
        energy_key: stored EBP energy; ``None`` (default) draws candidates uniformly.
        diversity_metric: metric of F_div if it differs from ``metric`` (the original code used
            Euclidean nearest neighbours). Default: ``metric``.
        neighbours: shortlist length (≥ 1) of the nearest-neighbour search, or ``None`` for all pairs.
            Default 3.
        unreachable_distance: metres an unreachable goal counts in F_prox; ``None`` (default) as
            described above.
        draw_ahead: samples whose candidates are drawn and scored together (≥ 1; see "Drawing
            ahead"). Default 8.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from gchgg.graph import EuclideanMetric
        >>> g = torch.Generator().manual_seed(0)
        >>> goals = torch.rand(1000, 3, generator=g)
        >>> transitions = TensorDict({"desired_goal": goals, "target_goal": torch.zeros(1000, 3)}, [1000])
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
        target_key: NestedKey = "target_goal",
        diversity_key: NestedKey | None = None,
        scale: str = "raw",
        energy_key: NestedKey | None = None,
        diversity_metric=None,
        neighbours: int | None = 3,
        unreachable_distance: float | None = None,
        draw_ahead: int = 8,
    ) -> None:
        for name, m in (("metric", metric), ("diversity_metric", diversity_metric)):
            if m is not None and not isinstance(m, Metric):
                raise TypeError(f"{name} must be a gchgg.graph.Metric (distance(a, b) and lattice: GoalGraph, EuclideanMetric), got {m!r}")
        check_number("num_candidates", num_candidates, integer=True, low=1)
        if neighbours is not None:
            check_number("neighbours (or None: all pairs)", neighbours, integer=True, low=1)
        if unreachable_distance is not None:
            check_number("unreachable_distance (or None)", unreachable_distance, low=0)
        check_choice("scale", scale, SCALES)
        check_number("draw_ahead (samples scored together)", draw_ahead, integer=True, low=1)
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
        self._energy = EnergySampler(energy_key) if energy_key is not None else None
        self._nearest = NearestNeighbours(self.diversity_metric, neighbours)
        # Per stored row: goal vertex and goal-to-target distance, valid for rows < _known not in _pending.
        self._rows: torch.Tensor | None = None
        self._known = 0
        self._pending: list[torch.Tensor] = []
        self._pool: _Pool | None = None  # scored candidates of the next samples, dropped at every write
        self._saved_pool: dict | None = None  # a loaded state's pool, drawn again at the next sample

    @property
    def cache_bytes(self) -> int:
        """Bytes of the per-row cache (28 per stored row, sized to the storage's capacity at the first sample)."""
        return 0 if self._rows is None else self._rows.numel() * self._rows.element_size()

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

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        n = check_sampleable(storage, self)
        if self._saved_pool is not None:
            self._pool = self._restore_pool(storage, n, batch_size)
        pool = self._pool
        if (
            pool is None
            or pool.next == len(pool.index)
            or (pool.batch_size, pool.stored, pool.index.shape[1]) != (batch_size, n, self.num_candidates)
        ):
            pool = self._pool = self._score(storage, n, batch_size)
        ahead, pool.next = pool.next, pool.next + 1
        lam = float(self.tradeoff.value)  # read now: λ may change between samples of one pool
        diversity, proximity = pool.diversity[ahead], pool.proximity[ahead]
        div_term, prox_term = curriculum_objective(diversity, proximity, lam, self.scale)
        best = int(torch.argmax(div_term + prox_term))
        info = {
            "diversity": diversity[best],
            "proximity": proximity[best],
            "tradeoff": torch.tensor(lam, dtype=torch.float32),
            "diversity_spread": div_term.std(correction=0),
            "proximity_spread": prox_term.std(correction=0),
            "diversity_decided": torch.tensor(float(best != int(torch.argmax(proximity)))),
        }
        return pool.index[ahead, best], info

    def _score(self, storage: Storage, n: int, b: int, rng: torch.Generator | None = None) -> _Pool:
        """Draw and score the candidate batches of the next ``draw_ahead`` samples (with the buffer's
        generator, or ``rng`` to draw a saved pool again)."""
        rng = generator(self) if rng is None else rng
        rng_state = rng.get_state()
        a, k = self.draw_ahead, self.num_candidates
        if self._energy is not None:
            self._energy._rng = rng
            index = self._energy.draw(storage, a * k, b).view(a, k, b)
        else:
            index = torch.randint(n, (a, k, b), generator=rng)
        rows = self._stored_rows(storage, index, n)  # [A, K, B, 7]: shortlist point (6), goal-to-target distance
        goals = None
        if not self._nearest.snaps:
            goals = read_field(storage, self.diversity_key, index, self).reshape(a * k, b, -1)
        nearest = self._nearest.from_points(rows[..., :_TO_TARGET].reshape(a * k, b, _TO_TARGET), goals)
        diversity = nearest.nan_to_num(posinf=0.0).sum(-1).view(a, k)  # eq. 19: no finite neighbour adds nothing
        proximity = -self._finite(rows[..., _TO_TARGET]).sum(-1)  # eq. 15 with C = 0, [A, K]
        return _Pool(index, diversity, proximity, b, n, rng_state)

    def _restore_pool(self, storage: Storage, n: int, b: int) -> _Pool | None:
        """The pool a loaded state was in the middle of, drawn again from its saved generator state
        (on a private generator: the buffer's own generator is restored by the buffer)."""
        saved, self._saved_pool = self._saved_pool, None
        if (saved["batch_size"], saved["stored"], saved["num_candidates"]) != (b, n, self.num_candidates):
            return None  # the buffer or the request changed since: draw afresh
        rng = torch.Generator()
        rng.set_state(torch.frombuffer(bytearray(base64.b64decode(saved["rng_state"])), dtype=torch.uint8))
        pool = self._score(storage, n, b, rng)
        pool.next = int(saved["next"])
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
        """Cached ``[..., 7]`` of rows ``index``: the goal's shortlist point (see
        :meth:`NearestNeighbours.points`) and its goal-to-target distance, computed once per written row."""
        if self._rows is None or n != self._known or self._pending:
            self._refresh(storage, n)
        return self._rows.index_select(0, index.view(-1)).view(*index.shape, _TO_TARGET + 1)

    def _refresh(self, storage: Storage, n: int) -> None:
        """Compute the cache entries of rows written since the last sample (and of rows new to the storage)."""
        cache = self._rows
        fresh = [index[index < min(n, self._known)] for index in self._pending]
        if cache is None or len(cache) < n:
            size = max(n, int(getattr(storage, "max_size", n) or n))
            grown = torch.empty(size, _TO_TARGET + 1)
            if cache is not None:
                grown[: self._known] = cache[: self._known]
            cache, self._known = grown, 0
            fresh = []
        if n > self._known:
            fresh.append(torch.arange(self._known, n))
        self._rows, self._known, self._pending = cache, n, []
        fresh = torch.cat(fresh) if fresh else torch.empty(0, dtype=torch.long)
        if not len(fresh):
            return
        goals = read_field(storage, self.goal_key, fresh, self)
        targets = read_field(storage, self.target_key, fresh, self)
        diverse = goals if self.diversity_key == self.goal_key else read_field(storage, self.diversity_key, fresh, self)
        cache[fresh, :_TO_TARGET] = self._nearest.points(diverse)
        cache[fresh, _TO_TARGET] = _check(self.metric.distance(goals, targets), "metric")

    def _forget(self, index) -> None:
        """Mark (re)written rows: their cache entries are recomputed at the next sample, and candidates
        drawn before the write are dropped."""
        self._pool = self._saved_pool = None
        if self._rows is None:
            return
        if isinstance(index, (int, torch.Tensor, np.ndarray)) and not torch.as_tensor(index).is_floating_point():
            self._pending.append(torch.as_tensor(index).reshape(-1).long())
        else:  # a slice or anything else: recompute everything
            self._rows = None

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
        self._rows, self._known, self._pending, self._pool, self._saved_pool = None, 0, [], None, None
        if self._energy is not None:
            self._energy._empty()

    def state_dict(self) -> dict[str, Any]:
        return OrderedDict(
            num_candidates=self.num_candidates,
            neighbours=self.neighbours,
            unreachable_distance=self.unreachable_distance,
            draw_ahead=self.draw_ahead,
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
        return {
            "rng_state": base64.b64encode(pool.rng_state.numpy().tobytes()).decode("ascii"),
            "next": pool.next,
            "batch_size": pool.batch_size,
            "stored": pool.stored,
            "num_candidates": int(pool.index.shape[1]),
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.num_candidates = int(state_dict["num_candidates"])
        self.neighbours = None if state_dict["neighbours"] is None else int(state_dict["neighbours"])
        self.unreachable_distance = state_dict["unreachable_distance"]
        self.draw_ahead = int(state_dict.get("draw_ahead", self.draw_ahead))
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


def nearest_neighbour_distances(
    goals: torch.Tensor, metric, neighbours: int | None = 3, *, block: int = 32, stats: dict | None = None
) -> torch.Tensor:
    """Metric distance from each goal to its nearest other goal of the same batch: min_{j≠i} d(g_i, g_j).

    A one-off :class:`NearestNeighbours` (which keeps its scratch memory between calls).

    Args:
        goals: ``[K, B, 3]``: K batches of B goals.
        metric: object with ``distance(a, b)``.
        neighbours: shortlist length, ``None`` for all pairs.
        block: goals per block of the shortlist search (see :class:`NearestNeighbours`).
        stats: if given, ``stats["rescored"]`` is set to the number of goals the shortlist did not
            prove (for which the goals within the Euclidean bound were read too).

    Returns:
        float32 ``[K, B]``, ``inf`` where a goal has no finite distance to any other (or B = 1).
    """
    return NearestNeighbours(metric, neighbours, block)(goals, stats=stats)


class NearestNeighbours:
    """Exact nearest-neighbour metric distances within batches of goals, via a Euclidean shortlist.

    Each goal becomes a *point* once (:meth:`points`, which a sampler can cache per stored row):
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
        metric: object with ``distance(a, b)`` on goals ``[..., 3]``.
        neighbours: shortlist length ≥ 1, or ``None`` to score all pairs with the metric.
        block: goals per block (≥ 2); batches of at most ``3 · block`` goals are one block.
    """

    def __init__(self, metric, neighbours: int | None = 3, block: int = 32) -> None:
        check_number("block", block, integer=True, low=2)
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
        self._scratch: dict[Any, Any] = {}

    @property
    def snaps(self) -> bool:
        """Whether the metric has a :class:`~gchgg.graph.Lattice` whose vertices goals are snapped to."""
        return self._snap

    def points(self, goals: torch.Tensor) -> torch.Tensor:
        """float32 ``[..., 6]`` shortlist points of goals ``[..., 3]``: ``(x, y, z, |p|², 1, id)``.

        ``p`` is the goal's lattice vertex (graph metrics; off-graph goals: a parking spot far outside
        the field) or the goal itself, relative to a fixed origin (the field's centre, or the first
        goals' mean); ``id`` is the vertex index (``-1`` off the graph) or 0.
        """
        goals = torch.as_tensor(goals)
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
                flat = goals.reshape(-1, 3)
                self._origin = flat.mean(0) if len(flat) else torch.zeros(3)
                self._axis = int(flat.std(0).argmax()) if len(flat) > 1 else 0
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
        self._park = torch.zeros(3)
        self._park[self._axis] = self._reach

    def __call__(self, goals: torch.Tensor, *, stats: dict | None = None) -> torch.Tensor:
        """Nearest-neighbour distances ``[K, B]`` of goals ``[K, B, 3]``."""
        goals = torch.as_tensor(goals)
        return self.from_points(self.points(goals), None if self._snap else goals, stats=stats)

    def from_points(
        self, points: torch.Tensor, goals: torch.Tensor | None = None, *, stats: dict | None = None
    ) -> torch.Tensor:
        """Nearest-neighbour distances ``[K, B]`` from the goals' :meth:`points` ``[K, B, 6]`` (made by this
        object). A metric without a graph also needs the goals ``[K, B, 3]`` themselves."""
        k, b = points.shape[:2]
        if b < 2:
            return torch.full((k, b), math.inf)
        if not self._snap and goals is None:
            raise ValueError("NearestNeighbours.from_points: a metric without a graph needs the goals [K, B, 3]")
        m = self.neighbours
        if m is None or m >= b - 1:  # all pairs
            if stats is not None:
                stats["rescored"] = 0
            distance = self._pairs(points[..., 5].long(), goals)(
                torch.arange(b).view(1, b, 1), torch.arange(b).view(1, 1, b), torch.arange(k).view(k, 1, 1)
            ).clone()
            distance.diagonal(dim1=-2, dim2=-1).fill_(math.inf)
            return distance.min(-1).values

        if self._snap:
            self._setup_graph()
        # Sorted along the axis, neighbours in space are mostly neighbours in the order.
        order = torch.from_numpy(np.argsort(points[..., self._axis].numpy(), -1))  # faster than torch's here
        points = points.gather(1, order.unsqueeze(-1).expand(points.shape))
        if goals is not None and not self._snap:
            goals = goals.gather(1, order.unsqueeze(-1).expand(k, b, goals.shape[-1]))
        vertex = points[..., 5].long()  # [K, B]: -1 off the graph (and 0 for other metrics)
        pair = self._pairs(vertex, goals)
        cols, bound = self._shortlist(points, m)  # sorted positions [K, B, m], lower bound [K, B] on the rest
        if self._snap:  # the same lookup as pair(rows, cols, batch), with fewer index operations
            candidates = vertex.gather(1, cols.reshape(k, b * m)).view(k, b, m)
            nearest = self._lookup(vertex.unsqueeze(-1), candidates).amin(-1)  # [K, B]
        else:
            nearest = pair(torch.arange(b).view(1, b, 1), cols, torch.arange(k).view(k, 1, 1)).amin(-1)
        # Proven where the shortlist beats every goal outside it (a distance of 0, a duplicate goal,
        # always does). For the others, only goals nearer in a straight line than the best distance
        # so far can be nearer: read those (usually a handful) from the metric too.
        unproven = nearest > bound
        if self._snap:
            unproven &= vertex >= 0  # an off-graph goal is inf from everything
        if stats is not None:
            stats["rescored"] = int(unproven.sum())
        if bool(unproven.any()):
            kk, ii = unproven.nonzero(as_tuple=True)
            best = nearest[kk, ii]
            planar = points[..., :3].transpose(1, 2)  # [K, 3, B]: coordinate planes, for a fast sum
            straight = (planar[kk] - points[kk, ii, :3].unsqueeze(-1)).square_().sum(1).sqrt_()  # [U, B]
            straight.sub_(self._tolerance()).scatter_(1, ii.unsqueeze(1), math.inf)  # not itself
            uu, jj = (straight < best.unsqueeze(-1)).nonzero(as_tuple=True)
            if len(uu):
                best = best.scatter_reduce(0, uu, pair(ii[uu], jj, kk[uu]), reduce="amin")
                nearest[kk, ii] = best
        return torch.empty_like(nearest).scatter_(1, order, nearest)

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
                return _check(metric.distance(goals[batch, rows], goals[batch, cols]), "diversity metric")

        return pair

    def _lookup(self, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
        """Graph distance between vertex indices (the graph's unchecked lookup where it has one)."""
        return self._graph.pair_distance(i, j)  # unchecked: the indices come from the graph

    def _tolerance(self) -> float:
        """Metres the straight-line bound is lowered by: float32 rounding, and for a graph half its
        table's resolution (its distances are rounded to it)."""
        return _BOUND_TOLERANCE + (0.5 * float(self._graph.resolution) if self._snap else 0.0)

    def _shortlist(self, points: torch.Tensor, m: int) -> tuple[torch.Tensor, torch.Tensor]:
        """For points sorted along the axis ``[K, B, 6]``: each one's m nearest others in its window, as
        sorted positions ``[K, B, m]``, and a lower bound in metres ``[K, B]`` on its straight-line
        distance to every other goal (outside the window: the gap along the axis)."""
        k, b, _ = points.shape
        layout = self._layout(b, m)
        size, pad, blocks, width, stride = (layout[key] for key in ("size", "pad", "blocks", "width", "stride"))
        levels = _levels(stride)
        # |p_i − p_j| ≤ 2·max|p|: no pair is above the top level, so no clamp is needed. For a graph
        # max|p| is the parking distance; otherwise it is read from the points.
        reach = self._reach if self._snap else float(points[..., 3].amax()) ** 0.5
        quantum = max(4.0 * reach * reach, 1e-12) / levels
        left = points[..., :5]  # [p, |p|², 1]
        rows = blocks * size
        if pad or rows != b:  # padding rows (zeros, masked below) around the sorted goals
            padded = left.new_zeros(k, rows + 2 * pad, 5)
            padded[:, pad : pad + b] = left
        else:
            padded = left
        # [p, |p|², 1] -> [-2p, 1, |p|² + slack·q] / q (padding rows -> [0, 0, slack]).
        scale, shift = self._product_map(quantum)
        right = torch.addcmul(shift, padded.index_select(-1, _SWAP), scale)
        windows = right.unfold(1, width, size).reshape(k * blocks, 5, width)
        own = padded[:, pad : pad + rows].reshape(k * blocks, size, 5)
        squared = self._buffer("squared", (k * blocks, size, width), torch.float32)
        torch.bmm(own, windows, out=squared)  # squared distance in levels, + _LEVEL_SLACK
        # In place (same 4-byte slots, element by element: one scratch matrix, half the cache footprint).
        keys = squared.view(torch.int32)
        keys.copy_(squared)  # truncation: level + slack - 1 <= key level <= level + slack (float32 rounding < 1 level)
        # key = level · S + column (S: a power of two >= W), above every pair's key for the goal itself
        # and padding columns.
        blocked = keys.view(k, blocks, size, width)
        torch.add(layout["offset"], blocked, alpha=stride, out=blocked)
        flat, mask = keys.view(-1), stride - 1
        starts = self._row_starts(k * blocks * size, width).view(k * blocks, size, 1)  # flat index of each row
        nearest = []
        for _ in range(m):
            low = keys.amin(-1, keepdim=True)  # [K·blocks, size, 1]
            nearest.append(low)
            flat.index_fill_(0, torch.add(starts, low.bitwise_and(mask)).view(-1), _INT32_MAX)
        cols = torch.cat(nearest, -1).bitwise_and_(mask).long().view(k, rows, m)
        cols = cols[:, :b].add_(layout["first"])  # window column -> sorted position
        bound = _distance(keys.amin(-1).view(k, rows)[:, :b].bitwise_right_shift_(stride.bit_length() - 1), quantum)
        # Goals outside the window are at least the gap along the axis away.
        axis = points[..., self._axis]
        ends = torch.cat([axis.new_full((k, 1), -math.inf), axis, axis.new_full((k, 1), math.inf)], 1)
        gap = torch.minimum(axis - ends[:, layout["before"]], ends[:, layout["after"]] - axis)
        return cols, torch.minimum(bound, gap).sub_(self._tolerance()).clamp_(min=0.0)

    def _layout(self, b: int, m: int) -> dict[str, Any]:
        """Block geometry for B goals, kept per (B, m): block size, padding, number of blocks, window
        width, the keys' column numbers, the mask of excluded keys (a goal itself, padding), each
        sorted position's first window position, and its nearest goals outside the window (indices
        into the axis values with -inf / +inf put at both ends)."""
        cached = self._scratch.get(("layout", b, m))
        if cached is not None:
            return cached
        size = self.block
        if b > 3 * size and size > m:
            pad, blocks, width = size, -(-b // size), 3 * size
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
        offset = column.expand(blocks, size, width) + excluded * ((_levels(stride) + 2 * _LEVEL_SLACK + 2) * stride)
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

    def _product_map(self, quantum: float) -> tuple[torch.Tensor, torch.Tensor]:
        """``scale, shift`` with ``[p, 1, |p|²] · scale + shift = [-2p, 1, |p|² + slack·q] / q`` (kept per quantum)."""
        cached = self._scratch.get("map")
        if cached is None or cached[0] != quantum:
            scale = torch.tensor([-2.0, -2.0, -2.0, 1.0, 1.0]) / quantum
            shift = torch.tensor([0.0, 0.0, 0.0, 0.0, float(_LEVEL_SLACK)])
            cached = self._scratch["map"] = (quantum, (scale, shift))
        return cached[1]

    def _buffer(self, name: str, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        buffer = self._scratch.get(name)
        if buffer is None or buffer.shape != shape:
            buffer = self._scratch[name] = torch.empty(shape, dtype=dtype)
        return buffer


def _levels(stride: int) -> int:
    """Squared-distance levels for keys ``level · stride + column`` (room is left for excluded entries)."""
    return _INT32_MAX // stride - 4 * _LEVEL_SLACK - 4


def _distance(level: torch.Tensor, quantum: float) -> torch.Tensor:
    """A lower bound in metres on the distance of a pair whose key has this level: the level less the
    slack and one more for float32 rounding (at least 0), times the quantum, square-rooted."""
    return (level - (_LEVEL_SLACK + 1)).clamp_(min=0).float().mul_(quantum).sqrt_()


def _check(distance: torch.Tensor, name: str) -> torch.Tensor:
    distance = torch.as_tensor(distance)
    if bool(torch.isnan(distance).any()):
        raise ValueError(f"the {name} returned NaN distances; goals must be finite")
    return distance
