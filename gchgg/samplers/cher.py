"""CHER's curriculum sampler: greedy facility-location selection of a mini-batch from a candidate pool (eqs. 1–4)."""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from tensordict import NestedKey
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

from gchgg.common.validation import check_distances, check_number
from gchgg.graph import EuclideanMetric, Metric
from gchgg.samplers._storage import (
    check_sampleable,
    dump_state,
    generator,
    init_signature,
    load_state,
    one_thread,
    read_field,
)
from gchgg.samplers.tradeoff import ExponentialTradeoff, Tradeoff, as_tradeoff

__all__ = ["CherSampler", "lazier_than_lazy_greedy", "nearest_other"]


@init_signature
class CherSampler(Sampler):
    """Curriculum-guided HER (Fang et al. 2019) selection, the baseline of the paper's Table I.

    Each ``sample(storage, B)`` runs CHER's algorithm as published with its code:

    1. draw a pool of ``pool_size`` stored transitions uniformly (HER copies are already stored,
       so the pool mixes relabelled and original goals 4 : 1 like CHER's HER sampling);
    2. build the k-nearest-neighbour graph of the pool's goals (Euclidean, k-d tree, self
       excluded; k = ``neighbours``, 1 in CHER) with similarities s = exp(−d² / mean(d)²);
    3. pick B pool entries greedily, "lazier than lazy greedy": at each of the B steps draw
       ``subset_size`` (3 in CHER) not yet chosen entries uniformly and keep the one with the largest
       facility-location gain Σ_v max(0, s(v, c) − cover(v)) − λ · d(g_c, g*_c), then raise every
       cover(v) to s(v, c). d is ``metric`` between the goal and ``target_key`` (eq. 1; CHER's code
       measured to the transition's achieved goal: ``target_key="achieved_goal"``).

    The B greedy steps are sequential by nature, but each reads only the cover of the entries whose
    neighbour its candidates are, and with k = 1 that cover is still 0 whenever the candidate is
    free, so a candidate's gain is fixed: :func:`lazier_than_lazy_greedy` scores many steps at once
    and keeps those no earlier step changed, with the plain loop's choices. A sample costs one k-d
    tree over the pool's distinct goals (:func:`nearest_other`) and a few vectorised passes
    (``benchmarks/samplers.py`` times both). Unlike CHER's code the cover is only
    updated with the chosen entry (CHER's loop also kept the cover of a better-scoring but finally
    rejected subset member; with k = 1 the gains are the same either way). An unreachable goal
    (``inf``) counts as the largest finite distance of the pool, as in
    :class:`~gchgg.samplers.GraphCurriculumSampler`.

    ``info`` (copied into every sampled row by a ``TensorDictReplayBuffer``): ``diversity``, the
    facility-location value Σ_v cover(v) of the chosen batch over the pool (each pool entry's best
    similarity to a chosen entry, so it grows with B and at most ``pool_size``: higher = the batch
    covers more of the pool's goals); ``proximity``, −Σ d(g, g*) over the chosen batch; ``tradeoff``, λ.

    Args:
        metric: proximity metric (a :class:`~gchgg.graph.Metric` on goals ``[..., d]``, any d ≥ 1; its
            distances are cast to float32). Default :class:`~gchgg.graph.EuclideanMetric`.
        pool_size: candidates per sample, ≥ B + subset_size − 1. Default 5,000 (GC-HGG's CHER runs
            drew one candidate per stored episode of a 5,000-episode buffer; CHER's own code drew
            128 for a batch of 64).
        tradeoff: λ as a number or schedule. Default ``ExponentialTradeoff(lambda_0=1, tau=0.005)``
            (eq. 4), which the training loop steps once per iteration.

    Keyword Args:
        goal_key: stored goal. Default ``"desired_goal"``.
        target_key: stored goal proximity is measured to. Default ``"task_goal"`` (the target task's
            goal T*, as :class:`~gchgg.transforms.HindsightRelabel` stores it).
        neighbours: k of the similarity graph (≥ 1). Default 1.
        subset_size: random candidates per greedy step (≥ 1). Default 3.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> g = torch.Generator().manual_seed(0)
        >>> data = TensorDict({"desired_goal": torch.rand(500, 3, generator=g),
        ...                    "task_goal": torch.zeros(500, 3)}, [500])
        >>> buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(500), batch_size=32, generator=g,
        ...                                 sampler=CherSampler(pool_size=200, tradeoff=10.0))
        >>> _ = buffer.extend(data)
        >>> batch = buffer.sample()
        >>> batch["tradeoff"][0].item(), batch.batch_size
        (10.0, torch.Size([32]))
        >>> # λ = 10 favours goals near their target (the origin) over the buffer's average
        >>> bool(batch["desired_goal"].norm(dim=-1).mean() < data["desired_goal"].norm(dim=-1).mean())
        True
    """

    def __init__(
        self,
        metric=None,
        pool_size: int = 5000,
        tradeoff: Tradeoff | float | None = None,
        *,
        goal_key: NestedKey = "desired_goal",
        target_key: NestedKey = "task_goal",
        neighbours: int = 1,
        subset_size: int = 3,
    ) -> None:
        metric = EuclideanMetric() if metric is None else metric
        if not isinstance(metric, Metric):
            raise TypeError(f"metric must be a gchgg.graph.Metric (distance(a, b) and lattice), got {metric!r}")
        for name, value in (("pool_size", pool_size), ("neighbours", neighbours), ("subset_size", subset_size)):
            check_number(name, value, integer=True, low=1)
        self.metric = metric
        self.pool_size = pool_size
        self.tradeoff = as_tradeoff(ExponentialTradeoff(1.0, 0.005) if tradeoff is None else tradeoff)
        self.goal_key = goal_key
        self.target_key = target_key
        self.neighbours = neighbours
        self.subset_size = subset_size

    @one_thread
    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        n = check_sampleable(storage, self)
        if self.pool_size < batch_size + self.subset_size - 1:
            raise ValueError(
                f"CherSampler needs pool_size >= batch_size + subset_size - 1 = {batch_size + self.subset_size - 1} "
                f"to choose {batch_size} distinct entries, got pool_size={self.pool_size}"
            )
        rng = generator(self)
        pool = torch.randint(n, (self.pool_size,), generator=rng)
        goals = self._goals(self.goal_key, read_field(storage, self.goal_key, pool, self))
        targets = self._goals(self.target_key, read_field(storage, self.target_key, pool, self), goals.shape[1])

        distance = check_distances(self.metric.distance(goals, targets), "metric", (self.pool_size,))
        finite = torch.isfinite(distance)
        if not bool(finite.all()):
            distance = torch.where(finite, distance, distance[finite].max() if bool(finite.any()) else 0.0)
        lam = float(self.tradeoff.value)
        penalty = lam * distance.to(torch.float32)

        neighbour, similarity = self.similarity_graph(goals)  # [P, k] each

        chosen, cover = lazier_than_lazy_greedy(neighbour, similarity, penalty, batch_size, self.subset_size, rng)
        info = {
            "diversity": cover.sum(),  # facility-location value of the chosen set
            "proximity": -distance[chosen].sum().to(torch.float32),
            "tradeoff": torch.tensor(lam, dtype=torch.float32),
        }
        return pool[chosen], info

    def _goals(self, key: NestedKey, goals: torch.Tensor, dim: int | None = None) -> torch.Tensor:
        """Pool goals ``[P, d]`` read under ``key``, checked (d ≥ 1; ``dim`` when given, the goals' d)."""
        if goals.ndim != 2 or goals.shape[1] < 1 or (dim is not None and goals.shape[1] != dim):
            allowed = (f"[{dim}] like {self.goal_key!r}" if dim is not None
                       else "[d] with d >= 1 (a 1-D goal is stored as [1])")
            raise ValueError(
                f"CherSampler reads goals {key!r} from the storage as one vector per transition, {allowed}; "
                f"got {tuple(goals.shape[1:])} per transition"
            )
        return goals

    def similarity_graph(self, goals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each pool goal's k nearest other pool goals and their similarity exp(−d²/mean(d)²).

        With k = 1 (:func:`nearest_other`), copies of a goal are its neighbours at distance 0 (the
        first copy for the others, the second for the first) and a goal nearest to a repeated goal
        has its first copy as neighbour; with k > 1 the k-d tree orders equally distant neighbours.
        """
        points = goals.detach().cpu().to(torch.float64).numpy()
        k = min(self.neighbours, len(points) - 1)
        if k == 1:
            index, distance = (x[:, None] for x in nearest_other(points))
        else:
            distance, index = cKDTree(points).query(points, k=k + 1)
            # Drop each goal itself (or, when duplicates hide it, its last neighbour), as sklearn does.
            own = index == np.arange(len(points))[:, None]
            own[~own.any(1), -1] = True
            distance = distance[~own].reshape(len(points), k)
            index = index[~own].reshape(len(points), k)
        mean = distance.mean()
        similarity = np.exp(-np.square(distance) / mean**2) if mean > 0 else np.ones_like(distance)
        return torch.from_numpy(index), torch.from_numpy(similarity).to(torch.float32)

    def _empty(self) -> None:
        pass

    def state_dict(self) -> dict[str, Any]:
        return OrderedDict(
            pool_size=self.pool_size,
            neighbours=self.neighbours,
            subset_size=self.subset_size,
            tradeoff=dict(self.tradeoff.state_dict()),
        )

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.pool_size = int(state_dict["pool_size"])
        self.neighbours = int(state_dict["neighbours"])
        self.subset_size = int(state_dict["subset_size"])
        self.tradeoff.load_state_dict(state_dict["tradeoff"])

    def dumps(self, path) -> None:
        dump_state(self.state_dict(), path)

    def loads(self, path) -> None:
        self.load_state_dict(load_state(path))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(metric={self.metric!r}, pool_size={self.pool_size}, tradeoff={self.tradeoff!r})"


DRAWS_PER_CANDIDATE = 4
"""Uniform draws per subset member pre-drawn for each greedy step (see :func:`lazier_than_lazy_greedy`)."""


def lazier_than_lazy_greedy(
    neighbour: torch.Tensor,
    similarity: torch.Tensor,
    penalty: torch.Tensor,
    batch_size: int,
    subset_size: int,
    generator: torch.Generator,
    *,
    window: int = 64,
) -> tuple[torch.Tensor, torch.Tensor]:
    """CHER's greedy facility-location choice of ``batch_size`` pool entries (eqs. 2–3 with eq. 1's penalty).

    The algorithm, step by step (``t = 0 … batch_size − 1``), as a plain loop would run it:

    1. the step's subset: of the ``DRAWS_PER_CANDIDATE · subset_size`` pool indices drawn uniformly
       for this step (all steps' draws come from one ``torch.randint`` call on ``generator``), the
       first ``subset_size`` that are distinct and not chosen yet; if fewer remain (only when the
       pool is nearly used up), ``subset_size`` entries drawn from the not-yet-chosen ones with
       ``torch.multinomial`` on ``generator``;
    2. each subset member c scores its gain Σ_v max(0, s(v, c) − cover(v)) − penalty(c), the sum
       over the pool entries v that have c among their neighbours (``neighbour[v, j] == c``, with
       similarity ``s(v, c) = similarity[v, j]``); gains are summed in float64, so equal gains tie
       exactly and the first subset member with the largest score wins;
    3. the winner is chosen and each of its in-neighbours' cover rises to s(v, winner).

    Step t depends on the steps before it only through the cover of the in-neighbours of its own
    subset and through which entries are taken. With k = 1 (CHER's setting) not even the cover: an
    entry's in-neighbours have it as their only neighbour, so their cover stays 0 until it is
    chosen, and a candidate's gain is the same at every step it is free. The gains are then summed
    once, and only which entries the earlier steps took is followed from step to step
    (:func:`_static_gain_greedy`). With k > 1 the loop runs in vectorised passes: each pass scores
    up to ``window`` steps at once against the cover the pass starts with, then keeps the longest
    prefix of steps that no earlier step of the pass could have changed (no earlier winner in their
    subset, no cover they read raised by an earlier winner). The kept steps are exactly the plain
    loop's; the next pass starts at the first step that was not kept. Either way a batch of 256
    takes a few vectorised passes instead of 256 scans of the pool (``benchmarks/samplers.py``).

    Args:
        neighbour: ``[P, k]`` each pool entry's k nearest other entries (:meth:`CherSampler.similarity_graph`).
        similarity: ``[P, k]`` their similarities, ≥ 0.
        penalty: ``[P]`` λ · d(g, g*) of each pool entry, subtracted from its gain.
        batch_size: entries to choose, ≤ P − subset_size + 1.
        subset_size: candidates per greedy step (3 in CHER).
        generator: the random stream of the subset draws.

    Keyword Args:
        window: steps scored per pass with k > 1 (speed only: the choices do not depend on it).

    Returns:
        ``(chosen, cover)``: the ``[batch_size]`` chosen pool indices in the order chosen and the
        ``[P]`` float32 cover after the last step (its sum is the facility-location value).
    """
    size = int(neighbour.shape[0])
    draws = torch.randint(size, (batch_size, DRAWS_PER_CANDIDATE * subset_size), generator=generator).numpy()
    fresh = _first_of_repeats(draws, size)
    if neighbour.shape[1] == 1:
        return _static_gain_greedy(neighbour, similarity, penalty, draws, fresh, subset_size, generator)
    start, reader, reader_similarity = _in_neighbours(neighbour.numpy(), similarity.numpy().astype(np.float64), size)
    penalty = penalty.numpy().astype(np.float64)
    cover = np.zeros(size)
    taken = np.zeros(size, dtype=bool)
    chosen = np.empty(batch_size, dtype=np.int64)
    step = 0
    while step < batch_size:
        window_draws = draws[step: step + window]
        subsets = _first_available(window_draws, fresh[step: step + window] & ~taken[window_draws], subset_size)
        if subsets[0, 0] < 0:  # too few fresh draws for this step: draw among the entries left
            free = torch.from_numpy(~taken).to(torch.float32)
            subsets[0] = torch.multinomial(free, subset_size, replacement=False, generator=generator).numpy()
        short = np.flatnonzero(subsets[1:, 0] < 0)
        if len(short):  # a later short row needs the generator in order: score only the rows before it
            subsets = subsets[: short[0] + 1]
        rows = np.arange(len(subsets))

        # eq. 2's gain of every candidate of the pass, against the cover the pass starts with
        owner, edges = _ragged(start, subsets.reshape(-1))  # edges: (v, c) pairs, candidate by candidate
        readers = reader[edges]
        gain = np.bincount(owner, np.maximum(reader_similarity[edges] - cover[readers], 0.0), minlength=subsets.size)
        best = subsets[rows, np.argmax(gain.reshape(subsets.shape) - penalty[subsets], axis=1)]

        # keep the steps that no earlier step of the pass could have changed
        winner_row, winner_edges = _ragged(start, best)
        raised = reader[winner_edges]
        raises = reader_similarity[winner_edges] > cover[raised]
        first_raise = np.full(size, len(rows))
        np.minimum.at(first_raise, raised[raises], winner_row[raises])
        first_pick = np.full(size, len(rows))
        np.minimum.at(first_pick, best, rows)
        earliest = first_pick[subsets].min(1)
        np.minimum.at(earliest, owner // subset_size, first_raise[readers])
        stale = np.flatnonzero(earliest < rows)
        kept = int(stale[0]) if len(stale) else len(rows)

        update = raises & (winner_row < kept)
        cover[raised[update]] = reader_similarity[winner_edges[update]]
        taken[best[:kept]] = True
        chosen[step: step + kept] = best[:kept]
        step += kept
    return torch.from_numpy(chosen), torch.from_numpy(cover).to(torch.float32)


def _static_gain_greedy(
    neighbour: torch.Tensor,
    similarity: torch.Tensor,
    penalty: torch.Tensor,
    draws: np.ndarray,
    fresh: np.ndarray,
    subset_size: int,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`lazier_than_lazy_greedy` with k = 1, where a free candidate's gain never changes.

    Every entry's score, Σ_v s(v, c) over the v whose neighbour is c, minus penalty(c), is summed
    once (float64, in increasing v as the k > 1 passes sum it). What a step still takes from the
    steps before it is which entries they took. Starting from "nothing taken", every step's subset
    and winner is found at once from the winners of the previous round, until a round changes
    nothing. Step t is right once the steps before it were right a round earlier, so the rounds
    end, at the plain loop's choices, after a few rounds for a batch of 256 from a pool of 5,000. A step
    with too few fresh draws takes the generator's fallback draw in order, and the rounds start
    again after it.
    """
    size, batch_size = int(neighbour.shape[0]), len(draws)
    nearest = neighbour[:, 0].numpy()
    similarity = similarity[:, 0].numpy().astype(np.float64)
    score = np.bincount(nearest, similarity, minlength=size) - penalty.numpy().astype(np.float64)
    taken = np.zeros(size, dtype=bool)  # by the steps before `step`
    chosen = np.empty(batch_size, dtype=np.int64)
    step = 0
    while step < batch_size:
        rows, candidates = np.arange(step, batch_size), draws[step:]
        free = fresh[step:] & ~taken[candidates]
        winner = np.full(len(rows), -1)
        while True:
            first_win = np.full(size, batch_size)  # the first step that took each entry, by this round's winners
            won = winner >= 0
            np.minimum.at(first_win, winner[won], rows[won])
            subsets = _first_available(candidates, free & (first_win[candidates] >= rows[:, None]), subset_size)
            best = subsets[np.arange(len(rows)), np.argmax(score[subsets], axis=1)]
            update = np.where(subsets[:, 0] >= 0, best, -1)  # a short row takes nothing this round
            if np.array_equal(update, winner):
                break
            winner = update
        short = np.flatnonzero(winner < 0)
        kept = int(short[0]) if len(short) else len(rows)  # steps before the first short one are the loop's
        chosen[step: step + kept] = winner[:kept]
        taken[winner[:kept]] = True
        step += kept
        if kept < len(rows):  # too few fresh draws: draw among the entries left, in the generator's order
            left = torch.from_numpy(~taken).to(torch.float32)
            subset = torch.multinomial(left, subset_size, replacement=False, generator=generator).numpy()
            chosen[step] = subset[np.argmax(score[subset])]
            taken[chosen[step]] = True
            step += 1
    cover = np.where(taken[nearest], similarity, 0.0)
    return torch.from_numpy(chosen), torch.from_numpy(cover).to(torch.float32)


def _in_neighbours(neighbour: np.ndarray, similarity: np.ndarray, size: int) -> tuple[np.ndarray, ...]:
    """Invert the k-NN lists (CSR): the entries v with c among their neighbours are
    ``reader[start[c]:start[c + 1]]``, in increasing order, with similarities s(v, c)."""
    target = neighbour.reshape(-1)
    order = np.argsort(_small(target), kind="stable")
    start = np.zeros(size + 1, dtype=np.int64)
    np.cumsum(np.bincount(target, minlength=size), out=start[1:])
    return start, order // neighbour.shape[1], similarity.reshape(-1)[order]


def _ragged(start: np.ndarray, items: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The CSR positions of every item's row, concatenated, and the item (its position in ``items``) of each."""
    first, count = start[items], start[items + 1] - start[items]
    owner = np.repeat(np.arange(len(items)), count)
    return owner, np.arange(len(owner)) + np.repeat(first - (np.cumsum(count) - count), count)


def _first_of_repeats(draws: np.ndarray, size: int) -> np.ndarray:
    """Per row of draws (entries below ``size``), whether each draw is the first of its repeats in the row."""
    keys = (draws + size * np.arange(len(draws))[:, None]).reshape(-1)  # (row, entry) as one number
    order = np.argsort(keys, kind="stable")
    first = np.empty(keys.size, dtype=bool)
    first[order] = np.concatenate([[True], keys[order[1:]] != keys[order[:-1]]])
    return first.reshape(draws.shape)


def _first_available(draws: np.ndarray, available: np.ndarray, subset_size: int) -> np.ndarray:
    """Per row of draws, the first ``subset_size`` draws where ``available``; rows with too few get −1."""
    rank = np.cumsum(available, axis=1)
    subsets = np.full((len(draws), subset_size), -1, dtype=np.int64)
    full = rank[:, -1] >= subset_size
    subsets[full] = draws[full][(available & (rank <= subset_size))[full]].reshape(-1, subset_size)
    return subsets


def nearest_other(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point's nearest other point and the distance to it; among copies of a point, the first.

    A point with copies has the first of them as nearest (the first copy has the second); a point
    nearest to a repeated point has that point's first copy; between distinct points at exactly
    the same distance the k-d tree chooses.

    Exact copies are grouped first (a hash of the coordinates' bits, checked, :func:`_hash_rows`), so the k-d tree is
    built on distinct points only and queried only for points without copies: a pool where an
    object at rest repeats one position thousands of times costs no more than its distinct
    positions (``benchmarks/samplers.py``).

    Args:
        points: ``[n, d]`` float64, n ≥ 2.

    Returns:
        ``(index, distance)``, each ``[n]``.

    >>> index, distance = nearest_other(np.array([[0.0, 0], [5, 0], [0, 0], [1, 0], [0, 0]]))
    >>> index.tolist(), distance.tolist()
    ([2, 3, 0, 0, 0], [0.0, 4.0, 0.0, 1.0, 0.0])
    """
    n = len(points)
    points = np.ascontiguousarray(points + 0.0)  # -0.0 as 0.0
    mix = _hash_rows(points)
    order = np.argsort(mix, kind="stable")  # copies side by side, each group's members in increasing index
    starts = np.flatnonzero(np.concatenate([[True], mix[order[1:]] != mix[order[:-1]]]))
    first, copies = order[starts], np.diff(starts, append=n)
    group = np.empty(n, dtype=np.int64)
    group[order] = np.repeat(np.arange(len(starts)), copies)
    if not np.array_equal(points[first[group]], points):  # a hash collision: group by the coordinates themselves
        _, first, group, copies = np.unique(points, axis=0, return_index=True, return_inverse=True, return_counts=True)
        order = np.argsort(_small(group), kind="stable")
        starts = np.cumsum(copies) - copies
    index, distance = np.zeros(n, dtype=np.int64), np.zeros(n)
    single = np.flatnonzero(copies == 1)  # the groups whose nearest point is another position: ask the tree
    if len(first) > 1 and len(single):
        distinct = points[first]
        near, other = cKDTree(distinct).query(distinct[single], k=2)
        lone = first[single]
        index[lone], distance[lone] = first[other[:, 1]], near[:, 1]
    repeated = copies[group] > 1
    second = order[np.minimum(starts + 1, n - 1)]  # each group's second member (where it has one)
    own_first = first[group] == np.arange(n)
    index = np.where(repeated, np.where(own_first, second[group], first[group]), index)
    return index, np.where(repeated, 0.0, distance)


_K1, _K2, _K3 = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)
_S29, _S31 = np.uint64(29), np.uint64(31)


def _hash_rows(points: np.ndarray) -> np.ndarray:
    """A 64-bit hash of each row's coordinate bits: each coordinate's bits multiplied in after an
    xor-shift of the hash so far, then a MurmurHash3-style finaliser. Goals stored as float32 and
    widened to float64 have their 29 low bits zero, which a plain weighted sum of the bits keeps
    zero, so that near-equal goals could collide (a pair recorded on push_new did,
    ``tests/test_samplers.py``) and send the call to the slow exact grouping; the xor-shifts bring
    the high bits down before each multiplication."""
    x = points.view(np.uint64)
    with np.errstate(over="ignore"):
        mix = x[:, 0] * _K1
        for column in range(1, x.shape[1]):
            mix = (mix ^ (mix >> _S29)) * _K2 + x[:, column] * _K1
        mix ^= mix >> _S31
        mix *= _K3
        mix ^= mix >> _S29
    return mix  # wraps around


def _small(index: np.ndarray) -> np.ndarray:
    """Indices below 2**16 as uint16, which numpy's stable argsort sorts by radix (~8x faster on a pool of 5,000)."""
    return index.astype(np.uint16) if len(index) and index.max() < 2**16 else index
