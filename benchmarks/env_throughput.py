"""Env throughput: raw dm_control ``Environment.step`` vs the batched TorchRL env, per task.

Prints, per task, raw dm_control steps/s on one env with random actions, the TorchRL env's
env-steps/s (``num_envs`` simulations per call, one batched random policy call per step) and their
ratio. The two are timed in alternating rounds of the same run, so the ratio holds on a shared machine.

    python benchmarks/env_throughput.py [--num-envs 50] [--steps 5000] [--tasks reach push_new]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # run from a checkout

os.environ.setdefault("MUJOCO_GL", "disable")
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")

import numpy as np  # noqa: E402
import torch  # noqa: E402

import envs  # noqa: E402


class _Raw:
    """One dm_control env stepped with random actions; resets included."""

    def __init__(self, name: str, seed: int = 0):
        self.env = envs.load(name, seed=seed)
        self.rng = np.random.default_rng(seed)
        self.shape = self.env.action_spec().shape
        self.env.reset()

    def run(self, steps: int) -> float:
        actions = self.rng.uniform(-1.0, 1.0, size=(steps, *self.shape))
        start = time.perf_counter()
        for action in actions:
            if self.env.step(action).last():
                self.env.reset()
        return time.perf_counter() - start


class _Batched:
    """The batched TorchRL env with a batched random policy (one call for all envs per step)."""

    def __init__(self, name: str, num_envs: int, seed: int = 0):
        self.env = envs.make(name, num_envs=num_envs, seed=seed)
        generator = torch.Generator().manual_seed(seed)
        shape = (num_envs, self.env.action_dim)
        self.policy = lambda td: td.set("action", torch.rand(shape, generator=generator) * 2 - 1)
        self.env.rollout(2, self.policy, break_when_any_done=False)  # warm-up

    def run(self, calls: int) -> float:
        start = time.perf_counter()
        self.env.rollout(calls, self.policy, break_when_any_done=False)
        return time.perf_counter() - start


def measure(name: str, num_envs: int, steps: int, rounds: int) -> tuple[float, float]:
    """Raw steps/s and batched env-steps/s, timed in alternating rounds so that load changes hit both."""
    raw, batched = _Raw(name), _Batched(name, num_envs)
    calls = max(1, steps // (rounds * num_envs))
    raw_time = batched_time = 0.0
    for _ in range(rounds):
        raw_time += raw.run(calls * num_envs)
        batched_time += batched.run(calls)
    total = rounds * calls * num_envs
    return total / raw_time, total / batched_time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, default=50)
    parser.add_argument("--steps", type=int, default=5000, help="env-steps measured per task and side")
    parser.add_argument("--rounds", type=int, default=5, help="alternating raw/batched timing rounds")
    parser.add_argument("--tasks", nargs="+", default=list(envs.TASKS), choices=envs.TASKS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"{'task':<18} {'raw dm_control steps/s':>23} {f'TorchRL x{args.num_envs} env-steps/s':>26} {'ratio':>6}")
    for name in args.tasks:
        raw, batched = measure(name, args.num_envs, args.steps, args.rounds)
        print(f"{name:<18} {raw:>23.0f} {batched:>26.0f} {batched / raw:>6.2f}")


if __name__ == "__main__":
    from report import run  # prints, and with --docs writes docs/benchmarks.md

    run(main, __file__)
