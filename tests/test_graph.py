"""Tests of the goal-space graph and d_G (gchgg/graph/) against an independent networkx lattice."""

import doctest
import itertools
import math
import os
from concurrent.futures import ThreadPoolExecutor

import networkx as nx
import numpy as np
import pytest
import torch
from scipy.sparse.csgraph import dijkstra

import gchgg.graph.grid
import gchgg.graph.lattice
import gchgg.graph.metric
import gchgg.graph.table
from gchgg.graph import (
    DEFAULT_MARGIN,
    DEFAULT_N,
    EuclideanMetric,
    GoalGraph,
    Metric,
    check_density_criterion,
    default_cache_dir,
)
from gchgg.graph.__main__ import main

# A 0.8 × 0.8 × 0.2 m field with 0.1 m spacing (9 × 9 × 3 vertices) and a wall along x at y = 0 that
# leaves a gap at x = 0.3 and 0.4 (without margin the wall removes x = -0.4 .. 0.2 at y = 0).
FIELD = ((0.0, 0.0, 0.0), (0.4, 0.4, 0.1))
WALL = ((-0.1, 0.0, 0.0), (0.3, 0.06, 0.2))
N = (9, 9, 3)


def wall_graph(margin=0.0, **kwargs):
    return GoalGraph(FIELD, [WALL], N, margin, cache_dir=kwargs.pop("cache_dir", None), **kwargs)


@pytest.fixture(scope="module")
def graph():
    return wall_graph()


def reference_distances(field, obstacles, n, margin):
    """All-pairs shortest paths on an independently built 26-connected lattice (networkx)."""
    (center, half) = (np.asarray(v, dtype=float) for v in field)
    low, spacing = center - half, 2 * half / (np.asarray(n) - 1)

    def blocked(p):
        return any(
            np.all(np.abs(p - np.asarray(c)) <= np.asarray(h) + margin + 1e-9) for c, h in obstacles
        )

    lattice = nx.Graph()
    position = {}
    for ijk in itertools.product(*(range(k) for k in n)):
        p = low + np.asarray(ijk) * spacing
        if not blocked(p):
            lattice.add_node(ijk)
            position[ijk] = p
    for ijk in lattice.nodes:
        for step in itertools.product((-1, 0, 1), repeat=3):
            other = tuple(a + s for a, s in zip(ijk, step, strict=True))
            if any(step) and other in position:
                lattice.add_edge(ijk, other, weight=float(np.linalg.norm(np.asarray(step) * spacing)))
    return position, dict(nx.all_pairs_dijkstra_path_length(lattice))


def uniform_goals(graph, count, generator, slack=0.0):
    low = torch.tensor(graph.low, dtype=torch.float32) - slack
    high = torch.tensor(graph.high, dtype=torch.float32) + slack
    return low + (high - low) * torch.rand(count, 3, generator=generator)


# ---------------------------------------------------------------------- values


def test_free_axis_and_diagonal_equal_euclidean():
    graph = GoalGraph(FIELD, [], N, 0.0, cache_dir=None)
    x = graph.lattice_axes[0].to(torch.float32)
    a = torch.stack([x, torch.full_like(x, -0.1), torch.zeros_like(x)], -1)  # a line along x
    d = graph.distance(a[:, None], a[None, :])
    expected = (x[:, None] - x[None, :]).abs()
    assert (d - expected).abs().max() <= graph.resolution / 2 + 1e-6
    assert d[0, -1] == pytest.approx(0.8, abs=1e-4)
    # A lattice diagonal is a straight run of diagonal edges: d_G is Euclidean there too.
    diagonal = torch.tensor([[-0.4, -0.4, -0.1], [-0.2, -0.2, 0.1]])
    expected = math.sqrt(0.2**2 + 0.2**2 + 0.2**2)
    assert graph.distance(diagonal[0], diagonal[1]).item() == pytest.approx(expected, abs=1e-4)
    # Between vertices d_G is never below the Euclidean distance.
    v = graph.vertices
    euclidean = torch.linalg.vector_norm(v[:, None] - v[None, :], dim=-1)
    assert (graph.distance(v[:, None], v[None, :]) >= euclidean - graph.resolution).all()


