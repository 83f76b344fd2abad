"""Graph-curriculum sampler (Algorithm 1): best of K candidate batches by diversity (eq. 19) + λ·proximity (eq. 15).

Its speed devices sit apart, in :mod:`gchgg.fast`: the candidates drawn ahead and the per-row
caches in :mod:`gchgg.fast.candidates`, F_div's nearest-neighbour search in :mod:`gchgg.fast.nearest`.
With ``fast=False`` the sampler calls none of them (nor EBP's, :class:`~gchgg.samplers.EnergySampler`).

In a plain TorchRL buffer:

    >>> from tensordict import TensorDict
    >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
    >>> from gchgg.graph import EuclideanMetric
    >>> g = torch.Generator().manual_seed(0)
    >>> goals = torch.rand(1000, 3, generator=g)
    >>> transitions = TensorDict({"desired_goal": goals, "task_goal": torch.zeros(1000, 3)}, [1000])
    >>> sampler = GraphCurriculumSampler(EuclideanMetric(), num_candidates=8, tradeoff=10.0)
    >>> buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), sampler=sampler, batch_size=64,
    ...                                 generator=g)
    >>> _ = buffer.extend(transitions)
    >>> batch = buffer.sample()
    >>> batch["tradeoff"][0].item(), "diversity" in batch and "proximity" in batch
    (10.0, True)
    >>> bool(batch["desired_goal"].norm(dim=-1).mean() < goals.norm(dim=-1).mean())  # nearer its targets
    True
"""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import Any

import torch
from tensordict import NestedKey
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

