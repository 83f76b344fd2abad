"""CHER's sampler pinned end to end against a reference written here, from the paper (issue 72 item 5).

``tests/test_samplers.py`` pins the greedy (``lazier_than_lazy_greedy``) against a loop, given its inputs;
this file pins what feeds it: the pool drawn from the buffer's generator, the proximity term λ · d(g, g*)
(eq. 1), the similarities of the pool's nearest-neighbour graph (eq. 2's diversity as CHER's code
computes it, a facility-location value) and the mapping back to stored rows (``pool[chosen]``). Nothing
of gchgg's CHER code is imported: the reference replays the buffer's generator, in the order the
sampler draws from it, and runs a plain greedy in Python floats.

The random stream (``CherSampler.sample``'s docstring and code): one ``torch.randint(n, (P,))`` for
the pool, then one ``torch.randint(P, (B, 4 · subset_size))`` of candidate draws, step by step
(``torch.multinomial`` over the free entries only when a step has fewer than ``subset_size`` fresh
draws left, which the sizes here keep rare; the reference follows that path too).
"""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from gchgg.samplers import CherSampler

DRAWS_PER_CANDIDATE = 4  # CHER's subset draws per member and step (CherSampler's documented stream)


def stored_transitions(n: int, seed: int) -> TensorDict:
    """Goals in the unit cube, every fifth row a copy of another (a resting object), targets at four spots."""
    g = torch.Generator().manual_seed(seed)
    goals = torch.rand(n, 3, generator=g)
    copies = torch.arange(0, n, 5)
    goals[copies] = goals[torch.randint(n, (len(copies),), generator=g)]
    spots = torch.rand(4, 3, generator=g)
    targets = spots[torch.randint(4, (n,), generator=g)]
    return TensorDict({"desired_goal": goals, "task_goal": targets, "reward": torch.zeros(n, 1)}, [n])


def euclidean(a, b) -> float:
    return math.sqrt(sum((x - y) ** 2 for x, y in zip(a, b, strict=True)))


def nearest_other(points: list[list[float]]) -> tuple[list[int], list[float]]:
    """Each point's nearest other point (the smallest index among equally near ones, so copies of a point
    have its first copy, and the first copy its second) and the distance to it: a plain O(P²) scan."""
    index, distance = [], []
    for i, p in enumerate(points):
        best, best_d = -1, math.inf
        for j, q in enumerate(points):
            if j != i:
                d = euclidean(p, q)
                if d < best_d:
                    best, best_d = j, d
        index.append(best)
        distance.append(best_d)
    return index, distance


def reference_cher(data: TensorDict, rng: torch.Generator, pool_size: int, batch_size: int, lam: float,
                   subset_size: int = 3, power: float = 1.0) -> dict:
    """CHER's choice of ``batch_size`` stored rows, replaying ``rng`` as the sampler draws from it.

    Objective (paper eqs. 1–3, in CHER's facility-location form): maximise
    F(A) = Σ_{v ∈ pool} max_{c ∈ A, v → c} s(v, c) − λ Σ_{c ∈ A} d(g_c, g*_c), with s(v, c) = exp(−d_v² / mean(d)²)
    on each pool goal's nearest other pool goal c (d_v its distance), greedily: at each step draw
    candidates, keep the first ``subset_size`` distinct not-yet-chosen ones, take the one with the largest
    marginal gain Σ_v max(0, s(v, c) − cover(v)) − λ d(g_c, g*_c). ``power`` = 2 gives the λ · d² variant.
    """
    n = data.shape[0]
    pool = torch.randint(n, (pool_size,), generator=rng).tolist()
    goals = [data["desired_goal"][i].double().tolist() for i in pool]
    targets = [data["task_goal"][i].double().tolist() for i in pool]
    near, near_d = nearest_other(goals)
    mean = sum(near_d) / pool_size
    similarity = [math.exp(-(d * d) / (mean * mean)) for d in near_d]
    penalty = [lam * euclidean(g, t) ** power for g, t in zip(goals, targets, strict=True)]

    draws = torch.randint(pool_size, (batch_size, DRAWS_PER_CANDIDATE * subset_size), generator=rng).tolist()
    cover = [0.0] * pool_size
    chosen: list[int] = []
    margins = []
    for row in draws:
        subset: list[int] = []
        for c in row:
            if c not in chosen and c not in subset:
                subset.append(c)
            if len(subset) == subset_size:
                break
        if len(subset) < subset_size:  # too few fresh draws: the sampler draws among the entries left
            free = torch.tensor([0.0 if c in chosen else 1.0 for c in range(pool_size)])
            subset = torch.multinomial(free, subset_size, replacement=False, generator=rng).tolist()
        gains = [sum(max(0.0, similarity[v] - cover[v]) for v in range(pool_size) if near[v] == c) - penalty[c]
                 for c in subset]
        best = max(range(subset_size), key=lambda k: (gains[k], -k))  # the first of equal gains
        others = [gains[k] for k in range(subset_size) if k != best and goals[subset[k]] != goals[subset[best]]]
        if others:
            margins.append(gains[best] - max(others))
        winner = subset[best]
        chosen.append(winner)
        for v in range(pool_size):
            if near[v] == winner:
                cover[v] = max(cover[v], similarity[v])
    return {
        "indices": [pool[c] for c in chosen],
        "diversity": sum(cover),
        "proximity": -sum(euclidean(goals[c], targets[c]) for c in chosen),
        "margin": min(margins),
    }