def test_across_wall_longer_and_equal_to_networkx(graph):
    a, b = torch.tensor([0.0, -0.2, 0.0]), torch.tensor([0.0, 0.2, 0.0])
    d = graph.distance(a, b).item()
    # Around the wall's end at x = 0.3: (0,-0.2) -> (0.3,0) is 2 diagonal + 1 straight edge, twice.
    assert d == pytest.approx(2 * (2 * math.sqrt(0.02) + 0.1), abs=1e-4)
    assert d > EuclideanMetric().distance(a, b).item() + 0.3

    position, reference = reference_distances(FIELD, [WALL], N, 0.0)
    assert len(position) == graph.num_vertices
    nodes = sorted(position)  # C order over the lattice, as the graph's vertices
    positions = torch.tensor(np.stack([position[k] for k in nodes]))
    assert torch.allclose(graph.vertices.double(), positions, atol=1e-6)
    expected = torch.tensor([[reference[p].get(q, math.inf) for q in nodes] for p in nodes])
    i = torch.arange(graph.num_vertices)
    got = graph.distance_between_vertices(i[:, None], i[None, :]).double()
    assert torch.equal(got.isinf(), expected.isinf())
    error = (got - expected)[expected.isfinite()].abs().max()
    assert error <= graph.resolution / 2 + 1e-6  # rounding in the table, plus float32 output


def lattice_dijkstra(field, obstacles, n, margin):
    """Free lattice points ``[V, 3]`` and their all-pairs shortest distances ``[V, V]`` (float64),
    from a 26-connected adjacency built here with numpy and scipy's Dijkstra (not the graph's own)."""
    from scipy.sparse import coo_matrix

    (center, half), n = (np.asarray(v, dtype=float) for v in field), np.asarray(n)
    spacing = 2 * half / (n - 1)
    ijk = np.stack(np.meshgrid(*(np.arange(k) for k in n), indexing="ij"), -1).reshape(-1, 3)
    points = center - half + ijk * spacing
    blocked = np.zeros(len(points), dtype=bool)
    for c, h in obstacles:
        blocked |= np.all(np.abs(points - np.asarray(c)) <= np.asarray(h) + margin + 1e-9, axis=1)
    number = np.full(len(points), -1)
    number[~blocked] = np.arange((~blocked).sum())
    grid = number.reshape(*n)
    rows, cols, weights = [], [], []
    for step in itertools.product((-1, 0, 1), repeat=3):
        if not any(step):
            continue
        target = ijk + step
        inside = np.all((target >= 0) & (target < n), axis=1)
        a, b = number[inside], grid[tuple(target[inside].T)]
        keep = (a >= 0) & (b >= 0)
        rows.append(a[keep]), cols.append(b[keep])
        weights.append(np.full(keep.sum(), np.linalg.norm(np.asarray(step) * spacing)))
    v = int((~blocked).sum())
    adjacency = coo_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), shape=(v, v))
    return points[~blocked], dijkstra(adjacency.tocsr(), directed=True)


def test_table_error_below_resolution_and_1mm():
    from envs.geometry import geometry

    task = geometry("push_new")
    graph = GoalGraph(task.field, task.obstacles, (16, 16, 6), 0.02, cache_dir=None)
    points, exact = lattice_dijkstra(task.field, task.obstacles, (16, 16, 6), 0.02)
    assert len(points) == graph.num_vertices
    goals = torch.from_numpy(points).float()
    exact = torch.from_numpy(exact)  # float64 [V, V]
    got = graph.distance(goals[:, None], goals[None, :]).double()
    finite = exact.isfinite()
    assert torch.equal(finite, got.isfinite())
    error = (got - exact)[finite].abs().max().item()
    assert error <= graph.resolution / 2 + 1e-6  # + float32 output
    assert error < 1e-3 and graph.resolution < 1e-4
    assert graph.table_bytes == 2 * (graph.num_vertices + 1) * (graph.num_vertices + 2) // 2


