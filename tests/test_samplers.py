"""Replay samplers in plain TorchRL buffers: EBP proportions, curriculum behaviour, exact neighbours, CHER, state."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

from gchgg.graph import EuclideanMetric, GoalGraph
from gchgg.samplers import (
    AdaptiveTradeoff,
    CherSampler,
    EnergySampler,
    ExponentialTradeoff,
    FixedTradeoff,
    GraphCurriculumSampler,
    NearestNeighbours,
    as_tradeoff,
    nearest_neighbour_distances,
)
from gchgg.transforms import EpisodeEnergy, HindsightRelabel

TARGET = (0.0, -0.5, 0.0)  # below the wall; goals above it are far in d_G


@pytest.fixture(scope="module")
def graph() -> GoalGraph:
    """A 2 m × 2 m field with a wall from x = -1.0 to 0.4 along y = 0 (the GoalGraph docstring's example)."""
    wall = ((-0.3, 0.0, 0.0), (0.7, 0.1, 0.2))
    return GoalGraph(((0.0, 0.0, 0.0), (1.0, 1.0, 0.1)), [wall], n=(21, 21, 3), margin=0.0, cache_dir=None)


def goal_transitions(num: int, seed: int = 0, energy: torch.Tensor | None = None) -> TensorDict:
    """Transitions with goals spread over the field (z = 0) and one target below the wall."""
    g = torch.Generator().manual_seed(seed)
    goals = torch.rand(num, 3, generator=g) * 2 - 1
    goals[:, 2] = 0.0
    data = {"desired_goal": goals, "task_goal": torch.tensor(TARGET).expand(num, 3).clone(),
            "observation": torch.randn(num, 4, generator=g)}
    if energy is not None:
        data["energy"] = energy
    return TensorDict(data, [num])


def make_buffer(sampler, data: TensorDict, size: int | None = None, seed: int = 0, batch: int = 64):
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(size or len(data)), sampler=sampler, batch_size=batch,
                                    generator=torch.Generator().manual_seed(seed))
    buffer.extend(data)
    return buffer


def mean_over_batches(buffer, fn, draws: int = 25) -> float:
    return sum(fn(buffer.sample()) for _ in range(draws)) / draws


# ----------------------------------------------------------------------------- EBP


def test_ebp_draws_in_proportion_to_energy():
    energies = torch.tensor([0.0, 1.0, 2.0, 5.0]).repeat_interleave(50)  # 4 episodes of 50 transitions
    buffer = make_buffer(EnergySampler(), goal_transitions(200, energy=energies), batch=40_000)
    episode = buffer.sample()["index"] // 50
    counts = torch.bincount(episode, minlength=4).double()
    assert counts[0] == 0  # no energy: never drawn
    expected = torch.tensor([1.0, 2.0, 5.0], dtype=torch.float64) / 8 * counts.sum()
    chi2 = ((counts[1:] - expected) ** 2 / expected).sum().item()
    assert chi2 < 13.8, (counts, chi2)  # chi-square, 2 degrees of freedom, p = 0.001


def test_ebp_uniform_without_energy_and_refreshed_after_writes():
    buffer = make_buffer(EnergySampler(), goal_transitions(100, energy=torch.zeros(100)), size=300, batch=20_000)
    counts = torch.bincount(buffer.sample()["index"], minlength=100).double()
    assert counts.min() > 100 and counts.max() < 300  # uniform: 200 each
    buffer.extend(goal_transitions(100, seed=1, energy=torch.ones(100)))  # rows 100..199 now hold all the energy
    index = buffer.sample()["index"]
    assert ((index >= 100) & (index < 200)).all()


