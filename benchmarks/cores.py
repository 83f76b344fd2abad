"""How much a second busy process slows this machine's work: the cost of sharing the cores.

A background evaluation (``eval.background``) and two runs side by side put a second process beside
the trainer. On a machine whose cores are its own that costs the trainer nothing; on one whose cores
share hardware (hyperthreads of one physical core, a busy host) each process slows the other. This
script times two fixed pieces of a training iteration's work, one thread each: 200 bare fp32 DDPG
updates of 256 (``benchmarks/agent_update.py``'s ``BareDDPG``) and 1,000 raw dm_control
``Environment.step`` calls on push_new (an evaluation's work), and a third that touches no memory
beyond the core's own: a pure-Python arithmetic loop. Each is timed alone and beside a second
process that steps push_new's physics without pause, in alternating rounds, and the median of the
rounds' ratios is printed. Where the loop is slowed as much as the rest, the two CPUs share a core
(hyperthreads, or a host that runs other work on them); where it is not, what they share is caches
and memory. ``benchmarks/iteration.py``'s ``background / without`` and ``side by side`` lines read
against it: where a busy neighbour costs 1.2x, so does an evaluation in the background.

    python benchmarks/cores.py [--rounds 7]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]  # run from a checkout
os.environ.setdefault("MUJOCO_GL", "disable")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from agent_update import BareDDPG  # noqa: E402

import envs  # noqa: E402


def _physics_forever(ready, stop) -> None:
    """The neighbour: push_new's physics stepped until ``stop`` is set (one thread)."""
    torch.set_num_threads(1)
    env = envs.load("push_new", seed=1)
    env.reset()
    action = np.zeros(3)
    ready.set()
    while not stop.is_set():
        for _ in range(50):
            env.step(action)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7, help="alternating rounds alone / beside the neighbour")
    args = parser.parse_args()
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    bare = BareDDPG(25, 3, 3)
    batch = (torch.randn(256, 25, generator=g), torch.randn(256, 3, generator=g),
             torch.rand(256, 3, generator=g) * 2 - 1, torch.randn(256, 25, generator=g),
             -(torch.rand(256, 1, generator=g) < 0.8).float())  # fmt: skip
    env = envs.load("push_new", seed=0)
    actions = np.random.default_rng(0).uniform(-1, 1, (100, 3))

    def updates() -> float:
        start = time.perf_counter()
        for _ in range(200):
            bare.update(*batch)
        return time.perf_counter() - start

    def physics() -> float:
        env.reset()
        start = time.perf_counter()
        for i in range(1000):
            env.step(actions[i % 100])
        return time.perf_counter() - start

    def loop() -> float:
        start = time.perf_counter()
        total = 0
        for i in range(3_000_000):
            total += i * i
        return time.perf_counter() - start

    work = {"200 bare fp32 DDPG updates": updates, "1,000 raw dm_control steps": physics,
            "a pure-Python loop of 3,000,000 multiply-adds (no memory traffic)": loop}
    for run in work.values():  # warm-up
        run()
    times = {(name, where): [] for name in work for where in ("alone", "beside")}
    context = multiprocessing.get_context("spawn")
    for r in range(args.rounds):
        for where in ("alone", "beside") if r % 2 == 0 else ("beside", "alone"):
            neighbour = None
            if where == "beside":
                ready, stop = context.Event(), context.Event()
                neighbour = context.Process(target=_physics_forever, args=(ready, stop), daemon=True)
                neighbour.start()
                ready.wait(60)
                time.sleep(0.2)
            for name, run in work.items():
                times[name, where].append(run())
            if neighbour is not None:
                stop.set()
                neighbour.join(10)
    print(f"{os.cpu_count()} CPUs; one thread each; median of {args.rounds} alternating rounds; the neighbour steps "
          "push_new's physics without pause")
    for name in work:
        alone, beside = times[name, "alone"], times[name, "beside"]
        ratio = statistics.median(b / a for a, b in zip(alone, beside, strict=True))
        print(f"{name}: {statistics.median(alone):.3f} s alone, {statistics.median(beside):.3f} s beside a busy "
              f"process: {ratio:.2f}x")


if __name__ == "__main__":
    from report import run  # prints, and with --docs writes docs/benchmarks.md

    run(main, __file__)