def reference_snap(goals, field=FIELD, obstacles=(WALL,), n=N, margin=0.0):
    """Each goal's free lattice point, written here (eq. 14: the nearest lattice point; -1 outside the field
    or on a blocked point), as an index into ``lattice_dijkstra``'s points, and which goals sit safely away
    from a rounding half-way plane or the field's faces (float32 rounding could tip those either way)."""
    (center, half), n = (np.asarray(v, dtype=float) for v in field), np.asarray(n)
    low, spacing = center - half, 2 * half / (n - 1)
    g = np.asarray(goals, dtype=np.float64)
    units = (g - low) / spacing
    ijk = np.rint(units).astype(int)
    inside = np.all((g >= low) & (g <= center + half), axis=1)
    # lattice_dijkstra numbers the free points in C order over the lattice
    lattice = np.stack(np.meshgrid(*(np.arange(k) for k in n), indexing="ij"), -1).reshape(-1, 3)
    free = np.ones(len(lattice), dtype=bool)
    for c, h in obstacles:
        free &= ~np.all(np.abs(low + lattice * spacing - np.asarray(c)) <= np.asarray(h) + margin + 1e-9, axis=1)
    number = np.full(len(lattice), -1)
    number[free] = np.arange(free.sum())
    flat = np.ravel_multi_index(tuple(np.clip(ijk, 0, n - 1).T), tuple(n))
    index = np.where(inside, number[flat], -1)  # -1 also on a blocked point
    clear = (np.abs(units - np.floor(units) - 0.5) > 1e-4).all(1)
    clear &= (np.abs(g - low) > 2e-5).all(1) & (np.abs(g - (center + half)) > 2e-5).all(1)
    return index, clear


def test_distance_of_random_goals_equals_snap_and_dijkstra_written_here(graph):
    """d_G of random goals (some outside the field, some on the wall) equals the shortest path between their
    nearest free lattice points on a lattice built here (scipy Dijkstra), ``inf`` exactly where a goal is off
    the graph: a wrong snap (floor, off by one), wrong edge weights or a table that is not shortest-path fails."""
    generator = torch.Generator().manual_seed(0)
    a, b = (uniform_goals(graph, 20_000, generator, slack=0.01) for _ in range(2))
    points, exact = lattice_dijkstra(FIELD, [WALL], N, 0.0)
    (ia, clear_a), (ib, clear_b) = reference_snap(a.numpy()), reference_snap(b.numpy())
    keep = torch.from_numpy(clear_a & clear_b)
    expected = torch.from_numpy(np.where((ia >= 0) & (ib >= 0), exact[ia, ib], math.inf))
    got = graph.distance(a, b).double()
    assert keep.float().mean() > 0.99
    got, expected = got[keep], expected[keep]
    assert torch.equal(got.isinf(), expected.isinf())
    finite = expected.isfinite()
    assert 0.5 < finite.float().mean() < 0.9  # most pairs are on the graph, some off it: both are checked
    assert (got[finite] - expected[finite]).abs().max() <= graph.resolution / 2 + 1e-6
    # pairs on either side of the wall, west of its gap at x = 0.3: the path around it is over 0.2 m longer than
    # the straight line (which a Euclidean "d_G" or a graph that ignores the wall would give)
    a, b = a[keep], b[keep]
    across = finite & (a[:, 1] < -0.05) & (b[:, 1] > 0.1) & (a[:, 0] < 0.0) & (b[:, 0] < 0.0)
    straight = torch.linalg.vector_norm(a - b, dim=-1).double()
    assert across.sum() > 100 and (got[across] > straight[across] + 0.2).all()