def test_ebp_draw_is_the_inverse_cdf_of_the_rows_even_with_crowded_guide_bins():
    # 300 episodes of 5 rows: one holds almost all the energy, the others are tiny or zero, so the
    # guide table's bins crowd with run boundaries and the binary-search fallback is used too.
    g = torch.Generator().manual_seed(3)
    episode = torch.rand(300, generator=g, dtype=torch.float64) * 1e-6
    episode[::7] = 0.0
    episode[150] = 1.0
    energy = episode.repeat_interleave(5)
    storage = LazyTensorStorage(2000)
    storage.set(torch.arange(1500), TensorDict({"energy": energy.float()}, [1500]))
    sampler = EnergySampler()
    sampler._rng = torch.Generator().manual_seed(7)
    index = sampler.draw(storage, 64, 256)
    u = torch.rand(64, 256, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    cdf = energy.float().double().cumsum(0)
    expected = torch.searchsorted(cdf, u * cdf[-1], right=True)  # the row whose cumulative energy passes u
    assert (index == expected).double().mean() > 0.999
    assert (energy.float()[index] > 0).all()
    assert ((index >= 750) & (index < 755)).double().mean() > 0.99


def test_ebp_follows_every_write_and_draws_as_a_sampler_built_afresh():
    # The energies are copied once per written row; after wrapping, add, mark_update and a slice
    # write, the draws equal those of a new sampler reading the whole storage, bit for bit.
    g = torch.Generator().manual_seed(5)

    def episodes(num: int) -> TensorDict:  # episodes of 10 rows sharing an energy, some of them 0
        energy = (torch.rand(num, generator=g) * (torch.rand(num, generator=g) > 0.2)).repeat_interleave(10)
        return goal_transitions(10 * num, energy=energy)

    sampler = EnergySampler(epsilon=0.01)
    buffer = make_buffer(sampler, episodes(20), size=500, batch=1000)

    def check() -> None:
        fresh = EnergySampler(epsilon=0.01)
        fresh._rng = torch.Generator().manual_seed(11)
        sampler._rng = torch.Generator().manual_seed(11)
        assert torch.equal(sampler.draw(buffer.storage, 1000), fresh.draw(buffer.storage, 1000))

    check()
    buffer.extend(episodes(25))  # 450 rows: new rows read
    check()
    buffer.extend(episodes(10))  # wraps: rows 450..499 and 0..49 overwritten
    check()
    buffer.add(episodes(1)[0])  # one row
    check()
    buffer[torch.arange(100, 110)] = episodes(1)
    sampler.mark_update(torch.arange(100, 110))
    check()
    buffer.storage.set(slice(200, 210), episodes(1))
    sampler.mark_update(slice(200, 210))  # not row indices: everything is read again
    check()
    assert sampler.cache_bytes == 500 * 8  # a float64 per row of the capacity


def test_ebp_runs_follow_writes_that_split_and_merge_them():
    # Single rows and short stretches written with their neighbours' energy (merging runs), a new
    # one (splitting them) or 0, at the ends too: after each write the run starts kept up to date
    # equal those of a full scan (every position where the energy differs from the one before).
    g = torch.Generator().manual_seed(9)
    energy = torch.tensor([1.0, 2.0, 0.0, 3.0]).repeat_interleave(5)  # 4 runs of 5 rows
    buffer = make_buffer(EnergySampler(), goal_transitions(20, energy=energy), size=40, batch=8)
    sampler, stored = buffer.sampler, energy.clone()
    buffer.sample()
    for _ in range(60):
        n = len(buffer)
        first = int(torch.randint(n, (1,), generator=g))
        rows = torch.arange(first, min(n, first + int(torch.randint(1, 4, (1,), generator=g))))
        choice = int(torch.randint(4, (1,), generator=g))
        if choice == 0:  # a neighbour's energy
            neighbour = first - 1 if first else min(int(rows[-1]) + 1, n - 1)
            value = torch.full((len(rows),), float(stored[neighbour]))
        elif choice == 1:
            value = torch.zeros(len(rows))
        else:
            value = torch.rand(len(rows), generator=g).round(decimals=1)  # repeats now and then
        buffer[rows] = goal_transitions(len(rows), energy=value)
        sampler.mark_update(rows)
        stored[rows] = value
        buffer.sample()
        expected = [0] + [i for i in range(1, n) if stored[i] != stored[i - 1]]
        assert sampler._starts.tolist() == expected


def test_ebp_rejects_negative_energy():
    buffer = make_buffer(EnergySampler(), goal_transitions(10, energy=-torch.ones(10)))
    with pytest.raises(ValueError, match="finite and >= 0"):
        buffer.sample()


# ----------------------------------------------------------------------------- curriculum


def graph_distance(graph, batch) -> float:
    return graph.distance(batch["desired_goal"], batch["task_goal"]).clamp(max=10).mean().item()


def nn_distance(graph, batch) -> float:
    nearest = nearest_neighbour_distances(batch["desired_goal"][None], graph, neighbours=None)
    return nearest[torch.isfinite(nearest)].mean().item()


def test_large_tradeoff_brings_goals_nearer_their_targets(graph):
    data = goal_transitions(5000)
    uniform = make_buffer(RandomSampler(), data)
    curriculum = make_buffer(GraphCurriculumSampler(graph, num_candidates=8, tradeoff=1000.0), data)
    d_uniform = mean_over_batches(uniform, lambda b: graph_distance(graph, b))
    d_curriculum = mean_over_batches(curriculum, lambda b: graph_distance(graph, b))
    assert d_curriculum < 0.95 * d_uniform, (d_curriculum, d_uniform)


def test_zero_tradeoff_spreads_goals_out(graph):
    data = goal_transitions(5000)
    uniform = make_buffer(RandomSampler(), data)
    curriculum = make_buffer(GraphCurriculumSampler(graph, num_candidates=8, tradeoff=0.0), data)
    nn_uniform = mean_over_batches(uniform, lambda b: nn_distance(graph, b))
    nn_curriculum = mean_over_batches(curriculum, lambda b: nn_distance(graph, b))
    assert nn_curriculum > 1.02 * nn_uniform, (nn_curriculum, nn_uniform)


def test_info_reports_the_chosen_candidate(graph):
    sampler = GraphCurriculumSampler(graph, num_candidates=4, tradeoff=3.0, unreachable_distance=2.5)
    batch = make_buffer(sampler, goal_transitions(500)).sample()
    goals, targets = batch["desired_goal"], batch["task_goal"]
    assert (batch["tradeoff"] == 3.0).all()
    distance = graph.distance(goals, targets)
    finite = torch.isfinite(distance)
    assert not finite.all()  # some goals lie in the wall
    expected = -torch.where(finite, distance, 2.5).sum()
    assert batch["proximity"][0].item() == pytest.approx(expected.item(), rel=1e-3)
    nearest = nearest_neighbour_distances(goals[None], graph, neighbours=None)
    diversity = torch.where(torch.isfinite(nearest), nearest, 0.0).sum()
    assert batch["diversity"][0].item() == pytest.approx(diversity.item(), rel=1e-4)


def random_goals(k: int, b: int, seed: int) -> torch.Tensor:
    """Goals on and off a graph: inside the wall, outside the field, duplicated, clustered by the wall."""
    g = torch.Generator().manual_seed(seed)
    goals = torch.rand(k, b, 3, generator=g) * 2 - 1
    goals[..., 2] = 0.0
    goals[:, : b // 8, 1] = (torch.rand(k, b // 8, generator=g) - 0.5) * 0.5  # near (and in) the wall
    goals[:, -4:-2] = goals[:, :2]  # duplicates
    goals[:, -1] = torch.tensor([3.0, 0.0, 0.0])  # outside the field
    return goals


def brute_force_nearest(goals: torch.Tensor, metric) -> torch.Tensor:
    """min_{j != i} metric.distance(g_i, g_j) for goals [K, B, 3], from all K·B² distances."""
    pairs = metric.distance(goals.unsqueeze(2), goals.unsqueeze(1)).double()  # [K, B, B]
    pairs.diagonal(dim1=1, dim2=2).fill_(math.inf)
    return pairs.min(-1).values.float()


@pytest.mark.parametrize("neighbours", [1, 2, 5])
@pytest.mark.parametrize("block", [32, 6])  # one window of all 70 goals; 12 blocks (2 padding rows)
def test_shortlist_nearest_neighbours_are_exact(graph, neighbours, block):
    for seed in range(3):
        goals = random_goals(4, 70, seed)
        for metric in (graph, EuclideanMetric()):
            stats: dict = {}
            fast = nearest_neighbour_distances(goals, metric, neighbours, block=block, stats=stats)
            exact = brute_force_nearest(goals, metric)
            assert not torch.isnan(fast).any()
            assert torch.equal(torch.isinf(fast), torch.isinf(exact))
            finite = torch.isfinite(exact)
            torch.testing.assert_close(fast[finite], exact[finite], rtol=0, atol=1e-6)
        assert torch.isinf(fast[:, -1]).sum() == 0  # Euclidean: outside the field is still finite
    assert stats["rescored"] < goals.shape[0] * goals.shape[1]


@pytest.mark.parametrize(("scale", "shift"), [(1.0, 0.0), (0.01, 1000.0), (100.0, -5.0)])
def test_euclidean_nearest_neighbours_are_exact_at_any_scale_with_ties_and_duplicates(scale, shift):
    g = torch.Generator().manual_seed(0)
    goals = torch.rand(6, 256, 3, generator=g) * scale + shift
    goals[:, 200:] = torch.round((goals[:, 200:] - shift) / scale * 20) * scale / 20 + shift  # ties on a grid
    goals[:, 10:20] = goals[:, 30:40]  # duplicates
    exact = brute_force_nearest(goals, EuclideanMetric())
    for neighbours in ("auto", 1, 3):
        stats: dict = {}
        fast = nearest_neighbour_distances(goals, EuclideanMetric(), neighbours, stats=stats)
        assert torch.equal(fast, exact), neighbours
        assert stats["rescored"] > 0  # the unproven goals' paths ran


@pytest.mark.parametrize("block", [32, 6])
def test_nearest_neighbours_are_exact_for_an_object_at_rest(graph, block):
    """Achieved goals of early training: most at a few rest positions (exact repeats and copies
    jittered by 1e-6 m), a few along 1 mm steps, some off the graph (parked together)."""
    g = torch.Generator().manual_seed(3)
    rest = torch.tensor([[0.5, 0.5, 0.0], [0.52, 0.5, 0.0], [-0.5, -0.6, 0.0]])
    goals = rest[torch.randint(3, (4, 256), generator=g)]
    goals[:, 100:160] += torch.randn(4, 60, 3, generator=g) * 1e-6  # jitter of a resting object
    goals[:, 90:100] = rest[:, None].expand(3, 4, 3).reshape(12, 3)[:10] - 1e-6  # sorted just before a rest position
    goals[:, 160:200] = torch.tensor([0.3, 0.2, 0.0]) + torch.arange(40).view(1, 40, 1) * torch.tensor([1e-3, 0.0, 0.0])
    goals[:, 200:210] = torch.tensor([3.0, 0.0, 0.0])  # off the graph
    goals = goals[:, torch.randperm(256, generator=g)]
    for metric in (graph, EuclideanMetric()):
        exact = brute_force_nearest(goals, metric)
        fast = nearest_neighbour_distances(goals, metric, "auto", block=block)
        assert torch.equal(fast, exact)  # the same metric reads: bit for bit


@pytest.mark.parametrize("b", [5, 37, 97, 256])
@pytest.mark.parametrize("block", [32, 6])
def test_nearest_neighbours_are_exact_when_most_goals_repeat_a_few(graph, b, block):
    """A few distinct goals, each repeated many times in a different number per batch (the search runs
    over the distinct ones only), beside one batch without repeats and goals off the graph."""
    g = torch.Generator().manual_seed(b + block)
    spots = torch.rand(12, 3, generator=g) * 2 - 1
    spots[:, 2] = 0.0
    spots[-1] = torch.tensor([3.0, 0.0, 0.0])  # off the graph
    distinct = torch.arange(5).view(5, 1) + 3  # 3..7 distinct spots per batch
    goals = spots[torch.randint(12, (5, b), generator=g) % distinct]
    goals[0] = torch.rand(b, 3, generator=g) * 2 - 1  # no repeats at all
    goals[0, :, 2] = 0.0
    for metric in (graph, EuclideanMetric()):
        exact = brute_force_nearest(goals, metric)
        for neighbours in (1, 3):
            fast = nearest_neighbour_distances(goals, metric, neighbours, block=block)
            assert torch.equal(fast, exact), (metric, neighbours)


@pytest.mark.parametrize("block", [8, 32])
def test_nearest_neighbours_are_exact_when_the_nearest_is_far_along_the_sort_axis(block):
    """Goals on 40 rows 50 mm apart, one goal every 1 mm along the sort axis x, so that each goal's
    nearest neighbour (its row's next goal, 40 mm along) sits 40 sorted positions away, beyond a
    window of 3 · 8 goals: the shortlist cannot prove it, and the rescoring must reach it."""
    g = torch.Generator().manual_seed(block)
    search = NearestNeighbours(EuclideanMetric(), block=block)
    search(torch.rand(1, 8, 3, generator=g) * torch.tensor([10.0, 1.0, 1.0]))  # x: the widest spread, the sort axis
    i = torch.arange(200)
    rows = torch.stack([i * 1e-3, (i % 40) * 0.05, torch.zeros(200)], -1)
    goals = torch.stack([rows[torch.randperm(200, generator=g)] for _ in range(3)])
    stats: dict = {}
    assert torch.equal(search(goals, stats=stats), brute_force_nearest(goals, EuclideanMetric()))
    assert stats["rescored"] > (goals.shape[0] * goals.shape[1] // 2 if block == 8 else 0)


def test_euclidean_nearest_neighbours_tell_goals_one_float_step_apart():
    """Exact duplicates with, between them in the sorted order, a goal one float step away in y and z
    only; far goals move the origin so that the points (relative positions) round the step away."""
    g = torch.Generator().manual_seed(0)
    base = torch.rand(4, 60, 3, generator=g) * 0.01 + 0.75
    step = base.clone()
    step[..., 1:] = torch.nextafter(base[..., 1:], torch.tensor(2.0))
    far = torch.rand(4, 76, 3, generator=g) * 0.1 - 8.0
    goals = torch.cat([base, step, base, far], 1)[:, torch.randperm(256, generator=g)]
    exact = brute_force_nearest(goals, EuclideanMetric())
    fast = nearest_neighbour_distances(goals, EuclideanMetric(), "auto")
    assert torch.equal(fast, exact)


def test_off_graph_goals_never_make_nan(graph):
    data = goal_transitions(400)
    data["desired_goal"][::3] = torch.tensor([0.0, 0.0, 0.0])  # inside the wall: inf to everything
    sampler = GraphCurriculumSampler(graph, num_candidates=4, tradeoff=AdaptiveTradeoff(initial=5.0))
    batch = make_buffer(sampler, data).sample()
    for key in ("diversity", "proximity", "tradeoff"):
        assert torch.isfinite(batch[key]).all(), key
    nearest = nearest_neighbour_distances(data["desired_goal"][None, ::3][:, :50], graph)
    assert torch.isinf(nearest).all()


def test_curriculum_drops_candidates_drawn_before_a_write_and_reads_lambda_at_each_sample():
    tradeoff = AdaptiveTradeoff(initial=5.0)
    sampler = GraphCurriculumSampler(EuclideanMetric(), num_candidates=4, tradeoff=tradeoff,
                                     energy_key="energy", draw_ahead=4)
    first_half = (torch.arange(100) < 50).float()
    buffer = make_buffer(sampler, goal_transitions(100, energy=first_half), size=100)
    assert (buffer.sample()["index"] < 50).all()
    tradeoff.update(distance=0.0)  # λ changes between two samples of the same draw
    assert buffer.sample()["tradeoff"][0].item() == pytest.approx(tradeoff.value)
    # The full buffer is overwritten (same length): now only the second half has energy.
    buffer.extend(goal_transitions(100, seed=1, energy=1.0 - first_half))
    assert (buffer.sample()["index"] >= 50).all()


def test_curriculum_with_ebp_draws_only_energetic_rows(graph):
    energy = (torch.arange(1000) >= 500).float()
    sampler = GraphCurriculumSampler(graph, num_candidates=3, tradeoff=1.0, energy_key="energy")
    index = make_buffer(sampler, goal_transitions(1000, energy=energy)).sample()["index"]
    assert (index >= 500).all()


# ----------------------------------------------------------------------------- CHER


def test_cher_prefers_goals_near_targets_with_large_tradeoff():
    data = goal_transitions(3000)
    uniform = make_buffer(RandomSampler(), data)
    cher = make_buffer(CherSampler(pool_size=500, tradeoff=50.0), data)
    def to_target(batch) -> float:
        return EuclideanMetric().distance(batch["desired_goal"], batch["task_goal"]).mean().item()

    d_uniform = mean_over_batches(uniform, to_target, 5)
    d_cher = mean_over_batches(cher, to_target, 5)
    assert d_cher < 0.8 * d_uniform, (d_cher, d_uniform)


def test_cher_similarity_graph_excludes_self_even_with_duplicates():
    sampler = CherSampler(neighbours=1)
    goals = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    neighbour, similarity = sampler.similarity_graph(goals)
    assert neighbour[:, 0].tolist()[2:] == [1, 2] or neighbour[:, 0].tolist()[2:] == [0, 2]
    assert neighbour[0, 0] == 1 and neighbour[1, 0] == 0  # the duplicate, not itself
    d = torch.tensor([0.0, 0.0, 1.0, 2.0])
    torch.testing.assert_close(similarity[:, 0], torch.exp(-d**2 / d.mean() ** 2))


def plain_greedy(neighbour, similarity, penalty, batch_size, subset_size, seed):
    """CHER's lazier-than-lazy greedy as a plain loop: every step scans the whole pool for each candidate."""
    g = torch.Generator().manual_seed(seed)
    size, k = neighbour.shape
    draws = torch.randint(size, (batch_size, 4 * subset_size), generator=g).tolist()
    nb, sim, pen = neighbour.tolist(), similarity.double().tolist(), penalty.double().tolist()
    cover, taken, chosen = [0.0] * size, set(), []
    for row in draws:
        subset = []
        for c in row:
            if c not in taken and c not in subset and len(subset) < subset_size:
                subset.append(c)
        if len(subset) < subset_size:
            free = torch.tensor([0.0 if i in taken else 1.0 for i in range(size)])
            subset = torch.multinomial(free, subset_size, replacement=False, generator=g).tolist()
        best, best_score = None, None
        for c in subset:
            gain = 0.0
            for v in range(size):
                for j in range(k):
                    if nb[v][j] == c:
                        gain += max(0.0, sim[v][j] - cover[v])
            if best is None or gain - pen[c] > best_score:
                best, best_score = c, gain - pen[c]
        for v in range(size):
            for j in range(k):
                if nb[v][j] == best:
                    cover[v] = max(cover[v], sim[v][j])
        taken.add(best)
        chosen.append(best)
    return chosen, cover


@pytest.mark.parametrize("size, batch, k, lam", [(60, 20, 1, 0.0), (60, 58, 1, 1.0), (200, 64, 1, 0.3),
                                                 (300, 200, 1, 0.3), (200, 64, 2, 0.3), (150, 148, 2, 0.0)])
def test_cher_greedy_chooses_as_a_plain_loop(size, batch, k, lam):
    """Same draws, same choices; the pool nearly used up (batch = size - 2) exercises the fallback draw,
    and 200 of 300 makes later steps' draws hit earlier winners often (k = 1 follows them in rounds)."""
    from gchgg.samplers.cher import lazier_than_lazy_greedy

    for seed in range(3):
        g = torch.Generator().manual_seed(seed)
        goals = torch.rand(size, 3, generator=g).round(decimals=1)  # a coarse lattice: copies and ties
        neighbour, similarity = CherSampler(neighbours=k).similarity_graph(goals)
        penalty = lam * goals.norm(dim=-1)
        expected, cover = plain_greedy(neighbour, similarity, penalty, batch, 3, seed)
        for window in (1, 7, 64):
            chosen, fast_cover = lazier_than_lazy_greedy(neighbour, similarity, penalty, batch, 3,
                                                         torch.Generator().manual_seed(seed), window=window)
            assert chosen.tolist() == expected, (seed, window)
            assert fast_cover.tolist() == torch.tensor(cover, dtype=torch.float32).tolist()


def test_cher_groups_near_equal_float32_goals_without_a_hash_collision():
    """Two resting-object goals recorded on push_new, float32 widened to float64 (29 low bits zero): the old
    weighted sum of the coordinates' bits gave them one hash, which sent every grouping to the slow path."""
    import numpy as np

    from gchgg.samplers.cher import _hash_rows, nearest_other

    pair = np.array([[0.7050896883010864, 0.2486274093389511, 0.8698921203613281],
                     [0.705089807510376, 0.24862734973430634, 0.8698922395706177]], dtype=np.float32).astype(np.float64)
    weights = np.arange(1, 7, 2, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    assert len(set((pair.view(np.uint64) * weights).sum(1).tolist())) == 1  # the collision the fix removes
    assert len(set(_hash_rows(pair).tolist())) == 2
    index, distance = nearest_other(np.concatenate([pair, pair[:1]]))
    assert index.tolist() == [2, 0, 0] and distance[1] > 0


def test_cher_nearest_other_is_the_exact_nearest_neighbour():
    from gchgg.samplers.cher import nearest_other

    g = torch.Generator().manual_seed(0)
    points = torch.cat([torch.rand(300, 3, generator=g), torch.full((40, 3), 0.5), torch.rand(5, 3, generator=g)])
    points = points[torch.randperm(len(points), generator=g)].double().numpy()
    index, distance = nearest_other(points)
    for i in range(len(points)):
        d = [math.dist(points[i], points[j]) if j != i else math.inf for j in range(len(points))]
        assert distance[i] == pytest.approx(min(d), abs=1e-12)
        assert index[i] != i and d[index[i]] == pytest.approx(min(d), abs=1e-12)
        nearest = [j for j in range(len(points)) if d[j] == min(d)]
        if len({tuple(points[j]) for j in nearest}) == 1:  # one nearest position: its first copy
            assert index[i] == nearest[0]


def test_cher_needs_a_large_enough_pool():
    buffer = make_buffer(CherSampler(pool_size=50), goal_transitions(100))
    with pytest.raises(ValueError, match="pool_size >= batch_size \\+ subset_size - 1 = 66"):
        buffer.sample()


# ----------------------------------------------------------------------------- TorchRL pipeline, state, seeds


def samplers(graph):
    return {
        "ebp": lambda: EnergySampler("energy"),
        "curriculum": lambda: GraphCurriculumSampler(graph, 4, AdaptiveTradeoff(), energy_key="energy"),
        "cher": lambda: CherSampler(pool_size=300, tradeoff=ExponentialTradeoff()),
    }


def rollout(num: int, steps: int, seed: int) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    path = (torch.rand(num, 1, 3, generator=g) + torch.randn(num, steps + 1, 3, generator=g).cumsum(1) * 0.01)
    return TensorDict(
        {"observation": torch.randn(num, steps, 6, generator=g), "action": torch.rand(num, steps, 3, generator=g),
         "achieved_goal": path[:, :-1], "desired_goal": torch.rand(num, 1, 3, generator=g).expand(num, steps, 3),
         "next": {"observation": torch.randn(num, steps, 6, generator=g), "achieved_goal": path[:, 1:],
                  "reward": -torch.ones(num, steps, 1), "done": torch.zeros(num, steps, 1, dtype=torch.bool)}},
        [num, steps],
    )


@pytest.mark.parametrize("name", ["ebp", "curriculum", "cher"])
def test_plain_torchrl_pipeline_before_full_and_after_wrapping(graph, name):
    def reward(achieved, goal):
        return torch.where((achieved - goal).norm(dim=-1) > 0.05, -1.0, 0.0)

    her = HindsightRelabel(reward, k=4, generator=torch.Generator().manual_seed(0))
    energy = EpisodeEnergy()
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), sampler=samplers(graph)[name](),
                                    batch_size=32, generator=torch.Generator().manual_seed(0))
    buffer.extend(her(energy(rollout(4, 20, seed=0))))  # 400 rows: not full
    batch = buffer.sample()
    assert batch.batch_size == (32,) and (batch["index"] < 400).all()
    for seed in (1, 2):
        buffer.extend(her(energy(rollout(4, 20, seed=seed))))  # 1,200 rows written: wrapped
    assert len(buffer) == 1000
    batch = buffer.sample()
    stored = buffer.storage[batch["index"]]
    assert torch.equal(batch["desired_goal"], stored["desired_goal"])
    assert torch.equal(batch["next", "reward"], stored["next", "reward"])


@pytest.mark.parametrize("name", ["ebp", "curriculum", "cher"])
def test_same_seed_same_indices(graph, name):
    data = goal_transitions(2000, energy=torch.rand(2000, generator=torch.Generator().manual_seed(3)))
    first = make_buffer(samplers(graph)[name](), data, seed=7)
    second = make_buffer(samplers(graph)[name](), data, seed=7)
    other = make_buffer(samplers(graph)[name](), data, seed=8)
    a, b, c = (buffer.sample()["index"] for buffer in (first, second, other))
    assert torch.equal(a, b) and not torch.equal(a, c)


@pytest.mark.parametrize("name", ["ebp", "curriculum", "cher"])
def test_state_round_trips(graph, name, tmp_path):
    sampler = samplers(graph)[name]()
    if hasattr(sampler, "tradeoff"):
        sampler.tradeoff.update(distance=0.25)
        sampler.tradeoff.update(distance=0.1)
    state = sampler.state_dict()
    fresh = samplers(graph)[name]()
    fresh.load_state_dict(state)
    assert fresh.state_dict() == state
    sampler.dumps(tmp_path / name)
    loaded = samplers(graph)[name]()
    loaded.loads(tmp_path / name)
    assert loaded.state_dict() == state
    if hasattr(sampler, "tradeoff"):
        assert loaded.tradeoff.value == sampler.tradeoff.value != 0.0
    # through the buffer: the same generator state then draws the same indices
    data = goal_transitions(1000, energy=torch.rand(1000, generator=torch.Generator().manual_seed(0)))
    buffer = make_buffer(sampler, data, seed=5)
    buffer.dumps(tmp_path / "buffer")
    restored = make_buffer(samplers(graph)[name](), goal_transitions(10, energy=torch.ones(10)), size=1000)
    restored.loads(tmp_path / "buffer")
    assert restored.sampler.state_dict() == state
    assert torch.equal(buffer.sample()["index"], restored.sample()["index"])


def test_sampler_errors_name_the_problem(graph):
    empty = TensorDictReplayBuffer(storage=LazyTensorStorage(10), sampler=EnergySampler(), batch_size=4)
    with pytest.raises(RuntimeError, match="empty storage"):
        empty.sample()
    buffer = make_buffer(GraphCurriculumSampler(graph, target_key="goal_of_episode"), goal_transitions(100))
    with pytest.raises(KeyError, match="'goal_of_episode'.*HindsightRelabel writes"):
        buffer.sample()
    episodes = TensorDictReplayBuffer(storage=LazyTensorStorage(10, ndim=2), sampler=GraphCurriculumSampler(graph),
                                      batch_size=4)
    episodes.extend(goal_transitions(20).view(2, 10))
    with pytest.raises(ValueError, match="1-D storage"):
        episodes.sample()
    with pytest.raises(ValueError, match="num_candidates must be an integer >= 1, got 0"):
        GraphCurriculumSampler(graph, num_candidates=0)
    with pytest.raises(TypeError, match="distance"):
        GraphCurriculumSampler(object())


# ----------------------------------------------------------------------------- trade-off schedules


def test_tradeoff_schedules():
    adaptive = AdaptiveTradeoff(eta=1000.0, sigma=0.3)
    assert adaptive.value == 0.0  # before the first update, as in the original code
    assert adaptive.update(distance=0.0) == 1000.0
    assert adaptive.update(distance=0.3) == pytest.approx(1000.0 * math.exp(-0.3 / 0.09))
    assert adaptive.update(distance=math.inf) == 0.0
    with pytest.raises(ValueError, match="needs distance"):
        adaptive.update()
    with pytest.raises(ValueError, match="sigma must be a number > 0, got 0"):
        AdaptiveTradeoff(sigma=0)
    exponential = ExponentialTradeoff(lambda_0=2.0, tau=0.1)
    for _ in range(3):
        exponential.update()
    assert exponential.value == pytest.approx(2.0 * 1.1**3)  # eq. 4
    restored = ExponentialTradeoff()
    restored.load_state_dict(exponential.state_dict())
    assert restored.value == exponential.value
    assert as_tradeoff(0.5).value == 0.5 and isinstance(as_tradeoff(2), FixedTradeoff)
    assert as_tradeoff(adaptive) is adaptive
    with pytest.raises(TypeError, match="tradeoff must be"):
        as_tradeoff("large")
    with pytest.raises(ValueError, match="tradeoff must be a number >= 0"):
        FixedTradeoff(-1.0)


def test_sampler_reads_the_schedule_at_every_sample(graph):
    schedule = AdaptiveTradeoff()
    buffer = make_buffer(GraphCurriculumSampler(graph, 2, schedule), goal_transitions(300))
    assert buffer.sample()["tradeoff"][0] == 0.0
    schedule.update(distance=0.09)
    assert buffer.sample()["tradeoff"][0].item() == pytest.approx(1000 * math.exp(-1.0))


def test_curriculum_cache_follows_overwrites_and_buffer_writes(graph):
    # The per-row cache (goal vertex, goal-to-target distance) must follow rows overwritten in a
    # full buffer and rows reported with mark_update (TorchRL's buffer[index] = ... does not tell
    # the sampler): F_prox and F_div always match the stored rows.
    sampler = GraphCurriculumSampler(graph, num_candidates=4, tradeoff=2.0, unreachable_distance=2.5)
    buffer = make_buffer(sampler, goal_transitions(300, seed=0), size=300, batch=128)
    buffer.sample()  # fills the cache
    buffer.extend(goal_transitions(200, seed=1))  # wraps: rows 0..199 overwritten
    buffer.sample()
    buffer[torch.arange(200, 300)] = goal_transitions(100, seed=2)
    sampler.mark_update(torch.arange(200, 300))
    for _ in range(3):
        batch = buffer.sample()
        stored = buffer.storage[batch["index"]]
        assert torch.equal(batch["desired_goal"], stored["desired_goal"])
        distance = graph.distance(stored["desired_goal"], stored["task_goal"])
        expected = -torch.where(torch.isfinite(distance), distance, 2.5).sum()
        assert batch["proximity"][0].item() == pytest.approx(expected.item(), rel=1e-5)
        nearest = nearest_neighbour_distances(stored["desired_goal"][None], graph, neighbours=None)
        diversity = torch.where(torch.isfinite(nearest), nearest, 0.0).sum()
        assert batch["diversity"][0].item() == pytest.approx(diversity.item(), rel=1e-5)
    buffer.empty()
    buffer.extend(goal_transitions(100, seed=3))
    assert (buffer.sample()["index"] < 100).all()


# ----------------------------------------------------------------------------- Alg. 1's choice


def reference_objective(metric, goals, targets, tradeoff, scale):
    """F of each candidate ``[K]`` from all-pairs metric distances (goals, targets ``[K, B, 3]``)."""
    pairs = metric.distance(goals.unsqueeze(2), goals.unsqueeze(1))  # [K, B, B]
    pairs = pairs + torch.diag(torch.full((goals.shape[1],), math.inf))  # j != i
    nearest = pairs.min(-1).values
    f_div = torch.where(torch.isfinite(nearest), nearest, 0.0).sum(-1)  # eq. 19
    f_prox = -metric.distance(goals, targets).sum(-1)  # eq. 15, C = 0
    if scale == "standardized":
        f_div = f_div / f_div.std(correction=0)
        f_prox = f_prox / f_prox.std(correction=0)
    return f_div + tradeoff * f_prox


@pytest.mark.parametrize("scale", ["raw", "standardized"])
@pytest.mark.parametrize("metric_name", ["graph", "euclidean"])
def test_returned_batch_is_the_argmax_of_F_over_the_candidates(scale, metric_name, graph):
    # Uniform candidates are torch.randint(n, (draw_ahead, K, B)) from the buffer's generator (see
    # the class docstring): replaying that draw gives the K candidates of each sample, scored here
    # independently from all pairs; λ changes between samples of one drawn-ahead pool.
    metric = graph if metric_name == "graph" else EuclideanMetric()
    data = goal_transitions(3000, seed=4)
    on_graph = torch.isfinite(graph.distance(data["desired_goal"], data["task_goal"]))
    data = data[on_graph]
    data["row"] = torch.arange(len(data))
    n, k, b, ahead = len(data), 6, 48, 4
    schedule = AdaptiveTradeoff(eta=100.0, sigma=0.3)
    sampler = GraphCurriculumSampler(metric, k, schedule, neighbours=3, draw_ahead=ahead, scale=scale,
                                     diagnostics=True)
    buffer = make_buffer(sampler, data, seed=11, batch=b)
    candidates = torch.randint(n, (ahead, k, b), generator=torch.Generator().manual_seed(11))
    goals, targets = data["desired_goal"][candidates], data["task_goal"][candidates]
    for sample, distance in enumerate([math.inf, 0.3, 0.05, 0.6]):  # λ = 0, 3.6, 57, 0.0015
        lam = schedule.update(distance=distance)
        batch = buffer.sample()
        chosen = [i for i in range(k) if torch.equal(candidates[sample, i], batch["row"])]
        assert chosen, "the batch is not one of the drawn candidates"
        objective = reference_objective(metric, goals[sample], targets[sample], lam, scale)
        assert objective[chosen[0]] >= objective.max() - 1e-5 * objective.abs().max(), (sample, objective, chosen)
        best_proximity = int((-metric.distance(goals[sample], targets[sample]).sum(-1)).argmax())
        assert batch["diversity_decided"][0].item() == float(chosen[0] != best_proximity)


@pytest.mark.parametrize("diagnostics", [False, True])
def test_info_holds_the_choice_and_its_diagnostics_on_request(diagnostics):
    # The chosen candidate's F_div, F_prox and λ always; the three diagnostics only with diagnostics=True,
    # and then equal to their definitions over the K candidates of the sample (one pool: replayable).
    data = goal_transitions(500, seed=2)
    k, b, lam = 4, 32, 2.0
    sampler = GraphCurriculumSampler(EuclideanMetric(), k, lam, neighbours=None, draw_ahead=1, diagnostics=diagnostics)
    buffer = make_buffer(sampler, data, seed=3, batch=b)
    batch, info = buffer.sample(return_info=True)
    basic = {"diversity", "proximity", "tradeoff"}
    extra = {"diversity_spread", "proximity_spread", "diversity_decided"}
    assert set(info) - {"index"} == (basic | extra if diagnostics else basic)
    assert all(batch[key].shape == (b,) and (batch[key] == info[key]).all() for key in set(info) - {"index"})
    candidates = torch.randint(len(data), (1, k, b), generator=torch.Generator().manual_seed(3))[0]
    goals, targets = data["desired_goal"][candidates], data["task_goal"][candidates]
    pairwise = torch.cdist(goals.double(), goals.double()) + torch.diag(torch.full((b,), math.inf)).double()
    diversity = pairwise.min(-1).values.sum(-1)
    proximity = -(goals.double() - targets.double()).norm(dim=-1).sum(-1)
    best = int((diversity + lam * proximity).argmax())
    assert torch.equal(info["index"], candidates[best])
    assert info["diversity"].item() == pytest.approx(diversity[best].item(), rel=1e-5)
    assert info["proximity"].item() == pytest.approx(proximity[best].item(), rel=1e-5)
    assert info["tradeoff"].item() == lam and info["tradeoff"].dtype == torch.float32
    if diagnostics:
        assert info["diversity_spread"].item() == pytest.approx(diversity.std(correction=0).item(), rel=1e-4)
        assert info["proximity_spread"].item() == pytest.approx((lam * proximity).std(correction=0).item(), rel=1e-4)
        assert info["diversity_decided"].item() == float(best != int(proximity.argmax()))


PATHS = {  # sampler settings -> the variant they stand for
    "paper": dict(),  # eq. 15 to the episode's target, eq. 19 of the hindsight goals, λ raw
    "ebp": dict(energy_key="energy", unreachable_distance=2.5),
    "code": dict(goal_key="achieved_goal", target_key="desired_goal", diversity_key="achieved_goal",
                 diversity_metric=EuclideanMetric()),  # the authors' code: achieved goals, Euclidean F_div
    "standardized": dict(scale="standardized", energy_key="energy", neighbours=1),
}


@pytest.mark.parametrize("variant", list(PATHS))
@pytest.mark.parametrize("metric_name", ["graph", "euclidean"])
def test_plain_and_fast_paths_give_the_same_batches_and_info(graph, metric_name, variant):
    # fast=False runs Alg. 1's step 1 as written: K candidates drawn at each sample, scored from the stored
    # goals, nearest neighbours from all pairs. The fast path (candidates drawn ahead, per-row caches,
    # the shortlist) must give the same indices and info, bit for bit: with draw_ahead=1 across writes,
    # including writes that wrap the storage, and with draw_ahead=8 (a new pool after 8 samples) between writes.
    metric = graph if metric_name == "graph" else EuclideanMetric()
    g = torch.Generator().manual_seed(7)
    data = goal_transitions(900, seed=5, energy=torch.rand(900, generator=g).round(decimals=1))
    data["achieved_goal"] = data["desired_goal"] + torch.randn(900, 3, generator=g) * 0.1
    data["desired_goal"][::7] = torch.tensor([0.0, 0.0, 0.0])  # inside the wall: off the graph
    data["desired_goal"][1::9] = data["desired_goal"][2::9][:100]  # repeated goals

    def samples(fast: bool, draw_ahead: int, writes: bool) -> list[dict]:
        schedule = AdaptiveTradeoff(eta=50.0, sigma=0.3)
        sampler = GraphCurriculumSampler(metric, 4, schedule, draw_ahead=draw_ahead, diagnostics=True, fast=fast,
                                         on_write="redraw" if variant == "paper" else "keep", **PATHS[variant])
        buffer = make_buffer(sampler, data[:600], size=700, seed=3, batch=48)
        infos = []
        for step in range(12):
            schedule.update(distance=0.05 * step)  # λ changes between samples of one pool
            if writes and step % 3 == 1:
                buffer.extend(data[600 + 25 * step : 625 + 25 * step])  # the storage wraps at 700
            infos.append(buffer.sample(return_info=True)[1])
        return infos

    for draw_ahead, writes in ((1, True), (8, False)):
        plain, fast = samples(False, draw_ahead, writes), samples(True, draw_ahead, writes)
        for step, (a, b) in enumerate(zip(plain, fast, strict=True)):
            assert set(a) == set(b) and all(torch.equal(a[key], b[key]) for key in a), (draw_ahead, step)


@pytest.fixture(scope="module")
def recorded_push_new():
    """6,000 transitions drawn uniformly from the buffer of a push_new gchgg run after 7 iterations
    (tests/data/push_new_buffer.csv: desired, task and achieved goals, EBP energy; 0.1 mm text) and a push_new graph."""
    import numpy as np

    import envs

    rows = torch.from_numpy(np.loadtxt(Path(__file__).parent / "data" / "push_new_buffer.csv", delimiter=",")).float()
    geometry = envs.geometry("push_new")
    push_graph = GoalGraph(geometry.field, geometry.obstacles, n=(21, 21, 6), margin=0.02, cache_dir=None)
    data = TensorDict({"desired_goal": rows[:, 0:3], "task_goal": rows[:, 3:6], "achieved_goal": rows[:, 6:9],
                       "energy": rows[:, 9]}, [len(rows)])
    return push_graph, data


def test_standardized_scale_lets_diversity_decide(recorded_push_new):
    # Raw sums: F_prox's spread across candidates dwarfs F_div's, so proximity decides at any λ that
    # is not tiny. Standardized: λ = 1 weighs both equally.
    push_graph, data = recorded_push_new
    decided = {}
    for scale in ("raw", "standardized"):
        for lam in (0.1, 1.0, 10.0):
            sampler = GraphCurriculumSampler(
                push_graph, 8, lam, target_key="task_goal", energy_key="energy", scale=scale, diagnostics=True
            )
            buffer = make_buffer(sampler, data, seed=0, batch=256)
            decided[scale, lam] = sum(buffer.sample()["diversity_decided"][0].item() for _ in range(64)) / 64
    print("\nfraction of samples diversity decided (recorded push_new buffer, K = 8, B = 256, 64 samples):")
    for (scale, lam), fraction in decided.items():
        print(f"  {scale:12s} lambda={lam:<5g} {fraction:.2f}")
    assert decided["raw", 1.0] <= 0.1 and decided["raw", 10.0] <= 0.05
    assert decided["standardized", 0.1] >= 0.6
    assert 0.2 <= decided["standardized", 1.0] <= 0.9
    assert decided["standardized", 10.0] <= 0.3
    assert decided["standardized", 1.0] > decided["raw", 1.0] + 0.2


@pytest.mark.parametrize("storage_cls", [LazyTensorStorage, LazyMemmapStorage])
@pytest.mark.parametrize("name", ["ebp", "curriculum", "cher"])
def test_dumps_and_loads_continue_with_the_same_batches(name, storage_cls, tmp_path):
    # Saved at any point of a drawn-ahead pool (draw_ahead = 8: after 0, 3, 8 and 9 samples), a
    # restored buffer returns the batches the original would have returned.
    def sampler():
        return {
            "ebp": lambda: EnergySampler("energy"),
            "curriculum": lambda: GraphCurriculumSampler(EuclideanMetric(), 4, AdaptiveTradeoff(), energy_key="energy"),
            "cher": lambda: CherSampler(EuclideanMetric(), pool_size=200, tradeoff=1.0),
        }[name]()

    def buffer():
        return TensorDictReplayBuffer(storage=storage_cls(4000), sampler=sampler(), batch_size=64,
                                      generator=torch.Generator().manual_seed(1))

    data = goal_transitions(3000, energy=torch.rand(3000, generator=torch.Generator().manual_seed(2)))
    for before in (0, 3, 8, 9):
        original = buffer()
        original.extend(data)
        for _ in range(before):
            original.sample()
        folder = tmp_path / f"{before}"
        original.dumps(folder)
        restored = buffer()
        restored.loads(folder)
        for _ in range(10):
            assert torch.equal(original.sample()["index"], restored.sample()["index"]), before


# ----------------------------------------------------------------------------- threads


class _ThreadCountingMetric(EuclideanMetric):
    """Euclidean distances that record the torch thread count they were computed under."""

    def __init__(self) -> None:
        super().__init__()
        self.threads: set[int] = set()

    def distance(self, a, b):
        self.threads.add(torch.get_num_threads())
        return super().distance(a, b)


@pytest.mark.parametrize("kind", ["curriculum", "cher", "ebp"])
def test_samplers_run_on_one_thread_and_restore_the_callers_count(kind, monkeypatch):
    import importlib

    metric = _ThreadCountingMetric()
    sampler = {"curriculum": lambda: GraphCurriculumSampler(metric, 4, 1.0),
               "cher": lambda: CherSampler(metric, pool_size=128),
               "ebp": lambda: EnergySampler()}[kind]()
    module = importlib.import_module({"curriculum": "gchgg.samplers.curriculum", "cher": "gchgg.samplers.cher",
                                      "ebp": "gchgg.samplers.energy"}[kind])
    reads: set[int] = set()
    read_field = module.read_field
    monkeypatch.setattr(module, "read_field", lambda *a, **k: reads.add(torch.get_num_threads()) or read_field(*a, **k))
    buffer = make_buffer(sampler, goal_transitions(2000, energy=torch.rand(2000)), batch=32)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        sampler.sample(buffer.storage, 32)  # reads the storage (energies, goals) and, but for EBP, the metric
        assert reads == {1} and metric.threads <= {1}
        assert torch.get_num_threads() == 2  # the caller's count, restored
    finally:
        torch.set_num_threads(before)
