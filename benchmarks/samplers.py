"""Replay memory and sampler speed on push_new: bytes per stored transition, seconds per sample() of 256.

Prints, in one run:

* the bytes one stored transition costs (a real push_new rollout through ``EpisodeEnergy`` and
  ``HindsightRelabel(k=4)``) and what a buffer of 10,000 episodes (T = 100) with their copies
  reserves in a ``LazyTensorStorage``;
* on a full buffer of 5,000 push_new-shaped episodes (2.5 M transitions; synthetic object paths
  around the wall, see ``synthetic_episodes``) with the push_new graph (31 × 31 × 11, margin 0.02):
  seconds per ``buffer.sample()`` of 256 for uniform, EBP, graph curriculum (K = 8, EBP candidates,
  default ``draw_ahead=8``: averaged over the samples, as in training) and CHER greedy,
  each as a ratio to uniform (medians over interleaved rounds: the machine is shared and noisy);
* reading a batch as training does (uniform ``buffer.sample()`` of 256 with ``GoalToNext``) from a
  ``LazyTensorStorage`` against :class:`gchgg.fast.storage.FieldStorage`, which the trainer's buffer uses;
* the first EBP sample after a write of one episode: the written rows' energies read against all rows';
* how often the curriculum's nearest-neighbour shortlist could not prove a goal's nearest neighbour
  (more pairs are then read), and that it always equals the all-pairs value;
* in a plain ``TensorDictReplayBuffer`` of 200,000 synthetic transitions (goals and targets uniform
  in push_new's goal field) with a Euclidean metric: ``sample()`` of 256 with K = 8 against uniform
  sampling, at one torch thread and at torch's default thread count, interleaved in one run
  (target: <= 5x uniform at both; also with ``diagnostics=True``, the choice's three diagnostics
  in every batch), and the same with goals and targets drawn from achieved goals
  recorded in a push_new run (``benchmarks/data/push_new_achieved_goals.npy``, written by
  ``benchmarks/record_goals.py``): clustered as an object mostly at rest leaves them; the curriculum
  sampler's own ``sample()`` at both thread counts (target: no slower at 2 than at 1); and a loop
  that writes 50 rows before every sample, uniform against the curriculum with ``on_write="keep"``
  (target: <= 5x) and ``"redraw"``;
* where the recorded goals' extra time goes: the nearest-neighbour search of one pool on recorded
  goals against goals uniform in the field, and the share of goals its shortlist leaves unproven.

Run: ``python benchmarks/samplers.py`` (``--episodes``, ``--rounds`` to change the sizes; ``--docs``
writes the output into ``docs/benchmarks.md``).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("MUJOCO_GL", "disable")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from report import left_out, missing_input  # noqa: E402  (benchmarks/report.py)
from tensordict import TensorDict  # noqa: E402
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer  # noqa: E402

import envs  # noqa: E402
from gchgg.fast.storage import FieldStorage  # noqa: E402
from gchgg.graph import EuclideanMetric, GoalGraph  # noqa: E402
from gchgg.samplers import (  # noqa: E402
    AdaptiveTradeoff,
    CherSampler,
    EnergySampler,
    GraphCurriculumSampler,
    nearest_neighbour_distances,
)
from gchgg.transforms import EpisodeEnergy, GoalToNext, HindsightRelabel  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

K_HER = 4
BATCH = 256


def relabel(generator: torch.Generator) -> tuple[EpisodeEnergy, HindsightRelabel]:
    return EpisodeEnergy(), HindsightRelabel(envs.reward, k=K_HER, generator=generator)


DEFAULT_THREADS = torch.get_num_threads()  # torch's own choice, before main() sets one thread


def memory(graph: GoalGraph) -> None:
    env = envs.make("push_new", num_envs=2, seed=0)
    rollout = env.rollout(env_steps(env), break_when_any_done=False)
    energy, her = relabel(torch.Generator().manual_seed(0))
    transitions = her(energy(rollout))
    per_transition = transitions.bytes() / transitions.numel()
    steps = rollout.shape[-1]
    rows = 10_000 * (K_HER + 1) * steps
    storage = LazyTensorStorage(rows)
    storage.set(torch.arange(len(transitions)), transitions)  # allocates all rows (untouched pages)
    reserved = per_transition * rows  # LazyTensorStorage allocates every row of its capacity
    print(f"memory: one stored transition = {per_transition:.0f} bytes "
          f"({', '.join(sorted(str(k) for k in transitions.keys(True, True)))})")
    # The curriculum sampler's per-row caches (with EBP candidates, as in training) are sized to the
    # storage's capacity at the first sample.
    sampler = GraphCurriculumSampler(graph, 8, energy_key="energy")
    sampler.sample(storage, BATCH)
    cache = sampler.cache_bytes
    print(f"memory: 10,000 push_new episodes x {K_HER + 1} x T={steps} = {rows:,} transitions "
          f"reserve {reserved / 1e9:.2f} GB in LazyTensorStorage + {cache / 1e9:.2f} GB curriculum cache "
          f"({cache / rows:.0f} bytes/row) = {(reserved + cache) / 1e9:.2f} GB (target <= 2 GB)")


def env_steps(env) -> int:
    return envs.geometry("push_new").episode_length


def synthetic_episodes(num: int, steps: int, generator: torch.Generator) -> TensorDict:
    """push_new-shaped episodes: half leave the object at its start, the rest push it along a random path.

    Pushed objects head for the target side (y < 0) and often end on the wall (off the graph) or
    go round its end, like the object paths of a learning agent; z stays on the table, a few fall off.
    """
    geometry = envs.geometry("push_new")
    start = torch.tensor(geometry.object_range.center)
    positions = start.expand(num, steps + 1, 3).clone()
    moves = torch.rand(num, generator=generator) < 0.5
    t0 = torch.randint(0, steps // 2, (num, 1), generator=generator)
    heading = torch.randn(num, 1, 2, generator=generator) * 0.6 + torch.tensor([0.0, -1.0])
    heading = heading / heading.norm(dim=-1, keepdim=True)
    speed = torch.rand(num, 1, 1, generator=generator) * 0.012
    wiggle = torch.randn(num, steps, 2, generator=generator).cumsum(1) * 0.002
    active = (torch.arange(steps)[None, :] >= t0) & moves[:, None]  # [N, T]
    jitter = wiggle.diff(dim=1, prepend=wiggle[:, :1])
    step = ((heading * speed).expand(num, steps, 2) + jitter) * active[..., None]
    positions[:, 1:, :2] += step.cumsum(1)
    fall = (torch.rand(num, generator=generator) < 0.03) & moves
    positions[fall, -10:, 2] -= torch.linspace(0.0, 0.5, 10)
    low, high = geometry.target_range.low, geometry.target_range.high
    target = torch.stack([low[i] + (high[i] - low[i]) * torch.rand(num, generator=generator) for i in range(3)], -1)
    obs = torch.randn(num, steps + 1, 25, generator=generator)
    last = torch.zeros(num, steps, 1, dtype=torch.bool)
    last[:, -1] = True
    return TensorDict(
        {
            "observation": obs[:, :-1],
            "achieved_goal": positions[:, :-1],
            "desired_goal": target[:, None].expand(num, steps, 3),
            "action": torch.rand(num, steps, 3, generator=generator) * 2 - 1,
            "next": {
                "observation": obs[:, 1:],
                "achieved_goal": positions[:, 1:],
                "reward": -torch.ones(num, steps, 1),
                "done": last,
                "terminated": torch.zeros(num, steps, 1, dtype=torch.bool),
                "truncated": last.clone(),
            },
        },
        [num, steps],
    )


def fill(storage: LazyTensorStorage, episodes: int, steps: int, generator: torch.Generator) -> None:
    energy, her = relabel(generator)
    writer = TensorDictReplayBuffer(storage=storage, batch_size=BATCH)
    for start in range(0, episodes, 250):
        writer.extend(her(energy(synthetic_episodes(min(250, episodes - start), steps, generator))))


def push_new_graph() -> GoalGraph:
    geometry = envs.geometry("push_new")
    return GoalGraph(geometry.field, geometry.obstacles, n=(31, 31, 11), margin=0.02)


def speed(graph: GoalGraph, episodes: int, rounds: int) -> None:
    geometry = envs.geometry("push_new")
    steps = geometry.episode_length
    generator = torch.Generator().manual_seed(0)
    storage = LazyTensorStorage(episodes * (K_HER + 1) * steps)
    fill(storage, episodes, steps, generator)
    print(f"buffer: {episodes:,} episodes, {len(storage):,} transitions, graph {graph}")

    tradeoff = AdaptiveTradeoff()
    tradeoff.update(distance=0.3)  # λ = 1000·exp(−0.3/0.09) ≈ 35.7, mid-training
    samplers = {
        "uniform": RandomSampler(),
        "EBP": EnergySampler("energy"),
        "graph curriculum K=8": GraphCurriculumSampler(graph, 8, tradeoff, energy_key="energy"),
        "CHER greedy (pool 5,000)": CherSampler(pool_size=5000),
    }
    buffers = {
        name: TensorDictReplayBuffer(storage=storage, sampler=sampler, batch_size=BATCH,
                                     generator=torch.Generator().manual_seed(1))
        for name, sampler in samplers.items()
    }
    repeats = {name: (10 if name.startswith("CHER") else 50) for name in buffers}
    times: dict[str, list[float]] = {name: [] for name in buffers}
    alone: dict[str, list[float]] = {name: [] for name in buffers}  # the sampler's sample() without the row gather
    for buffer in buffers.values():  # warm-up (EBP cache, graph vertices)
        buffer.sample()
    for _ in range(rounds):
        for name, buffer in buffers.items():
            start = time.perf_counter()
            for _ in range(repeats[name]):
                buffer.sample()
            times[name].append((time.perf_counter() - start) / repeats[name])
            start = time.perf_counter()
            for _ in range(repeats[name]):
                buffer.sampler.sample(storage, BATCH)
            alone[name].append((time.perf_counter() - start) / repeats[name])
    uniform = statistics.median(times["uniform"])
    print(f"buffer.sample() of {BATCH} (indices + row gather), median of {rounds} interleaved rounds, "
          f"{torch.get_num_threads()} thread:")
    for name, values in times.items():
        seconds = statistics.median(values)
        print(f"  {name:26s} {seconds * 1e3:9.3f} ms   {seconds / uniform:8.1f} x uniform   "
              f"(sampler alone {statistics.median(alone[name]) * 1e3:.3f} ms)")
    per_iteration = ", ".join(f"{name.split(' (')[0]} {statistics.median(times[name]) * 1000:.1f} s"
                              for name in ("graph curriculum K=8", "CHER greedy (pool 5,000)"))
    print(f"  (per 1,000-update iteration: {per_iteration})")
    cher_speed(storage, rounds)
    ebp_after_a_write(storage, rounds)
    shortlist_check(storage, graph, generator)


def storage_read(rounds: int, episodes: int = 1000, repeats: int = 50) -> None:
    """Seconds per uniform ``buffer.sample()`` of 256 as training reads batches (``GoalToNext`` applied),
    from a ``LazyTensorStorage`` against :class:`gchgg.fast.storage.FieldStorage` (the same push_new-shaped
    rows in each), interleaved rounds."""
    steps = envs.geometry("push_new").episode_length
    rows = episodes * (K_HER + 1) * steps
    buffers = {}
    for name, storage in (("LazyTensorStorage", LazyTensorStorage(rows)), ("FieldStorage", FieldStorage(rows))):
        fill(storage, episodes, steps, torch.Generator().manual_seed(0))
        buffers[name] = TensorDictReplayBuffer(storage=storage, batch_size=BATCH, transform=GoalToNext(),
                                               generator=torch.Generator().manual_seed(1))  # fmt: skip
    first, second = (buffer.sample() for buffer in buffers.values())  # the same draws: the same rows
    same = set(first.keys(True, True)) == set(second.keys(True, True)) and bool((first == second).all())
    times: dict[str, list[float]] = {name: [] for name in buffers}
    for _ in range(rounds):
        for name, buffer in buffers.items():
            start = time.perf_counter()
            for _ in range(repeats):
                buffer.sample()
            times[name].append((time.perf_counter() - start) / repeats)
    lazy, field = (statistics.median(times[name]) for name in buffers)
    print(f"reading a batch: uniform buffer.sample() of {BATCH} with GoalToNext from {rows:,} rows, median of "
          f"{rounds} interleaved rounds: LazyTensorStorage {lazy * 1e3:.3f} ms, FieldStorage {field * 1e3:.3f} ms "
          f"({field / lazy:.2f}x; the same batch: {same})")


def cher_speed(storage: LazyTensorStorage, rounds: int, pool: int = 5000, repeats: int = 10) -> None:
    """CHER's ``buffer.sample()`` against uniform on the same buffer at one thread and at torch's
    default, interleaved (target: <= 10x uniform at both), and where CHER's time goes at one thread."""
    from gchgg.samplers._storage import read_field
    from gchgg.samplers.cher import lazier_than_lazy_greedy, nearest_other

    samplers = {"uniform": RandomSampler(), "CHER": CherSampler(pool_size=pool)}
    buffers = {name: TensorDictReplayBuffer(storage=storage, sampler=sampler, batch_size=BATCH,
                                            generator=torch.Generator().manual_seed(3))
               for name, sampler in samplers.items()}  # fmt: skip
    thread_counts = sorted({1, DEFAULT_THREADS})
    times = {(name, t): [] for name in buffers for t in thread_counts}
    parts: dict[str, list[float]] = {"pool": [], "graph": [], "greedy": []}
    cher, rng, distinct = buffers["CHER"].sampler, torch.Generator().manual_seed(4), []
    for _ in range(rounds):
        for threads in thread_counts:
            torch.set_num_threads(threads)
            for name, buffer in buffers.items():
                n = repeats if name == "CHER" else 10 * repeats
                start = time.perf_counter()
                for _ in range(n):
                    buffer.sample()
                times[name, threads].append((time.perf_counter() - start) / n)
        torch.set_num_threads(1)
        clock = time.perf_counter()
        index = torch.randint(len(storage), (pool,), generator=rng)
        goals, targets = (read_field(storage, key, index, cher) for key in (cher.goal_key, cher.target_key))
        penalty = cher.metric.distance(goals, targets).to(torch.float32)
        parts["pool"].append(time.perf_counter() - clock)
        clock = time.perf_counter()
        neighbour, similarity = cher.similarity_graph(goals)
        parts["graph"].append(time.perf_counter() - clock)
        clock = time.perf_counter()
        lazier_than_lazy_greedy(neighbour, similarity, penalty, BATCH, cher.subset_size, rng)
        parts["greedy"].append(time.perf_counter() - clock)
        distinct.append(len(set(nearest_other(goals.double().numpy())[0].tolist())))
    print(f"CHER (pool {pool:,}, k = 1, subsets of 3) against uniform, buffer.sample() of {BATCH} "
          f"from the buffer above, median of {rounds} interleaved rounds:")
    for threads in thread_counts:
        uniform, seconds = (statistics.median(times[name, threads]) for name in ("uniform", "CHER"))
        label = "default" if threads == DEFAULT_THREADS else "one"
        print(f"  {threads} thread(s) ({label}): uniform {uniform * 1e3:.3f} ms, CHER {seconds * 1e3:.3f} ms "
              f"= {seconds / uniform:.2f} x uniform (target <= 10)")
    print("  where CHER's time goes (1 thread): "
          + ", ".join(f"{label} {statistics.median(parts[key]) * 1e3:.2f} ms" for key, label in
                      (("pool", "pool read + distances"), ("graph", "similarity graph"), ("greedy", "greedy choice")))
          + f" (the pool's goals have {statistics.median(distinct):.0f} distinct nearest neighbours)")
    if RECORDED_GOALS.exists():  # an object at rest: near-equal float32 goals, which a weak hash made collide
        goals = recorded_achieved_goals(pool, torch.Generator().manual_seed(5)).double()
        seconds = []
        for _ in range(rounds):
            clock = time.perf_counter()
            cher.similarity_graph(goals)
            seconds.append(time.perf_counter() - clock)
        print(f"  similarity graph of {pool:,} recorded push_new achieved goals (1 thread): "
              f"{statistics.median(seconds) * 1e3:.2f} ms")


