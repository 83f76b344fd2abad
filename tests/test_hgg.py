"""Tests of HGG / G-HGG intermediate goal generation (gchgg/hgg.py): pool, eq. 6 cost, matching, D_G, stop."""

from __future__ import annotations

import io
import itertools
import math

import pytest
import torch

from envs.geometry import geometry
from envs.reward import DEFAULT_THRESHOLD
from gchgg.graph import EuclideanMetric, GoalGraph
from gchgg.hgg import HGGGoalGenerator, TrajectoryPool, estimate_max_distance

GAMMA = 0.98


def zero_value(observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    return torch.zeros(goal.shape[0])


def line(start, end, points: int = 11) -> torch.Tensor:
    """``points`` goals evenly spaced from ``start`` to ``end``: [points, 3]."""
    t = torch.linspace(0, 1, points)[:, None]
    return torch.tensor(start) * (1 - t) + torch.tensor(end) * t


def polyline(*corners, points_per_leg: int = 11) -> torch.Tensor:
    legs = [line(a, b, points_per_leg)[(1 if i else 0):] for i, (a, b) in enumerate(itertools.pairwise(corners))]
    return torch.cat(legs)


def generator_with(trajectories: torch.Tensor, metric=None, observations=None, **kwargs) -> HGGGoalGenerator:
    pool = TrajectoryPool(capacity=kwargs.pop("capacity", 1000))
    if observations is None:
        observations = torch.zeros(trajectories.shape[0], 4)
    assert pool.add(trajectories, observations).all()
    kwargs.setdefault("max_dis", 1.0)
    return HGGGoalGenerator(metric or EuclideanMetric(), kwargs.pop("value_fn", zero_value), pool=pool, **kwargs)


# ---------------------------------------------------------------------- trajectory pool


def test_pool_admits_only_trajectories_that_moved_more_than_the_threshold():
    pool = TrajectoryPool(capacity=10, min_displacement=0.01)
    # displacement first -> last point: 0, 0.01 (not more than the threshold), 0.011, and one that
    # wanders 0.5 m but comes back (the rule looks at the final point only).
    ends = torch.tensor([[0.0, 0, 0], [0.01, 0, 0], [0.0, 0.011, 0], [0.0, 0, 0]])
    trajectories = torch.zeros(4, 3, 3)  # 4 trajectories of 3 points
    trajectories[:, -1] = ends
    trajectories[3, 1] = torch.tensor([0.5, 0, 0])
    admitted = pool.add(trajectories, torch.arange(4.0)[:, None].expand(4, 2))
    assert admitted.tolist() == [False, False, True, False]
    assert len(pool) == 1
    assert torch.equal(pool.achieved_goals[0], trajectories[2])
    assert torch.equal(pool.initial_observations[0], torch.tensor([2.0, 2.0]))


def test_pool_is_fifo_and_keeps_the_newest():
    pool = TrajectoryPool(capacity=3)
    trajectories = line((0, 0, 0), (1, 0, 0), 4)[None].repeat(5, 1, 1)  # all admitted
    observations = torch.arange(5.0)[:, None]
    pool.add(trajectories[:2], observations[:2])
    pool.add(trajectories[2:], observations[2:])  # 5 added, capacity 3: 0 and 1 are overwritten
    assert sorted(pool.initial_observations[:, 0].tolist()) == [2.0, 3.0, 4.0]
    pool.add(trajectories[:1], torch.tensor([[9.0]]))  # overwrites the oldest, 2
    assert sorted(pool.initial_observations[:, 0].tolist()) == [3.0, 4.0, 9.0]
    big = TrajectoryPool(capacity=2)
    big.add(trajectories, observations)  # more admitted at once than fit: the last two stay
    assert sorted(big.initial_observations[:, 0].tolist()) == [3.0, 4.0]


def test_pool_rejects_bad_input():
    pool = TrajectoryPool()
    with pytest.raises(ValueError, match=r"\[N, T \+ 1, 3\]"):
        pool.add(torch.zeros(2, 5, 2), torch.zeros(2, 4))
    with pytest.raises(ValueError, match="one per trajectory"):
        pool.add(torch.zeros(2, 5, 3), torch.zeros(3, 4))
    with pytest.raises(ValueError, match="finite"):
        pool.add(torch.full((1, 5, 3), math.nan), torch.zeros(1, 4))
    pool.add(line((0, 0, 0), (1, 0, 0), 5)[None], torch.zeros(1, 4))
    with pytest.raises(ValueError, match="do not fit the pool"):
        pool.add(line((0, 0, 0), (1, 0, 0), 6)[None], torch.zeros(1, 4))
    with pytest.raises(ValueError, match="capacity"):
        TrajectoryPool(capacity=0)
    with pytest.raises(ValueError, match="min_displacement"):
        TrajectoryPool(min_displacement=-0.1)


# ---------------------------------------------------------------------- the cost of eq. 6 and the matching


def test_cost_matches_eq6_by_hand_and_the_matching_is_the_exact_optimum():
    g = torch.Generator().manual_seed(3)
    trajectories = torch.rand(4, 5, 3, generator=g)  # P = 4 trajectories of 5 points
    observations = torch.rand(4, 2, generator=g)
    initial = torch.rand(3, 3, generator=g)  # K = 3 target tasks
    targets = torch.rand(3, 3, generator=g)
    c, L, max_dis = 3.0, 5.0, 0.8

    def value(observation, goal):  # depends on s0 and g; values from -168 to 72, clipped to [-50, 0]
        return -80.0 * (observation[:, 0] - 0.3) * goal.sum(-1)

    generator = generator_with(trajectories, observations=observations, value_fn=value, c=c, L=L,
                               gamma=GAMMA, max_dis=max_dis, value_batch_size=7)  # 20 points in 3 batches
    result = generator.generate(initial, targets)

    # eq. 6 with explicit loops, in float64.
    def cost(j, i):
        terms = []
        for t in range(5):
            v = max(min(value(observations[i : i + 1].double(), trajectories[i, t : t + 1].double()).item(), 0.0),
                    -50.0)
            terms.append(torch.dist(trajectories[i, t].double(), targets[j].double()).item()
                         - v * max_dis * (1 - GAMMA) / L)
        best = min(range(5), key=terms.__getitem__)
        return c * torch.dist(trajectories[i, 0].double(), initial[j].double()).item() + terms[best], best

    table = [[cost(j, i) for i in range(4)] for j in range(3)]
    totals = {perm: sum(table[j][i][0] for j, i in enumerate(perm)) for perm in itertools.permutations(range(4), 3)}
    best_perm = min(totals, key=totals.get)
    assert sorted(totals.values())[1] - totals[best_perm] > 1e-3  # the optimum is unique
    assert result.trajectory_index.tolist() == list(best_perm)
    assert result.total_cost == pytest.approx(totals[best_perm], abs=1e-5)
    for j, i in enumerate(best_perm):
        cost_ji, step = table[j][i]
        assert result.cost[j].item() == pytest.approx(cost_ji, abs=1e-5)
        assert result.step_index[j].item() == step
        assert torch.equal(result.goals[j], trajectories[i, step])  # eq. 7: the argmin point
        assert result.distance[j].item() == pytest.approx(torch.dist(trajectories[i, step], targets[j]).item(),
                                                          abs=1e-6)
    assert result.d_g == pytest.approx(result.distance.double().mean().item())
    assert result.matched.all() and result.from_pool


def test_matched_trajectories_are_distinct_when_all_targets_want_the_same_one():
    g = torch.Generator().manual_seed(0)
    starts = torch.zeros(20, 3)
    ends = torch.rand(20, 3, generator=g) * 0.5
    ends[7] = torch.tensor([1.0, 1.0, 1.0])  # the best trajectory for every target
    trajectories = torch.stack([line(s.tolist(), e.tolist(), 6) for s, e in zip(starts, ends, strict=True)])
    targets = torch.tensor([1.0, 1.0, 1.0]) + 0.01 * torch.rand(10, 3, generator=g)
    result = generator_with(trajectories).generate(torch.zeros(10, 3), targets)
    chosen = result.trajectory_index.tolist()
    assert len(set(chosen)) == 10
    assert 7 in chosen


def test_empty_pool_returns_the_targets():
    generator = HGGGoalGenerator(EuclideanMetric(), zero_value, max_dis=1.0, stop_threshold=0.0)
    targets = torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    result = generator.generate(torch.zeros(2, 3), targets)
    assert torch.equal(result.goals, targets)
    assert not result.from_pool and not result.matched.any()
    assert result.d_g == 0.0 and result.inside_fraction == 1.0
    assert not generator.stopped  # goals not from the pool never stop HGG


# ---------------------------------------------------------------------- graph versus Euclidean at a wall


@pytest.fixture(scope="module")
def push_graph(tmp_path_factory) -> GoalGraph:
    """push_new's field and wall on a coarse lattice (0.02 m spacing in x and y, 3 layers)."""
    task = geometry("push_new")
    return GoalGraph(task.field, task.obstacles, n=(26, 36, 3), margin=0.02, cache_dir=tmp_path_factory.mktemp("graph"))


def test_graph_metric_picks_the_way_around_the_wall_euclidean_the_dead_end(push_graph):
    """push_new: the object starts behind the wall (y > 0), the targets lie in front of it (y < 0).

    One group of pool trajectories pushes the object straight toward the targets and stops against
    the wall, at the point Euclidean-closest to the targets; the other goes around the wall's free
    end (x ≈ 0.87 m) and gets less close in straight-line terms but much closer along the table.
    """
    task = geometry("push_new")
    z = task.table_height
    start = (0.71, 0.25, z)
    g = torch.Generator().manual_seed(1)
    wall_group = torch.stack([polyline(start, (0.58 + 0.02 * k, 0.07, z)) for k in range(6)])
    around_group = torch.stack([polyline(start, (0.95, 0.25, z), (0.95 - 0.005 * k, -0.10, z)) for k in range(6)])
    # Same number of points per trajectory: pad the wall group by resting at its end.
    wall_group = torch.cat(
        [wall_group, wall_group[:, -1:].expand(-1, around_group.shape[1] - wall_group.shape[1], -1)], 1
    )
    trajectories = torch.cat([wall_group, around_group])  # indices 0-5 stop at the wall, 6-11 go around
    targets = torch.tensor([[0.58, -0.18, z], [0.62, -0.15, z], [0.66, -0.20, z], [0.60, -0.24, z]])
    initial = torch.tensor(start).expand(4, 3)
    def value(s, goal):  # noise of at most 1 cm
        return -0.5 * torch.rand(goal.shape[0], generator=g)

    euclidean = generator_with(trajectories, EuclideanMetric(), value_fn=value).generate(initial, targets)
    graph = generator_with(trajectories, push_graph, value_fn=value).generate(initial, targets)

    assert (euclidean.trajectory_index < 6).all(), euclidean.trajectory_index
    assert (graph.trajectory_index >= 6).all(), graph.trajectory_index
    assert (euclidean.goals[:, 1] > 0.05).all()  # at the wall, on the far side
    assert (graph.goals[:, 1] < -0.05).all()  # past the wall's end, on the targets' side
    # Along the table, the wall group is the worse choice: D_G is larger with the Euclidean pick.
    assert push_graph.distance(euclidean.goals, targets).mean() > 1.5 * graph.d_g


def test_infinite_distances_become_the_large_finite_cost(push_graph):
    z = geometry("push_new").table_height
    inside_wall = (0.70, 0.0, z)  # on a removed vertex: every distance to it is inf
    trajectories = torch.stack([line((0.71, 0.25, z), (0.71, 0.10, z)), line((0.6, 0.25, z), (0.6, 0.15, z))])
    targets = torch.tensor([inside_wall, (0.6, 0.12, z)])
    result = generator_with(trajectories, push_graph).generate(torch.tensor([[0.71, 0.25, z]] * 2), targets)
    assert torch.isfinite(result.cost).all() and math.isfinite(result.d_g)
    assert result.distance[0].item() == 9999.0
    assert result.distance[1].item() < 0.05
    assert result.trajectory_index.tolist() == [0, 1]


def test_vertex_dedupe_gives_the_same_result_as_plain_distances(push_graph):
    class DistanceOnly:  # the graph seen through the bare metric interface (no lattice)
        lattice = None

        def distance(self, a, b):
            return push_graph.distance(a, b)

    g = torch.Generator().manual_seed(5)
    task = geometry("push_new")
    low, high = torch.tensor(task.field.low), torch.tensor(task.field.high)
    trajectories = ((low + (high - low) * torch.rand(40, 1, 3, generator=g))
                    + 0.02 * torch.randn(40, 9, 3, generator=g).cumsum(1))
    initial, targets = (torch.tensor(task.object_range.center).expand(12, 3),
                        low + (high - low) * torch.rand(12, 3, generator=g))
    keep = (trajectories[:, -1] - trajectories[:, 0]).norm(dim=-1) > 0.01
    by_vertex = generator_with(trajectories[keep], push_graph)
    plain = generator_with(trajectories[keep], DistanceOnly())
    assert by_vertex.metric.lattice is not None and plain.metric.lattice is None  # the two paths
    first, second = by_vertex.generate(initial, targets), plain.generate(initial, targets)
    assert torch.equal(first.goals, second.goals) and torch.equal(first.cost, second.cost)


# ---------------------------------------------------------------------- D_G and the stop condition


def test_d_g_shrinks_as_the_pool_moves_toward_the_targets():
    g = torch.Generator().manual_seed(2)
    targets = torch.tensor([1.0, 0.0, 0.0]) + 0.05 * torch.randn(8, 3, generator=g)
    pool = TrajectoryPool(capacity=8)
    generator = HGGGoalGenerator(EuclideanMetric(), zero_value, max_dis=1.0, pool=pool)
    d_g = []
    for reach in (0.2, 0.4, 0.6, 0.8, 1.0):  # each stage's trajectories replace the last (capacity 8)
        ends = torch.tensor([reach, 0.0, 0.0]) + 0.05 * torch.randn(8, 3, generator=g)
        pool.add(torch.stack([line((0, 0, 0), e.tolist()) for e in ends]), torch.zeros(8, 4))
        d_g.append(generator.generate(torch.zeros(8, 3), targets).d_g)
    assert all(a > b for a, b in itertools.pairwise(d_g)), d_g
    assert d_g[0] > 0.7 and d_g[-1] < 0.15


def stop_case(inside: int, k: int = 10):
    """Targets 1 m apart; trajectory j ends on target j (j < inside) or 0.3 m beside it (j >= inside)."""
    targets = torch.stack([torch.tensor([float(j), 0.0, 0.0]) for j in range(k)])
    ends = targets + torch.tensor([0.0, 0.3, 0.0]) * (torch.arange(k) >= inside)[:, None]
    starts = targets + torch.tensor([0.0, 0.5, 0.0])
    trajectories = torch.stack([line(s.tolist(), e.tolist()) for s, e in zip(starts, ends, strict=True)])
    return trajectories, starts, targets


@pytest.mark.parametrize("inside, stops", [(2, False), (3, False), (4, True), (10, True)])
def test_stop_condition_fires_above_its_threshold_and_not_at_it(inside, stops):
    trajectories, starts, targets = stop_case(inside)
    generator = generator_with(trajectories, stop_threshold=0.3)
    result = generator.generate(starts, targets)
    assert result.from_pool
    assert result.inside_fraction == inside / 10
    assert generator.stopped is stops
    assert result.stopped_now is stops  # the result says so: the caller switches what depends on HGG
    after = generator.generate(starts, targets)
    assert after.from_pool is not stops  # once stopped: plain HER, the targets themselves
    assert not after.stopped_now  # reported once
    if stops:
        assert torch.equal(after.goals, targets)


@pytest.mark.parametrize("offset, inside", [(0.049, 1.0), (0.051, 0.0)])
def test_the_stop_counts_goals_within_5_cm_of_any_target_of_the_call(offset, inside):
    """One pool trajectory serves both targets (``small_pool="repeat"``): both goals sit ``offset`` from
    target A, so B's goal is half a metre from its own target and ``offset`` from A's. Within 5 cm of
    some target (0.049 m) both count; at 0.051 m neither does, whatever target is asked. (The trajectory
    comes down the y axis to the spot, its point nearest to both targets.)"""
    a, b = torch.tensor([0.0, 0.0, 0.0]), torch.tensor([0.5, 0.0, 0.0])
    spot = a + torch.tensor([0.0, offset, 0.0])
    generator = generator_with(line((0.0, 0.5, 0.0), spot.tolist())[None], stop_threshold=0.5)
    result = generator.generate(torch.stack([a, b]), torch.stack([a, b]))
    assert result.from_pool and torch.allclose(result.goals, spot.expand(2, 3))
    assert result.inside_fraction == inside
    assert generator.stopped is (inside > 0.5)


def test_stop_condition_off_by_default():
    trajectories, starts, targets = stop_case(10)
    generator = generator_with(trajectories)
    assert generator.generate(starts, targets).inside_fraction == 1.0
    assert not generator.stopped


# ---------------------------------------------------------------------- a pool smaller than K


def small_pool_case():
    """Two trajectories ending at A = (0, 0, 0) and B = (1, 0, 0); four targets near A, one at B."""
    trajectories = torch.stack([line((0, 1, 0), (0, 0, 0)), line((1, 1, 0), (1, 0, 0))])
    targets = torch.tensor([[0.0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [0.1, 0, 0], [1.0, 0, 0]])
    return trajectories, torch.tensor([[0.0, 1, 0], [0, 1, 0], [0, 1, 0], [0, 1, 0], [1, 1, 0]]), targets


def test_small_pool_repeat_uses_each_trajectory_at_most_ceil_k_over_p_times():
    trajectories, initial, targets = small_pool_case()
    result = generator_with(trajectories, stop_threshold=0.5).generate(initial, targets)
    assert result.from_pool and result.matched.all()
    # ceil(5 / 2) = 3 uses each: three of the targets near A get A; the one with the least extra
    # cost on B (x = 0.1: 3·1 for the start, 1 − 2·0.1 for the distance) shares B with B's target.
    assert result.trajectory_index.tolist() == [0, 0, 0, 1, 1]
    assert result.goals.tolist() == [[0.0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0], [1, 0, 0]]
    assert result.total_cost == pytest.approx(0.0 + 0.01 + 0.02 + (3.0 + 0.9) + 0.0, abs=1e-5)


def test_small_pool_targets_matches_p_targets_and_keeps_the_rest():
    trajectories, initial, targets = small_pool_case()
    generator = generator_with(trajectories, small_pool="targets", stop_threshold=0.0)
    result = generator.generate(initial, targets)
    assert result.matched.sum() == 2 and not result.from_pool
    assert len(set(result.trajectory_index[result.matched].tolist())) == 2
    assert torch.equal(result.goals[~result.matched], targets[~result.matched])
    assert (result.trajectory_index[~result.matched] == -1).all()
    assert not generator.stopped  # partly the targets themselves: no stop check


# ---------------------------------------------------------------------- checkpoints, helpers and errors


def test_state_dict_round_trip_gives_the_same_goals():
    g = torch.Generator().manual_seed(4)
    trajectories = torch.rand(30, 6, 3, generator=g)
    source = generator_with(trajectories, capacity=20, stop_threshold=0.9)
    restored = HGGGoalGenerator(EuclideanMetric(), zero_value, max_dis=1.0, pool=TrajectoryPool(capacity=20))
    buffer = io.BytesIO()
    torch.save(source.state_dict(), buffer)  # plain tensors and numbers: loads with weights_only
    buffer.seek(0)
    restored.load_state_dict(torch.load(buffer, weights_only=True))
    initial, targets = torch.rand(5, 3, generator=g), torch.rand(5, 3, generator=g)
    assert torch.equal(source.generate(initial, targets).goals, restored.generate(initial, targets).goals)
    more = torch.rand(3, 6, 3, generator=g) + 1.0
    source.pool.add(more, torch.zeros(3, 4))
    restored.pool.add(more, torch.zeros(3, 4))  # same FIFO position after restore
    assert torch.equal(source.pool.achieved_goals, restored.pool.achieved_goals)
    with pytest.raises(ValueError, match="capacity"):
        TrajectoryPool(capacity=5).load_state_dict(source.pool.state_dict())


def test_state_dict_keeps_the_stop_flag():
    trajectories, starts, targets = stop_case(10)
    source = generator_with(trajectories, stop_threshold=0.5)
    source.generate(starts, targets)
    restored = generator_with(trajectories, stop_threshold=0.5)
    restored.load_state_dict(source.state_dict())
    assert source.stopped and restored.stopped
    assert torch.equal(restored.generate(starts, targets).goals, targets)


def test_estimate_max_distance_ignores_infinite_pairs(push_graph):
    z = geometry("push_new").table_height
    a = torch.tensor([[0.71, 0.25, z], [0.71, 0.25, z]])
    b = torch.tensor([[0.65, -0.2, z], [0.70, 0.0, z]])  # the second is inside the wall
    assert estimate_max_distance(push_graph, a, b) == pytest.approx(push_graph.distance(a[0], b[0]).item())
    with pytest.raises(ValueError, match="max_dis"):
        estimate_max_distance(push_graph, a[1:], b[1:])


def test_errors_name_the_problem():
    trajectories = line((0, 0, 0), (1, 0, 0))[None]
    with pytest.raises(ValueError, match="NaN"):
        generator_with(trajectories, value_fn=lambda s, g: torch.full((g.shape[0],), math.nan)).generate(
            torch.zeros(1, 3), torch.ones(1, 3))
    with pytest.raises(ValueError, match="one value per goal"):
        generator_with(trajectories, value_fn=lambda s, g: torch.zeros(g.shape[0], 2)).generate(
            torch.zeros(1, 3), torch.ones(1, 3))
    with pytest.raises(ValueError, match="no value function"):
        generator_with(trajectories, value_fn=None).generate(torch.zeros(1, 3), torch.ones(1, 3))
    with pytest.raises(ValueError, match="initial_achieved_goals"):
        generator_with(trajectories).generate(torch.zeros(2, 3), torch.ones(1, 3))
    with pytest.raises(ValueError, match="small_pool"):
        HGGGoalGenerator(EuclideanMetric(), max_dis=1.0, small_pool="pad")
    with pytest.raises(ValueError, match="max_dis"):
        HGGGoalGenerator(EuclideanMetric(), max_dis=math.inf)
    with pytest.raises(ValueError, match="stop_threshold"):
        HGGGoalGenerator(EuclideanMetric(), max_dis=1.0, stop_threshold=1.5)
    with pytest.raises(TypeError, match="distance"):
        HGGGoalGenerator(object(), max_dis=1.0)


def test_docstring_examples_run():
    import doctest

    import gchgg.hgg

    assert doctest.testmod(gchgg.hgg).failed == 0


@pytest.mark.parametrize("task, fraction", [("push_new", 0.3), ("pick_obstacle", 0.9)])
def test_a_run_stops_hgg_at_the_tasks_success_distance(task, fraction, tmp_path):
    """The trainer's goal generator counts a goal as near a target within the task's 5 cm (eq. 23), and
    stops at the task's fraction: the values the stop test above holds to."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_train import config, tiny

    from gchgg.run.parts import make_parts

    cfg = config([f"env={task}", "algo=ghgg", *tiny(tmp_path)])
    generator = make_parts(cfg).goal_generator
    assert generator.success_threshold == cfg.env.threshold == DEFAULT_THRESHOLD == 0.05  # eq. 23's 5 cm
    assert generator.stop_threshold == cfg.env.stop_threshold == fraction