@pytest.mark.parametrize("seed", [0, 1])
def test_cher_sample_equals_the_reference_replayed_from_the_buffer_generator(seed):
    """``buffer.sample()`` returns exactly the stored rows the reference chooses: pool, similarities, λ · d and the
    greedy all matter (a λ · d² penalty, λ = 0, or another pool draw chooses other rows, checked below)."""
    n, pool_size, batch_size, lam = 400, 160, 64, 3.0
    data = stored_transitions(n, seed)
    rng = torch.Generator().manual_seed(100 + seed)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(n), batch_size=batch_size, generator=rng,
                                    sampler=CherSampler(pool_size=pool_size, tradeoff=lam))
    buffer.extend(data)

    state = rng.get_state()
    batch = buffer.sample()
    replay = torch.Generator()
    replay.set_state(state)
    expected = reference_cher(data, replay, pool_size, batch_size, lam)

    assert expected["margin"] > 1e-4  # no near-tie that float32 rounding in the sampler could flip
    assert batch["index"].tolist() == expected["indices"]
    assert torch.equal(batch["desired_goal"], data["desired_goal"][expected["indices"]])
    assert batch["tradeoff"][0].item() == lam
    assert batch["diversity"][0].item() == pytest.approx(expected["diversity"], rel=1e-5)
    assert batch["proximity"][0].item() == pytest.approx(expected["proximity"], rel=1e-5)
    # the sampler consumed exactly the draws the reference replayed
    assert torch.equal(rng.get_state(), replay.get_state())

    # the test discriminates: each of these other objectives chooses other rows from the same stream
    for variant in ({"power": 2.0}, {"lam": 0.0}):
        replay.set_state(state)
        other = reference_cher(data, replay, pool_size, batch_size, **{"lam": lam, **variant})
        assert other["indices"] != expected["indices"], variant


def test_cher_reference_large_lambda_prefers_goals_near_their_target():
    """With λ = 3 the proximity term decides: the chosen goals are nearer their targets than the pool's."""
    n, pool_size, batch_size = 400, 160, 64
    data = stored_transitions(n, 2)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(n), batch_size=batch_size,
                                    generator=torch.Generator().manual_seed(5),
                                    sampler=CherSampler(pool_size=pool_size, tradeoff=3.0))
    buffer.extend(data)
    batch = buffer.sample()
    chosen = (batch["desired_goal"] - batch["task_goal"]).norm(dim=-1).mean()
    everyone = (data["desired_goal"] - data["task_goal"]).norm(dim=-1).mean()
    assert chosen < 0.9 * everyone