def ebp_after_a_write(storage: LazyTensorStorage, rounds: int, repeats: int = 10) -> None:
    """The first EBP sample after one episode's rows are written (the training loop writes 50 a
    iteration): reading only the written rows' energies and updating the runs they touch, against
    reading all rows' and scanning them for runs (a write given as a slice, which the sampler cannot
    follow row by row; before Dec 2026 every write did that)."""
    rows = (K_HER + 1) * envs.geometry("push_new").episode_length
    sampler = EnergySampler("energy")
    sampler._rng = torch.Generator().manual_seed(2)
    sampler.sample(storage, BATCH)
    times: dict[str, list[float]] = {"rows": [], "all": []}
    for r in range(rounds):
        for kind, written in (("rows", torch.arange(r * rows, (r + 1) * rows)),
                              ("all", slice(r * rows, (r + 1) * rows))):
            start = time.perf_counter()
            for _ in range(repeats):
                sampler.extend(written)
                sampler.sample(storage, BATCH)
            times[kind].append((time.perf_counter() - start) / repeats)
    written_rows, all_rows = statistics.median(times["rows"]), statistics.median(times["all"])
    print(f"EBP: first sample after a write of one episode ({rows} rows) into {len(storage):,}: "
          f"{written_rows * 1e3:.2f} ms reading the written rows (runs updated), "
          f"{all_rows * 1e3:.2f} ms reading all rows ({all_rows / written_rows:.1f}x; "
          f"x50 writes per iteration: {written_rows * 50:.2f} s against {all_rows * 50:.2f} s)")