def test_inf_outside_field_inside_obstacle_and_nan(graph):
    inside = torch.tensor([0.3, -0.3, 0.0])
    outside = [
        [0.42, 0.0, 0.0], [-0.42, 0.0, 0.0], [0.0, 0.42, 0.0], [0.0, -0.42, 0.0],
        [0.0, 0.3, 0.11], [0.0, 0.3, -0.11], [math.nan, 0.0, 0.0], [math.inf, 0.0, 0.0],
        [0.4 + 2e-5, 0.0, 0.0], [0.0, -0.4 - 2e-5, 0.0], [0.0, 0.3, 0.1 + 2e-5],  # beyond 10 µm
    ]
    in_wall = [[0.0, 0.0, 0.0], [-0.3, 0.02, 0.05], [0.2, 0.04, -0.1]]  # nearest vertex removed
    bad = torch.tensor(outside + in_wall)
    assert graph.distance(bad, inside).isinf().all()
    assert graph.distance(inside, bad).isinf().all()
    assert graph.distance(bad, bad).isinf().all()  # even a goal to itself
    assert (graph.vertex_index(bad) == -1).all()
    # On the field's faces (within 10 µm) goals are inside; at the wall's gap they are free.
    edge = torch.tensor([[0.4, 0.4, 0.1], [-0.4 - 5e-6, -0.4, -0.1], [0.3, 0.0, 0.0]])
    assert graph.distance(edge, inside).isfinite().all()


def test_disconnected_parts_are_inf():
    full_wall = ((0.0, 0.0, 0.0), (1.0, 0.06, 1.0))
    graph = GoalGraph(FIELD, [full_wall], N, 0.0, cache_dir=None)
    south, north = torch.tensor([0.0, -0.2, 0.0]), torch.tensor([0.0, 0.2, 0.0])
    assert graph.distance(south, north).isinf()
    nearby = south + torch.tensor([0.1, -0.1, 0.0])
    assert graph.distance(south, nearby).item() == pytest.approx(math.sqrt(0.02), abs=1e-4)
    assert graph.shortest_path(south, north).shape == (0, 3)


def test_larger_margin_never_shortens():
    graphs = [wall_graph(margin) for margin in (0.0, 0.02, 0.05, 0.12)]
    removed = [math.prod(N) - g.num_vertices for g in graphs]
    assert removed == sorted(removed) and removed[0] < removed[-1]
    v = graphs[-1].vertices  # free in every graph
    previous = None
    for g in graphs:
        d = g.distance(v[:, None], v[None, :])
        if previous is not None:
            assert (d >= previous - 2 * g.resolution).all()
        previous = d
    a, b = torch.tensor([0.0, -0.3, 0.0]), torch.tensor([0.0, 0.3, 0.0])
    assert graphs[-1].distance(a, b) > graphs[0].distance(a, b) + 0.05  # the gap moved outward


def test_broadcasting_and_dtypes(graph):
    generator = torch.Generator().manual_seed(1)
    a = uniform_goals(graph, 4, generator).reshape(4, 1, 3)
    b = uniform_goals(graph, 5, generator)
    d = graph.distance(a, b)
    assert d.shape == (4, 5) and d.dtype == torch.float32
    loop = torch.tensor([[graph.distance(a[i, 0], b[j]).item() for j in range(5)] for i in range(4)])
    assert torch.equal(d, loop)
    assert torch.equal(graph.distance(a.double(), b.double()), d)
    assert graph.distance(torch.empty(0, 3), b[0]).shape == (0,)