from gchgg.common.validation import check_choice, check_distances, check_number
from gchgg.fast.candidates import ON_WRITE, CandidatePool
from gchgg.fast.nearest import NearestNeighbours
from gchgg.graph import Metric
from gchgg.samplers._storage import (
    check_goal_rows,
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
    target-task goal of its episode (``target_key``), and returns the indices of the best candidate
    (C shifts every candidate equally). F_div can score another stored goal (``diversity_key``; the
    authors' code: the achieved goals) under another metric (``diversity_metric``), and F_prox can
    measure between any two stored goals (the authors' code: ``goal_key="achieved_goal",
    target_key="desired_goal"``, closeness to success). Goals are ``[d]`` per transition, any d ≥ 1.

    Scale. ``"raw"`` is the formula untouched: both sums grow with B, and their spreads across the
    candidates, not λ's nominal value, decide which term wins (``tests/test_samplers.py -k
    standardized`` prints how often diversity decides). ``"standardized"`` divides F_div and F_prox by
    their standard deviation across the K candidates (unless 0): λ = 1 weighs them equally.

    ``info`` (copied into every sampled row) holds the chosen candidate's ``diversity`` (F_div),
    ``proximity`` (F_prox) and the ``tradeoff`` λ; with ``diagnostics=True`` also ``diversity_spread``
    and ``proximity_spread`` (std across the K candidates of F_div and λ·F_prox as they enter F) and
    ``diversity_decided`` (1.0 when the chosen candidate is not the best-F_prox one).

    Distances that are ``inf`` (a goal off the graph) never produce NaN: in F_prox such a distance
    counts as ``unreachable_distance`` (by default the largest finite goal-to-target distance of the
    sample's K·B draws); in F_div a goal without a finite nearest neighbour contributes 0.

    Speed. ``fast=True`` (default) runs step 1 on :class:`~gchgg.fast.candidates.CandidatePool`: the
    candidates of the next ``draw_ahead`` samples drawn and scored in one go, per-row caches
    (:attr:`cache_bytes`), exact nearest neighbours through a Euclidean shortlist. ``fast=False`` runs
    it as written in :meth:`candidates` (all pairs, goals read at every sample; EBP's plain path too) and
    calls no speed device: the same indices and info bit for bit wherever no candidate drawn ahead goes
    unused (``draw_ahead=1``, or no write before a pool is used up).

    Args:
        metric: a :class:`~gchgg.graph.Metric` (``GoalGraph`` for GC-HGG, ``EuclideanMetric`` for the
            Euclidean ablation, or your own; distances cast to float32), for F_prox and F_div.
        num_candidates: K ≥ 1 candidate batches per sample. Default 8.
        tradeoff: λ ≥ 0 as a number or a schedule (:class:`~gchgg.samplers.AdaptiveTradeoff`, eq. 20),
            read at every sample.

    Keyword Args:
        goal_key, target_key: the stored goals F_prox measures from and to. Default ``"desired_goal"``
            and ``"task_goal"`` (eq. 15, as :class:`~gchgg.transforms.HindsightRelabel` stores them).
        diversity_key, diversity_metric: the stored goals F_div scores, and its metric. Default: the above.
        scale: ``"raw"`` (default) or ``"standardized"``, see "Scale".
        energy_key: stored EBP energy; ``None`` (default) draws candidates uniformly.
        neighbours: shortlist length (≥ 1) of the nearest-neighbour search, ``None`` for all pairs, or
            ``"auto"`` (default; :class:`~gchgg.fast.nearest.NearestNeighbours`: 3 with a lattice, 1 without).
            The batches do not depend on it; the plain path keeps it for its state only.
        unreachable_distance: metres an unreachable goal counts in F_prox; ``None`` (default): see above.
        draw_ahead, on_write: samples whose candidates are drawn and scored together (≥ 1, default 8);
            ``"keep"`` (default) or ``"redraw"`` them at a write (:mod:`gchgg.fast.candidates`).
        diagnostics: also return the choice's diagnostics in ``info``. Default ``False``.
        fast: step 1 on the fast path (default) or the plain one, see "Speed".
    """

    def __init__(
        self, metric, num_candidates: int = 8, tradeoff: Tradeoff | float = 0.0, *,
        goal_key: NestedKey = "desired_goal", target_key: NestedKey = "task_goal",
        diversity_key: NestedKey | None = None, scale: str = "raw", energy_key: NestedKey | None = None,
        diversity_metric=None, neighbours: int | str | None = "auto", unreachable_distance: float | None = None,
        draw_ahead: int = 8, on_write: str = "keep", diagnostics: bool = False, fast: bool = True,
    ) -> None:  # fmt: skip
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
        self.metric, self.num_candidates, self.tradeoff = metric, num_candidates, as_tradeoff(tradeoff)
        self.diversity_metric = metric if diversity_metric is None else diversity_metric
        self.goal_key, self.target_key = goal_key, target_key
        self.diversity_key = goal_key if diversity_key is None else diversity_key
        self.scale, self.energy_key, self.unreachable_distance = scale, energy_key, unreachable_distance
        self.draw_ahead, self.on_write, self.diagnostics = draw_ahead, on_write, bool(diagnostics)
        self._energy = EnergySampler(energy_key, fast=fast) if energy_key is not None else None
        lattice = self.diversity_metric.lattice  # F_div's goals: the lattice's vertices, of its dimension
        self._snaps, self._dim = lattice is not None, None if lattice is None else len(lattice.field[0])
        if fast:  # the fast path of step 1
            self._nearest = NearestNeighbours(self.diversity_metric, neighbours)
            self._pool = CandidatePool(self._nearest)
        else:  # the plain path reads all pairs; the setting is checked and kept (state_dict), as the engine keeps it
            self._nearest = self._pool = None
            self._neighbours = _neighbours(neighbours, self._snaps)

    @one_thread
    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        n, rng = check_sampleable(storage, self), generator(self)
        # 1. K candidate mini-batches A_1 … A_K of B transitions, drawn with EBP (uniformly without
        #    energy_key), and their F_div (eq. 19) and F_prox (eq. 15): [K, B], [K], [K]
        if self._pool is None:
            index, diversity, proximity = self.candidates(storage, n, batch_size, rng)
        else:  # the same, drawn ahead and scored from per-row caches (gchgg.fast.candidates)
            index, diversity, proximity = self._pool.next(self, storage, n, batch_size, rng)
        # 2. F(A) = F_div(A) + λ·F_prox(A), with λ as it is now
        lam = float(self.tradeoff.value)
        div_term, prox_term = curriculum_objective(diversity, proximity, lam, self.scale)
        # 3. the best candidate, reported with its scores
        best = int(torch.argmax(div_term + prox_term))
        info = {"diversity": diversity[best], "proximity": proximity[best],
                "tradeoff": torch.tensor(lam, dtype=torch.float32)}  # fmt: skip
        if self.diagnostics:
            info["diversity_spread"] = div_term.std(correction=0)
            info["proximity_spread"] = prox_term.std(correction=0)
            info["diversity_decided"] = torch.tensor(float(best != int(torch.argmax(proximity))))
        return index[best], info

    def candidates(self, storage: Storage, n: int, b: int, rng: torch.Generator):
        """Step 1 as written (``fast=False``): K candidates ``[K, B]`` drawn now with ``rng`` from ``n`` stored
        rows, and their F_div and F_prox ``[K]`` from the stored goals, nearest neighbours from all pairs."""
        k = self.num_candidates
        index = self.draw_candidates(storage, n, (k, b), rng)
        goals, to_target = self.read_rows(storage, index.view(-1))
        if not self._snaps:  # F_div reads float32 goals (a lattice metric: the stored goals' vertices)
            goals = goals.to(torch.float32)
        goals = goals.view(k, b, -1)
        pairs = self.diversity_metric.distance(goals.unsqueeze(2), goals.unsqueeze(1))  # [K, B, B]
        pairs = check_distances(pairs, "diversity metric", (k, b, b)).clone()
        pairs.diagonal(dim1=1, dim2=2).fill_(math.inf)  # j ≠ i
        # summed as a strided column, as the fast path caches them: float32 sums depend on the memory layout
        to_target = torch.stack([to_target, to_target], -1)[..., 0].view(k, b)
        return index, self.f_div(pairs.amin(-1)), self.f_prox(to_target)

    def draw_candidates(self, storage: Storage, n: int, shape: tuple[int, ...], rng: torch.Generator) -> torch.Tensor:
        """Candidate row indices of ``shape`` (``[C, B]``): EBP with ``energy_key``, else uniform."""
        if self._energy is not None:
            return self._energy.draw(storage, *shape, rng=rng)
        return torch.randint(n, shape, generator=rng)

    def read_rows(self, storage: Storage, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The diversity goals ``[N, d]`` and goal-to-target distances ``[N]`` of stored ``rows`` (checked)."""
        lattice = self.metric.lattice
        goals = self._goals(storage, self.goal_key, rows, None if lattice is None else len(lattice.field[0]),
                            "the metric's lattice")
        targets = self._goals(storage, self.target_key, rows, goals.shape[-1], repr(self.goal_key))
        dim = self._dim if self._nearest is None else self._nearest.dim  # the engine also learns d from goals
        if self.diversity_key == self.goal_key and dim in (None, goals.shape[-1]):
            diverse = goals
        else:
            diverse = self._goals(storage, self.diversity_key, rows, dim, "the diversity metric's lattice")
        return diverse, check_distances(self.metric.distance(goals, targets), "metric", (len(rows),))

    def _goals(self, storage: Storage, key: NestedKey, rows: torch.Tensor, dim: int | None, like: str):
        return check_goal_rows(read_field(storage, key, rows, self), key, self, dim, like)

    def f_div(self, nearest: torch.Tensor) -> torch.Tensor:
        """F_div ``[...]`` (eq. 19) from nearest-neighbour distances ``[..., B]`` (an ``inf`` one adds nothing)."""
        return nearest.nan_to_num(posinf=0.0).sum(-1)

    def f_prox(self, distance: torch.Tensor) -> torch.Tensor:
        """F_prox ``[..., K]`` (eq. 15, C = 0) from goal-to-target distances ``[..., K, B]``; ``inf`` counts as
        ``unreachable_distance``, by default the largest finite distance of the sample's K·B (0 if none)."""
        finite = torch.isfinite(distance)
        if not bool(finite.all()):
            if self.unreachable_distance is not None:
                fill = torch.tensor(float(self.unreachable_distance))
            else:
                fill = distance.masked_fill(~finite, -math.inf).amax((-2, -1), keepdim=True).clamp_(min=0.0)
            distance = torch.where(finite, distance, fill)
        return -distance.sum(-1)

    @property
    def cache_bytes(self) -> int:
        """Bytes of the per-row caches (:class:`~gchgg.fast.rows.RowCache`; with EBP also the energies' copy)."""
        rows = 0 if self._pool is None else self._pool.nbytes
        return rows + (0 if self._energy is None else self._energy.cache_bytes)

    @property
    def neighbours(self) -> int | None:
        """Shortlist length of the nearest-neighbour search (``None``: all pairs)."""
        return self._neighbours if self._nearest is None else self._nearest.neighbours

    @neighbours.setter
    def neighbours(self, value: int | None) -> None:
        if self._nearest is None:
            self._neighbours = value
        else:
            self._nearest.neighbours = value

    def stop_curriculum(self) -> None:
        """From now on one candidate per sample (EBP or uniform), as GC-HGG does once HGG's stop condition
        switches the run to target goals. Kept in ``state_dict``."""
        self.num_candidates = 1
        if self._pool is not None:
            self._pool.drop()

    def mark_update(self, index, *, storage: Storage | None = None) -> None:
        """Rows (re)written: EBP's energies and the rows' cached entries are read again, and the candidates
        drawn ahead are dropped or skipped where they hold a written row (``on_write``)."""
        if self._pool is not None:
            self._pool.written(index, self.on_write)
        if self._energy is not None:
            self._energy.mark_update(index)

    extend = add = mark_update  # the buffer's writes, reported with the rows written

    def _empty(self) -> None:
        if self._pool is not None:
            self._pool.reset()
        if self._energy is not None:
            self._energy._empty()

    def state_dict(self) -> dict[str, Any]:
        return OrderedDict(
            num_candidates=self.num_candidates, neighbours=self.neighbours,
            unreachable_distance=self.unreachable_distance, draw_ahead=self.draw_ahead, on_write=self.on_write,
            scale=self.scale, tradeoff=dict(self.tradeoff.state_dict()),
            pool=None if self._pool is None else self._pool.state(),
        )  # fmt: skip

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.num_candidates = int(state_dict["num_candidates"])
        self.neighbours = None if state_dict["neighbours"] is None else int(state_dict["neighbours"])
        self.unreachable_distance = state_dict["unreachable_distance"]
        self.draw_ahead = int(state_dict.get("draw_ahead", self.draw_ahead))
        self.on_write = state_dict.get("on_write", self.on_write)
        self.scale = state_dict.get("scale", self.scale)
        self.tradeoff.load_state_dict(state_dict["tradeoff"])
        self._empty()
        if self._pool is not None:
            self._pool.load(state_dict.get("pool"))

    def dumps(self, path) -> None:
        dump_state(self.state_dict(), path)

    def loads(self, path) -> None:
        self.load_state_dict(load_state(path))

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(metric={self.metric!r}, num_candidates={self.num_candidates}, "
                f"tradeoff={self.tradeoff!r}, scale={self.scale!r}, energy_key={self.energy_key!r}, "
                f"neighbours={self.neighbours})")  # fmt: skip


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


def _neighbours(neighbours: int | str | None, lattice: bool) -> int | None:
    """The ``neighbours`` setting checked and ``"auto"`` resolved as :class:`~gchgg.fast.nearest.NearestNeighbours`
    does (3 with a lattice, 1 without; ``tests/test_plain.py`` holds the two equal), for the plain path's state."""
    if neighbours == "auto":
        return 3 if lattice else 1
    if neighbours is not None:
        check_number('neighbours (or None: all pairs, or "auto")', neighbours, integer=True, low=1)
    return neighbours


def _spread(x: torch.Tensor) -> torch.Tensor:
    """Standard deviation across the last dimension, 1 where it is 0 (or not finite)."""
    std = x.std(-1, correction=0, keepdim=True)
    return torch.where(torch.isfinite(std) & (std > 0), std, torch.ones_like(std))