def shortlist_check(storage, graph, generator: torch.Generator, draws: int = 20) -> None:
    goals = storage.get(torch.arange(len(storage)))["desired_goal"]
    rescored = total = mismatched = 0
    for _ in range(draws):
        batch = goals[torch.randint(len(goals), (8 * BATCH,), generator=generator)].view(8, BATCH, 3)
        stats: dict = {}
        fast = nearest_neighbour_distances(batch, graph, neighbours=3, stats=stats)
        exact = nearest_neighbour_distances(batch, graph, neighbours=None)
        both_finite = torch.isfinite(fast) & torch.isfinite(exact)
        mismatched += int(((fast - exact).abs()[both_finite] > 1e-6).sum())
        mismatched += int((torch.isfinite(fast) != torch.isfinite(exact)).sum())
        rescored += stats["rescored"]
        total += batch.shape[0] * batch.shape[1]
    print(f"nearest neighbours (shortlist of 3): {rescored / total:.1%} of goals not proven by the shortlist "
          f"(more pairs read); {mismatched} of {total:,} differ from the all-pairs value")


RECORDED_GOALS = ROOT / "benchmarks" / "data" / "push_new_achieved_goals.npy"


def recorded_achieved_goals(size: int, generator: torch.Generator) -> torch.Tensor:
    """``size`` goals drawn (with replacement) from ``benchmarks/data/push_new_achieved_goals.npy``:
    20,000 achieved goals drawn uniformly from the first 12 iterations of the push_new ``algo=hgg`` run
    of seed 1 (``train.iterations=12 precision=float32 matmul=default`` at 1c92d3a, on an Intel Xeon;
    ``benchmarks/record_goals.py`` writes it from that run's replay files; it is an output, kept out of
    git), 836 of them distinct: an object mostly at rest repeats its position. The figures in
    docs/benchmarks.md dated before 2026-12-05 read an earlier recording (seed 1 at ccc4ff7, 1,058
    distinct), those dated 2026-12-05 another (d6e9109 on an AVX2 machine, 1,107 distinct), both lost
    with their machines; those dated 2026-12-06 one at e711ab2 (836 distinct, as the recording at
    1c92d3a that replaced it when the work tree was laid anew)."""
    achieved = torch.from_numpy(np.load(RECORDED_GOALS))
    return achieved[torch.randint(len(achieved), (size,), generator=generator)]