def test_snap_nearest_and_floor():
    nearest = GoalGraph(FIELD, [], N, 0.0, cache_dir=None)
    floor = GoalGraph(FIELD, [], N, 0.0, snap="floor", cache_dir=None)
    v = nearest.vertices
    goal = torch.tensor([-0.4 + 0.07, -0.4 + 0.02, -0.1 + 0.099])
    assert torch.allclose(v[nearest.vertex_index(goal)], torch.tensor([-0.3, -0.4, 0.0]), atol=1e-6)
    assert torch.allclose(v[floor.vertex_index(goal)], torch.tensor([-0.4, -0.4, -0.1]), atol=1e-6)
    # Both map every vertex to itself, and agree on the distances of vertex goals.
    assert torch.equal(nearest.vertex_index(v), torch.arange(len(v)))
    assert torch.equal(floor.vertex_index(v), torch.arange(len(v)))


def test_vertex_index_and_distance_between_vertices(graph):
    """vertex_index maps goals to the nearest free lattice point found here (-1 off the graph), and
    distance_between_vertices of those indices equals the shortest paths of the lattice built here."""
    generator = torch.Generator().manual_seed(2)
    goals = uniform_goals(graph, 300, generator, slack=0.05)
    index = graph.vertex_index(goals)
    assert index.dtype == torch.int64 and (index >= -1).all() and (index < graph.num_vertices).all()
    points, exact = lattice_dijkstra(FIELD, [WALL], N, 0.0)
    expected, clear = reference_snap(goals.numpy())
    assert clear.all()  # no goal of this draw sits within 10 µm of a half-way plane or 20 µm of the field's faces
    assert torch.equal(index, torch.from_numpy(expected))
    on = index >= 0
    nearest = torch.from_numpy(points[expected[on.numpy()]]).float()  # the free lattice point nearest each goal, here
    assert torch.allclose(graph.vertices[index[on]], nearest, atol=1e-6)
    assert ((goals[on] - nearest).abs() <= 0.05 + 1e-6).all()  # within half a spacing on every axis
    by_vertex = graph.distance_between_vertices(index[:, None], index[None, :])
    reference = torch.from_numpy(np.where(on[:, None] & on[None, :], exact[expected[:, None], expected[None, :]],
                                          math.inf))
    assert torch.equal(by_vertex.isinf(), reference.isinf())
    finite = reference.isfinite()
    assert (by_vertex.double() - reference)[finite].abs().max() <= graph.resolution / 2 + 1e-6
    assert torch.equal(by_vertex, graph.distance(goals[:, None], goals[None, :]))
    with pytest.raises(IndexError, match=r"\[-1, "):
        graph.distance_between_vertices(torch.tensor([graph.num_vertices]), torch.tensor([0]))
    with pytest.raises(IndexError):
        graph.distance_between_vertices(torch.tensor([-2]), torch.tensor([0]))
    # The unchecked lookup of the samplers' hot path gives the same values, -1 included.
    assert (index == -1).any() and (index >= 0).any()
    assert torch.equal(graph.pair_distance(index[:, None], index[None, :]), by_vertex)
    last = torch.tensor([graph.num_vertices - 1, -1, 0])
    assert torch.equal(graph.pair_distance(last[:, None], last[None, :]),
                       graph.distance_between_vertices(last[:, None], last[None, :]))


def test_shortest_path(graph):
    a, b = torch.tensor([0.01, -0.2, 0.0]), torch.tensor([0.0, 0.21, 0.0])
    path = graph.shortest_path(a, b)
    assert torch.allclose(path[0], torch.tensor([0.0, -0.2, 0.0]), atol=1e-6)
    assert torch.allclose(path[-1], torch.tensor([0.0, 0.2, 0.0]), atol=1e-6)
    steps = (path[1:] - path[:-1]).abs()
    assert (steps <= torch.tensor(graph.spacing, dtype=torch.float32) + 1e-6).all()  # neighbours
    assert (steps.sum(-1) > 0).all()
    assert (graph.vertex_index(path) >= 0).all()  # never through a removed vertex
    assert path[:, 0].max() >= 0.3 - 1e-6  # around the wall's end
    length = torch.linalg.vector_norm(steps, dim=-1).sum().item()
    assert length == pytest.approx(graph.distance(a, b).item(), abs=graph.resolution)
    assert graph.shortest_path(a, a).shape == (1, 3)
    assert graph.shortest_path(a, torch.tensor([0.0, 0.0, 0.0])).shape == (0, 3)


