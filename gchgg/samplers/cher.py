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

from gchgg.graph import EuclideanMetric, Metric
from gchgg.samplers._storage import check_sampleable, dump_state, generator, load_state, read_field
from gchgg.samplers.tradeoff import ExponentialTradeoff, Tradeoff, as_tradeoff
from gchgg.validation import check_number

__all__ = ["CherSampler"]


class CherSampler(Sampler):
    """Curriculum-guided HER (Fang et al. 2019) selection, the baseline of the paper's Table I.

    Each ``sample(storage, B)`` runs CHER's algorithm as published with its code:

    1. draw a pool of ``pool_size`` stored transitions uniformly (HER copies are already stored,
       so the pool mixes relabelled and original goals 4 : 1 like CHER's HER sampling);
    2. build the k-nearest-neighbour graph of the pool's goals (Euclidean, k-d tree, self
       excluded; k = ``neighbours``, 1 in CHER) with similarities s = exp(−d² / mean(d)²);
    3. pick B pool entries greedily, "lazier than lazy greedy": at each of the B steps draw
       ``subset_size`` (3 in CHER) not yet chosen entries and keep the one with the largest
       facility-location gain Σ_v max(0, s(v, c) − cover(v)) − λ · d(g_c, g*_c), then raise every
       cover(v) to s(v, c). d is ``metric`` between the goal and ``target_key`` (eq. 1; CHER's code
       measured to the transition's achieved goal: ``target_key="achieved_goal"``).

    The B greedy steps are sequential by nature; each is vectorised over the pool (O(pool·k)), so a
    sample costs one k-d tree build and query, O(pool·log pool), plus O(B·pool·k) tensor work, with
    B small Python iterations. Unlike CHER's code the cover is only updated with the chosen entry
    (CHER's loop also kept the cover of a better-scoring but finally rejected subset member; with
    k = 1 the gains are the same either way). An unreachable goal (``inf``) counts as the largest
    finite distance of the pool, as in :class:`~gchgg.samplers.GraphCurriculumSampler`.

    Args:
        metric: proximity metric with ``distance(a, b)``. Default :class:`~gchgg.graph.EuclideanMetric`.
        pool_size: candidates per sample, ≥ B + subset_size − 1. Default 5,000 (GC-HGG's CHER runs
            drew one candidate per stored episode of a 5,000-episode buffer; CHER's own code drew
            128 for a batch of 64).
        tradeoff: λ as a number or schedule. Default ``ExponentialTradeoff(lambda_0=1, tau=0.005)``
            (eq. 4), which the training loop steps once per iteration.

    Keyword Args:
        goal_key: stored goal. Default ``"desired_goal"``.
        target_key: stored goal proximity is measured to. Default ``"target_goal"``.
        neighbours: k of the similarity graph (≥ 1). Default 1.
        subset_size: random candidates per greedy step (≥ 1). Default 3.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> g = torch.Generator().manual_seed(0)
        >>> data = TensorDict({"desired_goal": torch.rand(500, 3, generator=g),
        ...                    "target_goal": torch.zeros(500, 3)}, [500])
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
        target_key: NestedKey = "target_goal",
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

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        n = check_sampleable(storage, self)
        if self.pool_size < batch_size + self.subset_size - 1:
            raise ValueError(
                f"CherSampler needs pool_size >= batch_size + subset_size - 1 = {batch_size + self.subset_size - 1} "
                f"to choose {batch_size} distinct entries, got pool_size={self.pool_size}"
            )
        rng = generator(self)
        pool = torch.randint(n, (self.pool_size,), generator=rng)
        goals = read_field(storage, self.goal_key, pool, self).reshape(self.pool_size, -1)
        targets = read_field(storage, self.target_key, pool, self).reshape(self.pool_size, -1)

        neighbour, similarity = self.similarity_graph(goals)  # [P, k] each
        distance = torch.as_tensor(self.metric.distance(goals, targets))
        if bool(torch.isnan(distance).any()):
            raise ValueError("the metric returned NaN distances; goals must be finite")
        finite = torch.isfinite(distance)
        if not bool(finite.all()):
            distance = torch.where(finite, distance, distance[finite].max() if bool(finite.any()) else 0.0)
        lam = float(self.tradeoff.value)
        penalty = lam * distance.to(torch.float32)

        cover = torch.zeros(self.pool_size)
        available = torch.ones(self.pool_size)
        chosen = torch.empty(batch_size, dtype=torch.long)
        for step in range(batch_size):  # greedy steps, each vectorised over the pool
            subset = torch.multinomial(available, self.subset_size, replacement=False, generator=rng)
            hit = neighbour.unsqueeze(-1) == subset  # [P, k, s]: v has candidate c among its neighbours
            gain = ((similarity - cover.unsqueeze(-1)).clamp_(min=0.0).unsqueeze(-1) * hit).sum((0, 1))
            best = subset[torch.argmax(gain - penalty[subset])]
            cover = torch.maximum(cover, torch.where(neighbour == best, similarity, 0.0).amax(-1))
            available[best] = 0.0
            chosen[step] = best
        info = {
            "diversity": cover.sum(),  # facility-location value of the chosen set
            "proximity": -distance[chosen].sum().to(torch.float32),
            "tradeoff": torch.tensor(lam, dtype=torch.float32),
        }
        return pool[chosen], info

    def similarity_graph(self, goals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each pool goal's k nearest other pool goals and their similarity exp(−d²/mean(d)²)."""
        points = goals.detach().cpu().to(torch.float64).numpy()
        k = min(self.neighbours, len(points) - 1)
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
