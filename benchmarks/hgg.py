"""Benchmark: seconds per G-HGG goal generation on a full pool, and where the time goes.

Setting (the paper's push_new run): a full pool of 1,000 trajectories × 101 achieved goals (T = 100),
K = 50 targets, the graph metric on push_new at 31 × 31 × 11, and V = Q(s, g, π(s, g)) from the
reference networks (3 × 256 ReLU; actor obs‖goal → tanh 3 actions, critic obs‖goal‖action → 1),
so one generation evaluates both networks on 101,000 points. Trajectories are random walks of the
object on the table from its start position; observations are random (the networks' cost does not
depend on their values).

It prints the median seconds per generation, the share spent in the networks, the distances, the
cost of eqs. 6–7 and the matching, for torch's default thread count and for one thread (interleaved,
so both see the same load on a shared machine), and, as a ratio in the same run, the distance step
without deduplicating pool points to graph vertices.

Run: ``python benchmarks/hgg.py`` (``--repeats N``, ``--threads N [N ...]``).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from torch import nn

from envs.geometry import geometry
from gchgg.graph import DEFAULT_MARGIN, DEFAULT_N, GoalGraph
from gchgg.hgg import HGGGoalGenerator, TrajectoryPool, estimate_max_distance

POOL = 1000  # trajectories
STEPS = 100  # T: each trajectory holds T + 1 achieved goals
TARGETS = 50  # K
OBS_DIM = 25
ACTION_DIM = 3
HIDDEN = 256
STEP_STD = 0.01  # metres per step of the synthetic object random walk


def mlp(inputs: int, outputs: int) -> nn.Sequential:
    """3 × 256 ReLU layers, then a linear output."""
    return nn.Sequential(
        nn.Linear(inputs, HIDDEN), nn.ReLU(),
        nn.Linear(HIDDEN, HIDDEN), nn.ReLU(),
        nn.Linear(HIDDEN, HIDDEN), nn.ReLU(),
        nn.Linear(HIDDEN, outputs),
    )


def make_value_fn(generator: torch.Generator):
    torch.manual_seed(int(torch.randint(2**31, (1,), generator=generator)))  # the layers' default init
    actor = nn.Sequential(mlp(OBS_DIM + 3, ACTION_DIM), nn.Tanh()).eval()
    critic = mlp(OBS_DIM + 3 + ACTION_DIM, 1).eval()

    def value(observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        inputs = torch.cat([observation, goal], dim=-1)
        return critic(torch.cat([inputs, actor(inputs)], dim=-1)).squeeze(-1).clamp(-50.0, 0.0)

    flops_per_point = 2 * sum(m.weight.numel() for m in [*actor.modules(), *critic.modules()]
                              if isinstance(m, nn.Linear))
    return value, flops_per_point


def uniform(box, size: int, generator: torch.Generator) -> torch.Tensor:
    center, half = torch.tensor(box.center), torch.tensor(box.half)
    return center + half * (2 * torch.rand(size, 3, generator=generator) - 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7, help="timed generations (after one warm-up)")
    parser.add_argument("--threads", type=int, nargs="+", default=None,
                        help="torch thread counts to compare, interleaved (default: torch's choice, then 1)")
    args = parser.parse_args()
    threads = args.threads or list(dict.fromkeys([torch.get_num_threads(), 1]))
    rng = torch.Generator().manual_seed(0)
    task = geometry("push_new")
    start = time.perf_counter()
    graph = GoalGraph(task.field, task.obstacles, DEFAULT_N, DEFAULT_MARGIN)
    print(f"graph: {graph} ready in {time.perf_counter() - start:.1f} s (cached: {graph.loaded_from_cache})")

    # Object random walks on the table from its start, kept in the field (they may cross the wall:
    # points on removed vertices read inf, as real ones never do, which only exercises that path).
    low, high = torch.tensor(task.field.low), torch.tensor(task.field.high)
    episodes = POOL + POOL // 5  # a few more than the pool holds: a few random walks end near their start
    steps = torch.randn(episodes, STEPS, 3, generator=rng) * STEP_STD
    steps[..., 2] = 0.0
    origin = torch.tensor(task.object_range.center).expand(episodes, 1, 3)
    trajectories = torch.cat([origin, origin + steps.cumsum(1)], dim=1).clamp(low, high)
    pool = TrajectoryPool(capacity=POOL)
    admitted = pool.add(trajectories, torch.randn(episodes, OBS_DIM, generator=rng))
    assert len(pool) == POOL, len(pool)
    initial = torch.tensor(task.object_range.center).expand(TARGETS, 3)
    targets = uniform(task.target_range, TARGETS, rng)
    max_dis = estimate_max_distance(graph, initial[:1].expand(1000, 3), uniform(task.target_range, 1000, rng))
    value_fn, flops_per_point = make_value_fn(rng)
    generator = HGGGoalGenerator(graph, value_fn, max_dis=max_dis, pool=pool)
    print(f"pool: {len(pool)} trajectories x {STEPS + 1} points (full; {int(admitted.sum())} of {episodes} "
          f"episodes admitted), K = {TARGETS}, max_dis = {max_dis:.3f} m")

    # Interleave the thread settings so that each sees the same background load (shared machine).
    runs = {n: [] for n in threads}
    for repeat in range(args.repeats + 1):  # the first round is a warm-up
        for n in threads:
            torch.set_num_threads(n)
            timings = generator.generate(initial, targets).timings
            if repeat:
                runs[n].append(timings)
    flops = flops_per_point * pool.achieved_goals.shape[:2].numel()
    print(f"networks: {flops / 1e9:.1f} GFLOP per generation (actor + critic on every pool point)")
    for n, timed in runs.items():
        total = statistics.median(run["total"] for run in timed)
        best = min(run["total"] for run in timed)
        print(f"torch threads = {n}: seconds per goal generation: median {total:.3f} s, best {best:.3f} s "
              f"of {args.repeats}  (target <= 1.5 s)")
        for part, label in (("value", "networks (actor + critic)"), ("distance", "graph distances"),
                            ("cost", "cost, eqs. 6-7"), ("matching", "matching")):
            seconds = statistics.median(run[part] for run in timed)
            share = statistics.median(run[part] / run["total"] for run in timed)
            extra = f"  ({flops / 1e9 / seconds:.0f} GFLOP/s)" if part == "value" else ""
            print(f"  {label:<26} {seconds:.3f} s  {share:6.1%}{extra}")

    # The same generation through the bare metric interface (no lattice: every pool point read with
    # metric.distance) against the graph's vertex view (pool points deduplicated to vertices).
    class DistanceOnly:
        lattice = None

        def distance(self, a, b):
            return graph.distance(a, b)

    torch.set_num_threads(threads[0])
    plain_generator = HGGGoalGenerator(DistanceOnly(), value_fn, max_dis=max_dis, pool=pool)
    seconds = {True: [], False: []}
    for _ in range(args.repeats):
        fast_result = generator.generate(initial, targets)
        plain_result = plain_generator.generate(initial, targets)
        assert torch.equal(fast_result.goals, plain_result.goals) and torch.equal(fast_result.cost, plain_result.cost)
        seconds[True].append(fast_result.timings["distance"])
        seconds[False].append(plain_result.timings["distance"])
    fast, plain = statistics.median(seconds[True]), statistics.median(seconds[False])
    points = pool.achieved_goals.shape[:2].numel() * TARGETS
    print(f"distance step (threads = {threads[0]}): deduplicated to vertices {fast:.3f} s, plain metric.distance "
          f"{plain:.3f} s (x{plain / fast:.1f}); {points:,} distances, same goals and costs")


if __name__ == "__main__":
    from report import run  # prints, and with --docs writes docs/benchmarks.md

    run(main, __file__)