def plain_buffer_speed(rounds: int, size: int = 200_000, recorded: bool = False) -> None:
    """Euclidean curriculum vs uniform in a plain TorchRL buffer, at one and at the default threads;
    goals uniform in push_new's goal field, or (``recorded``) a recorded buffer's achieved goals.
    Also the sampler's own ``sample`` at both thread counts, and (goals uniform) a loop that writes
    an episode's 50 rows before every sample."""
    generator = torch.Generator().manual_seed(0)
    center, half = (torch.tensor(v) for v in envs.geometry("push_new").field)

    def goals(count: int) -> torch.Tensor:
        if recorded:
            return recorded_achieved_goals(count, generator)
        return center + (torch.rand(count, 3, generator=generator) * 2 - 1) * half

    def rows(count: int) -> TensorDict:
        return TensorDict({
            "observation": torch.randn(count, 25, generator=generator), "desired_goal": goals(count),
            "task_goal": goals(count), "action": torch.rand(count, 3, generator=generator) * 2 - 1,
            "next": {"observation": torch.randn(count, 25, generator=generator), "reward": -torch.ones(count, 1)},
        }, [count])  # fmt: skip

    def plain(sampler) -> TensorDictReplayBuffer:
        buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(size), sampler=sampler, batch_size=BATCH,
                                        generator=torch.Generator().manual_seed(1))
        buffer.extend(data)
        return buffer

    data = rows(size)
    buffers = {"uniform": plain(RandomSampler()),
               "curriculum": plain(GraphCurriculumSampler(EuclideanMetric(), 8, 1.0)),
               "diagnostics": plain(GraphCurriculumSampler(EuclideanMetric(), 8, 1.0, diagnostics=True))}
    thread_counts = sorted({1, DEFAULT_THREADS})
    times = {(name, t): [] for name in buffers for t in thread_counts}
    alone = {t: [] for t in thread_counts}  # the curriculum sampler's own sample(), without TorchRL's row gather
    curriculum = buffers["curriculum"]
    for _ in range(rounds):
        for threads in thread_counts:
            torch.set_num_threads(threads)
            for name, buffer in buffers.items():
                buffer.sample()  # a fresh draw-ahead pool starts in every measurement
                start = time.perf_counter()
                for _ in range(48):  # six pools of draw_ahead=8
                    buffer.sample()
                times[name, threads].append((time.perf_counter() - start) / 48)
            curriculum.sampler._pool.drop()  # its candidates drawn ahead (gchgg.fast.candidates)
            start = time.perf_counter()
            for _ in range(48):
                curriculum.sampler.sample(curriculum.storage, BATCH)
            alone[threads].append((time.perf_counter() - start) / 48)
    torch.set_num_threads(1)
    kind = "a recorded buffer's achieved goals" if recorded else "goals uniform in the field"
    print(f"plain TensorDictReplayBuffer, {size:,} synthetic transitions, {kind}, EuclideanMetric, sample() of "
          f"{BATCH}, K=8, median of {rounds} interleaved rounds:")
    for threads in thread_counts:
        uniform = statistics.median(times["uniform", threads])
        seconds = statistics.median(times["curriculum", threads])
        label = "default" if threads == DEFAULT_THREADS else "one"
        diagnosed = statistics.median(times["diagnostics", threads])
        print(f"  {threads} thread(s) ({label}): uniform {uniform * 1e3:.3f} ms, curriculum {seconds * 1e3:.3f} ms "
              f"= {seconds / uniform:.2f} x uniform (target <= 5); the sampler's own sample() "
              f"{statistics.median(alone[threads]) * 1e3:.3f} ms; with diagnostics=True {diagnosed * 1e3:.3f} ms "
              f"= {diagnosed / uniform:.2f} x")
    if len(thread_counts) > 1:  # per round, the two thread counts ran back to back: their ratio, and its spread
        ratios = sorted(more / one for one, more in zip(alone[1], alone[thread_counts[-1]], strict=True))
        low, high = np.quantile(ratios, [0.25, 0.75])
        print(f"  sampler's own sample() at {thread_counts[-1]} threads / at 1 thread = "
              f"{statistics.median(ratios):.2f}, the rounds' interquartile range {low:.2f}-{high:.2f} "
              "(target <= 1: it runs on one thread whatever the caller's count, so the rounds scatter around 1)")
    if recorded:
        return
    # A loop that writes before every sample (TorchRL collectors extend, then the loss samples).
    written = rows(400 * 50)
    loops = {
        "uniform": plain(RandomSampler()),
        'curriculum, on_write="keep"': plain(GraphCurriculumSampler(EuclideanMetric(), 8, 1.0)),
        'curriculum, on_write="redraw"': plain(GraphCurriculumSampler(EuclideanMetric(), 8, 1.0, on_write="redraw")),
    }
    loop_times: dict = {(name, t): [] for name in loops for t in thread_counts}
    step = 0
    for _ in range(rounds):
        for threads in thread_counts:
            torch.set_num_threads(threads)
            for name, buffer in loops.items():
                start = time.perf_counter()
                for _ in range(32):
                    buffer.extend(written[(step % 400) * 50 : (step % 400 + 1) * 50])
                    buffer.sample()
                    step += 1
                loop_times[name, threads].append((time.perf_counter() - start) / 32)
    torch.set_num_threads(1)
    print(f"write-then-sample: extend(50 rows) then sample() of {BATCH}, same buffer, median of {rounds} "
          "interleaved rounds of 32 (target: keep <= 5 x uniform):")
    for threads in thread_counts:
        uniform = statistics.median(loop_times["uniform", threads])
        line = ", ".join(f"{name} {statistics.median(loop_times[name, threads]) * 1e3:.3f} ms = "
                         f"{statistics.median(loop_times[name, threads]) / uniform:.1f} x" for name in loops if
                         name != "uniform")
        print(f"  {threads} thread(s): uniform {uniform * 1e3:.3f} ms; {line}")