def test_euclidean_metric():
    metric = EuclideanMetric()
    a = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 2.0]], dtype=torch.float64)
    d = metric.distance(a[:, None], torch.tensor([[0.0, 0.0, 0.0], [0.0, 3.0, 4.0]]))
    assert d.dtype == torch.float32
    assert torch.allclose(d, torch.tensor([[0.0, 5.0], [3.0, math.sqrt(1 + 1 + 4)]]))
    far = torch.tensor([100.0, 0.0, 0.0])
    assert metric.distance(far, -far).item() == 200.0  # no field, no inf
    assert isinstance(metric, Metric) and isinstance(wall_graph(), Metric)


# ---------------------------------------------------------------------- errors


def test_density_criterion_fires_exactly_at_the_boundary():
    field, n = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)), (5, 5, 5)  # spacing 0.5 on every axis
    at_boundary = ((0.0, 0.0, 0.0), (0.25, 0.25, 0.25))  # edge 0.5 == spacing: eq. 12 is strict
    named = r"obstacle 0 \(center=\(0.0, 0.0, 0.0\), half=\(0.25, 0.25, 0.25\)\)"
    with pytest.raises(ValueError, match=named) as error:
        GoalGraph(field, [at_boundary], n, 0.0, cache_dir=None)
    assert "must be below 0.5 m" in str(error.value) and "n_x >= 6" in str(error.value)
    GoalGraph(field, [((0.0, 0.0, 0.0), (0.25 + 1e-12,) * 3)], n, 0.0, cache_dir=None)  # above: fine
    # The margin counts: half 0.125 + margin 0.125 is again exactly the spacing.
    with pytest.raises(ValueError, match="margin 0.125"):
        GoalGraph(field, [((0.0, 0.0, 0.0), (0.125,) * 3)], n, 0.125, cache_dir=None)
    GoalGraph(field, [((0.0, 0.0, 0.0), (0.125,) * 3)], n, 0.125 + 1e-9, cache_dir=None)
    # Only the violating axes are named; a finer lattice on them fixes it.
    with pytest.raises(ValueError, match="obstacle 1") as error:
        obstacles = [((0.5, 0.5, 0.5), (0.3,) * 3), ((0.0, 0.0, 0.0), (0.3, 0.25, 0.25))]
        GoalGraph(field, obstacles, n, 0.0, cache_dir=None)
    message = str(error.value)
    assert "along y" in message and "along z" in message and "along x" not in message
    GoalGraph(field, [((0.0, 0.0, 0.0), (0.3, 0.25, 0.25))], (5, 6, 6), 0.0, cache_dir=None)
    # Only the part inside the field counts; an obstacle outside the field is ignored.
    with pytest.raises(ValueError, match="obstacle 0"):
        GoalGraph(field, [((0.0, 0.0, 1.15), (0.3, 0.3, 0.3))], n, 0.0, cache_dir=None)  # 0.15 m inside
    with pytest.warns(UserWarning, match="obstacle 0 .* does not meet the field"):
        outside = GoalGraph(field, [((0.0, 0.0, 3.0), (0.1, 0.1, 0.1))], n, 0.0, cache_dir=None)
    assert outside.num_vertices == 125


