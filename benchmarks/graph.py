"""Benchmark of the goal-space graph: build time, peak memory, table size, cached load and lookup speed.

For each task (default: push_new and pick_obstacle at 31 × 31 × 11, margin 0.02 m) it prints

* the first build's seconds, in a fresh temporary cache folder, run in a subprocess so that its
  peak resident memory (``ru_maxrss``, imports of torch and scipy included) can be read, and the
  peak of the build's own allocations (``tracemalloc``);
* the cached load's seconds (median of 3 constructions that read the file);
* the distance table's bytes;
* ``distance(a, b)`` lookups per second for 10^6 random goal pairs drawn uniformly in the field,
  and the latency of one replay-sampler-sized call (4,096 goals × 1 goal), each the best of several
  calls, with one torch thread and with the default number;
* the table's largest rounding error against scipy's float64 Dijkstra over 64 sampled source rows.

Usage: ``python benchmarks/graph.py [--tasks push_new pick_obstacle] [--n 31 31 11] [--margin 0.02]``.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc

import numpy as np
import torch
from scipy.sparse.csgraph import dijkstra

from envs.geometry import geometry
from gchgg.graph import DEFAULT_MARGIN, DEFAULT_N, GoalGraph

TARGETS = (
    "targets: build <= 60 s, peak memory <= 1.5 GB, table <= 250 MB, cached load <= 1 s, "
    ">= 1e7 lookups/s"
)


def build_in_this_process(task: str, n: list[int], margin: float, cache_dir: str) -> dict:
    """Build (and cache) one graph; report seconds and peak memory of this process."""
    geom = geometry(task)
    tracemalloc.start()  # numpy (and so scipy's outputs) report their buffers to tracemalloc
    start = time.perf_counter()
    graph = GoalGraph(geom.field, geom.obstacles, n, margin, cache_dir=cache_dir)
    seconds = time.perf_counter() - start
    traced_peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert not graph.loaded_from_cache, "the cache folder was not fresh"
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB
    return {"seconds": seconds, "peak_bytes": peak, "traced_peak_bytes": traced_peak}


def best_seconds(fn, repeats: int) -> float:
    """Fastest of ``repeats`` timed calls after a warm-up: the least disturbed by a shared machine."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def benchmark(task: str, n: list[int], margin: float) -> None:
    geom = geometry(task)
    with tempfile.TemporaryDirectory(prefix="gchgg-graph-bench-") as cache_dir:
        child = subprocess.run(
            [sys.executable, __file__, "--build-child", task, "--n", *map(str, n),
             "--margin", str(margin), "--cache-dir", cache_dir],
            capture_output=True, text=True, check=True,
        )
        build = json.loads(child.stdout.strip().splitlines()[-1])
        loads = []
        for _ in range(3):
            start = time.perf_counter()
            graph = GoalGraph(geom.field, geom.obstacles, n, margin, cache_dir=cache_dir)
            loads.append(time.perf_counter() - start)
            assert graph.loaded_from_cache
        load_seconds = statistics.median(loads)

    generator = torch.Generator().manual_seed(0)
    low = torch.tensor(graph.low, dtype=torch.float32)
    size = torch.tensor(graph.high - graph.low, dtype=torch.float32)
    a = low + size * torch.rand(10**6, 3, generator=generator)
    b = low + size * torch.rand(10**6, 3, generator=generator)
    inf_fraction = graph.distance(a, b).isinf().float().mean().item()
    small = a[:4096]
    threads = torch.get_num_threads()
    lookup_seconds, small_seconds = {}, {}
    for count in sorted({1, threads}):
        torch.set_num_threads(count)
        lookup_seconds[count] = best_seconds(lambda: graph.distance(a, b), repeats=7)
        small_seconds[count] = best_seconds(lambda: graph.distance(small, b[0]), repeats=50)
    torch.set_num_threads(threads)

    rows = np.random.default_rng(0).choice(graph.num_vertices, size=64, replace=False)
    exact = dijkstra(graph.adjacency, directed=True, indices=rows)
    i = torch.from_numpy(rows)[:, None]
    j = torch.arange(graph.num_vertices)[None, :]
    table = graph.distance_between_vertices(i, j).double().numpy()
    finite = np.isfinite(exact)
    assert (finite == np.isfinite(table)).all()
    error = np.abs(table - exact)[finite].max()

    print(f"{task} {'x'.join(map(str, n))}, margin {margin} m: "
          f"{graph.num_vertices} free vertices of {np.prod(n)}")
    print(f"  first build        {build['seconds']:8.2f} s")
    print(f"  peak memory        {build['peak_bytes'] / 1e9:8.3f} GB (whole process, imports included; "
          f"build's own allocations peak at {build['traced_peak_bytes'] / 1e9:.3f} GB)")
    print(f"  table              {graph.table_bytes / 1e6:8.1f} MB")
    print(f"  cached load        {load_seconds:8.3f} s")
    for count in lookup_seconds:
        print(f"  lookups            {1e6 / lookup_seconds[count] / 1e6:8.1f} M/s (10^6 random pairs, "
              f"{inf_fraction:.1%} inf; torch threads {count})")
    for count in small_seconds:
        print(f"  sampler-size call  {small_seconds[count] * 1e3:8.3f} ms "
              f"(4,096 goals to one goal; torch threads {count})")
    print(f"  max table error    {error * 1e3:8.4f} mm over {finite.sum():,} pairs (resolution "
          f"{graph.resolution * 1e3:.4f} mm)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["push_new", "pick_obstacle"])
    parser.add_argument("--n", type=int, nargs=3, default=list(DEFAULT_N))
    parser.add_argument("--margin", type=float, default=DEFAULT_MARGIN)
    parser.add_argument("--build-child", metavar="TASK", help=argparse.SUPPRESS)
    parser.add_argument("--cache-dir", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.build_child:
        print(json.dumps(build_in_this_process(args.build_child, args.n, args.margin, args.cache_dir)))
        return
    print(TARGETS)
    for task in args.tasks:
        benchmark(task, args.n, args.margin)


if __name__ == "__main__":
    from report import run  # prints, and with --docs writes docs/benchmarks.md

    run(main, __file__)