def recorded_search_cost(rounds: int, pool: int = 64) -> None:
    """Where the recorded goals' extra time goes: the Euclidean nearest-neighbour search over one pool of
    candidates (``draw_ahead`` 8 x K 8 = 64 batches of 256) on recorded goals against goals uniform in the
    field, the share of goals its shortlist leaves unproven, and how many recorded goals have a
    neighbour nearer than the search's tolerance (no straight-line bound can prove those)."""
    from scipy.spatial import cKDTree

    from gchgg.fast.nearest import _RELATIVE_TOLERANCE, NearestNeighbours

    generator = torch.Generator().manual_seed(6)
    center, half = (torch.tensor(v) for v in envs.geometry("push_new").field)
    batches = {
        "recorded": recorded_achieved_goals(pool * BATCH, generator).view(pool, BATCH, 3),
        "uniform": (center + (torch.rand(pool * BATCH, 3, generator=generator) * 2 - 1) * half).view(pool, BATCH, 3),
    }
    seconds: dict[str, list[float]] = {name: [] for name in batches}
    unproven: dict[str, int] = {}
    for _ in range(rounds):
        for name, goals in batches.items():
            search, stats = NearestNeighbours(EuclideanMetric()), {}
            search(goals)  # its scratch memory and layouts, as in a sampler that has run
            clock = time.perf_counter()
            search(goals, stats=stats)
            seconds[name].append(time.perf_counter() - clock)
            unproven[name] = stats["rescored"]
    recorded, uniform = (statistics.median(seconds[name]) for name in ("recorded", "uniform"))
    distinct = np.unique(np.load(RECORDED_GOALS), axis=0).astype(np.float64)
    nearest = cKDTree(distinct).query(distinct, k=2)[0][:, 1]
    tolerance = _RELATIVE_TOLERANCE  # metres, for coordinates below 1 m
    print(f"where the recorded goals' time goes (1 thread): the nearest-neighbour search of one pool "
          f"({pool} x {BATCH} goals) takes {recorded * 1e3:.2f} ms on recorded goals, {uniform * 1e3:.2f} ms on "
          f"goals uniform in the field ({recorded / uniform:.1f}x);")
    print(f"  its shortlist leaves {unproven['recorded'] / (pool * BATCH):.1%} of the recorded goals unproven "
          f"(uniform: {unproven['uniform'] / (pool * BATCH):.1%}), whose nearest neighbours are then read among the "
          f"goals within their best distance along the sort axis: {np.mean(nearest < tolerance):.0%} of the "
          f"{len(distinct):,} distinct "
          f"recorded goals have another within the search's {tolerance:g} m tolerance (an object at rest "
          "jitters), which no straight-line bound can prove")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=5000)
    parser.add_argument("--rounds", type=int, default=21,
                        help="interleaved rounds per figure, their median printed (default 21: on a shared machine "
                             "the medians of 7 moved between runs by more than the targets allow)")
    parser.add_argument("--plain-only", action="store_true", help="only the plain-buffer (Euclidean) figures")
    parser.add_argument("--cher-only", action="store_true", help="only CHER against uniform on the push_new buffer")
    parser.add_argument("--storage-only", action="store_true", help="only reading a batch, by storage")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for flag in ("plain_only", "cher_only", "storage_only"):
        if getattr(args, flag):
            left_out("the figures outside its part", f"--{flag.replace('_', '-')}")
    if args.storage_only:
        storage_read(args.rounds)
        return
    if args.cher_only:
        storage = LazyTensorStorage(args.episodes * (K_HER + 1) * envs.geometry("push_new").episode_length)
        fill(storage, args.episodes, envs.geometry("push_new").episode_length, torch.Generator().manual_seed(0))
        print(f"buffer: {args.episodes:,} push_new-shaped episodes, {len(storage):,} transitions")
        cher_speed(storage, args.rounds)
        return
    if not args.plain_only:
        graph = push_new_graph()
        memory(graph)
        speed(graph, args.episodes, args.rounds)
        storage_read(args.rounds)
    plain_buffer_speed(args.rounds)
    if RECORDED_GOALS.exists():
        plain_buffer_speed(args.rounds, recorded=True)
        recorded_search_cost(args.rounds)
    else:  # an output: benchmarks/record_goals.py writes it from a run's replay files
        missing_input("plain buffer with a recorded buffer's achieved goals", RECORDED_GOALS,
                      "benchmarks/record_goals.py writes it")


if __name__ == "__main__":
    from report import run  # prints, and with --docs writes docs/benchmarks.md

    run(main, __file__)