def test_kuka_tasks_satisfy_the_criterion_at_default_settings():
    from envs.geometry import GEOMETRY

    for task in GEOMETRY.values():
        for n in (DEFAULT_N, (31, 31, 15), (31, 31, 21)):
            boxes = check_density_criterion(task.field, task.obstacles, n, DEFAULT_MARGIN)
            assert len(boxes) == len(task.obstacles)
    # The inflated push_new wall is 0.12 m thick in y: 0.7 / 6 m spacing passes, 0.7 / 5 m fails.
    push = GEOMETRY["push_new"]
    check_density_criterion(push.field, push.obstacles, (31, 7, 11), DEFAULT_MARGIN)
    with pytest.raises(ValueError, match=r"obstacle 0 .*along y.*n_y >= 7"):
        check_density_criterion(push.field, push.obstacles, (31, 6, 11), DEFAULT_MARGIN)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n": (31, 31)}, "n must be three integers"),
        ({"n": (1, 9, 3)}, "each >= 2"),
        ({"n": (9.5, 9, 3)}, "n must be three integers"),
        ({"n": (True, 9, 3)}, "n must be three integers"),
        ({"margin": -0.01}, "margin must be >= 0"),
        ({"margin": math.nan}, "margin must be a finite number"),
        ({"field": ((0, 0, 0), (0.4, 0.4, 0.0))}, "field half-sizes must be > 0"),
        ({"field": ((0, 0, 0, 0), (0.4, 0.4, 0.4, 0.4))}, "field must be a box"),  # 2-D fields are allowed
        ({"field": ((0, 0), (0.4, 0.4))}, r"n must be two integers \(n_x, n_y\), for the 2-D field"),
        ({"field": 3.0}, "field must be a box"),
        ({"obstacles": [((0, 0, 0), (-0.1, 0.2, 0.2))]}, r"obstacles\[0\] half-sizes must be >= 0"),
        ({"snap": "round"}, "snap must be 'nearest' or 'floor'"),
        ({"obstacles": [((0, 0, 0), (1, 1, 1))]}, "every lattice vertex"),
        ({"n": (301, 301, 3)}, r"GiB \(more than 4 GiB\): use a smaller n"),
    ],
)
def test_bad_settings_raise(kwargs, match):
    settings = {"field": FIELD, "obstacles": [WALL], "n": N, "margin": 0.0, "cache_dir": None} | kwargs
    with pytest.raises(ValueError, match=match):
        GoalGraph(**settings)


def test_bad_goals_raise(graph):
    with pytest.raises(ValueError, match=r"shape \[\.\.\., 3\]"):
        graph.distance(torch.zeros(4, 2), torch.zeros(3))
    with pytest.raises(ValueError, match="shape"):
        graph.shortest_path(torch.zeros(2, 3), torch.zeros(3))


# ---------------------------------------------------------------------- cache


def all_pairs(graph):
    i = torch.arange(-1, graph.num_vertices)
    return graph.distance_between_vertices(i[:, None], i[None, :])


def test_cache_roundtrip_and_key(tmp_path):
    first = wall_graph(cache_dir=tmp_path)
    assert not first.loaded_from_cache and first.cache_path.exists()
    assert first.cache_path.parent == tmp_path
    assert first.cache_path.stat().st_size > first.table_bytes
    second = wall_graph(cache_dir=tmp_path)
    assert second.loaded_from_cache and second.resolution == first.resolution
    assert torch.equal(all_pairs(first), all_pairs(second))
    # Every parameter that changes the table changes the file; snap does not.
    assert wall_graph(cache_dir=tmp_path, snap="floor").loaded_from_cache
    assert wall_graph(0.01, cache_dir=tmp_path).cache_path != first.cache_path
    assert GoalGraph(FIELD, [WALL], (9, 9, 5), 0.0, cache_dir=tmp_path).cache_path != first.cache_path
    assert GoalGraph(FIELD, [], N, 0.0, cache_dir=tmp_path).cache_path != first.cache_path
    assert len(list(tmp_path.glob("goalgraph-*.bin"))) == 4
    assert not list(tmp_path.glob(".goalgraph-*"))  # no temporary files left behind
    assert first.cache_path.stat().st_mode & 0o777 == 0o644  # readable like any cache file


def test_cache_file_name_is_stable(tmp_path):
    # Cache files written before the graph's modules were split (format 2) must still be found: the key
    # hashes the same settings and format as then.
    assert wall_graph(cache_dir=tmp_path).cache_path.name == "goalgraph-d64627766ad9815909b337b1d57a03c8.bin"


def test_public_names_stay_importable_from_the_lattice_module():
    for name in gchgg.graph.lattice.__all__:
        assert getattr(gchgg.graph.lattice, name) is getattr(gchgg.graph, name)


@pytest.mark.parametrize(
    "damage", ["flip_payload", "flip_header", "truncate", "append", "empty", "garbage", "other_graph"]
)
def test_damaged_cache_is_rebuilt_not_used(tmp_path, damage):
    good = wall_graph(cache_dir=tmp_path)
    path = good.cache_path
    data = bytearray(path.read_bytes())
    if damage == "flip_payload":
        data[-101] ^= 0x01
    elif damage == "flip_header":  # a bit of the stored checksum
        data[12] ^= 0x01
    elif damage == "truncate":
        data = data[: len(data) // 2]
    elif damage == "append":
        data += b"\x00\x00"
    elif damage == "empty":
        data = bytearray()
    elif damage == "other_graph":  # an intact file of another graph under this graph's name
        data = bytearray(GoalGraph(FIELD, [], N, 0.0, cache_dir=tmp_path / "other").cache_path.read_bytes())
    else:
        data = bytearray(os.urandom(len(data)))
    path.write_bytes(bytes(data))
    with pytest.warns(RuntimeWarning, match="damaged graph cache file"):
        rebuilt = wall_graph(cache_dir=tmp_path)
    assert not rebuilt.loaded_from_cache
    assert torch.equal(all_pairs(rebuilt), all_pairs(good))
    assert wall_graph(cache_dir=tmp_path).loaded_from_cache  # rewritten intact


def test_concurrent_constructions_build_once(tmp_path):
    def construct(_):  # a finer lattice, so that each build takes a while
        return GoalGraph(FIELD, [WALL], (17, 17, 5), 0.0, cache_dir=tmp_path)

    with ThreadPoolExecutor(3) as pool:
        graphs = list(pool.map(construct, range(3)))
    assert sorted(g.loaded_from_cache for g in graphs) == [False, True, True]
    assert all(torch.equal(all_pairs(g), all_pairs(graphs[0])) for g in graphs)


def test_no_cache_and_unwritable_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.delenv("GCHGG_CACHE_DIR", raising=False)
    assert default_cache_dir() == tmp_path / "xdg" / "gchgg"
    graph = wall_graph(cache_dir=None)
    assert graph.cache_path is None and not (tmp_path / "xdg").exists()
    default = GoalGraph(FIELD, [WALL], N, 0.0)
    assert default.cache_path.parent == tmp_path / "xdg" / "gchgg"
    monkeypatch.setenv("GCHGG_CACHE_DIR", str(tmp_path / "own"))
    assert default_cache_dir() == tmp_path / "own"
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.warns(RuntimeWarning, match="could not write graph cache file"):
        fallback = wall_graph(cache_dir=blocker / "cache")
    assert torch.equal(all_pairs(fallback), all_pairs(graph))


# ---------------------------------------------------------------------- CLI and docs


def test_cli_draws_push_new(tmp_path, capsys):
    out = tmp_path / "push_new.png"
    main(["push_new", "--out", str(out), "--n", "11", "11", "3", "--cache-dir", str(tmp_path / "cache")])
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    printed = capsys.readouterr().out
    d_graph, d_line = (float(part.split("= ")[1].split(" m")[0]) for part in printed.split(", ")[:2])
    assert d_graph > d_line + 0.1  # the object must go around the wall


def test_docstring_examples_run():
    for module in (gchgg.graph.grid, gchgg.graph.lattice, gchgg.graph.metric, gchgg.graph.table):
        assert doctest.testmod(module, raise_on_error=False).failed == 0
