"""Env throughput: raw dm_control ``Environment.step`` vs the batched TorchRL env, per task.

Prints, per task, raw dm_control steps/s on one env with random actions, the TorchRL env's
env-steps/s (``num_envs`` simulations per call, one batched random policy call per step) and their
ratio. Then the per-episode loop's case (``train.chunks = train.episodes``): whole episodes of a
one-simulation env, by TorchRL's ``env.rollout`` and by ``KukaEnv.rollout_with`` (the same
TensorDict without a TensorDict per step), against raw dm_control. Each table's loops are timed in
alternating rounds of the same run, so the ratios hold on a shared machine.

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


class _Episodes:
    """Whole episodes of a one-simulation env under a random tensor policy, as the per-episode loop
    collects them: ``env.rollout`` (``fast=False``) or ``KukaEnv.rollout_with`` (``fast=True``)."""

    def __init__(self, name: str, fast: bool, seed: int = 0):
        self.env, self.fast = envs.make(name, num_envs=1, seed=seed), fast
        self.steps = self.env.geometry.episode_length
        generator = torch.Generator().manual_seed(seed)
        self.act = lambda observation, goal: torch.rand(1, self.env.action_dim, generator=generator) * 2 - 1
        self.run(1)  # warm-up

    def run(self, episodes: int) -> float:
        start = time.perf_counter()
        for _ in range(episodes):
            reset = self.env.reset()
            if self.fast:
                self.env.rollout_with(self.act, self.steps, reset)
            else:
                policy = lambda td: td.set("action", self.act(td["observation"], td["desired_goal"]))  # noqa: E731
                self.env.rollout(self.steps, policy, tensordict=reset, auto_reset=False, break_when_any_done=False)
        return time.perf_counter() - start


def measure_episodes(name: str, steps: int, rounds: int) -> tuple[float, float, float]:
    """Steps/s of raw dm_control, ``env.rollout`` and ``rollout_with`` on one simulation (alternating rounds)."""
    raw, torchrl_loop, fast_loop = _Raw(name), _Episodes(name, fast=False), _Episodes(name, fast=True)
    episodes = max(1, steps // (rounds * torchrl_loop.steps))
    seconds = [0.0, 0.0, 0.0]
    for _ in range(rounds):
        seconds[0] += raw.run(episodes * torchrl_loop.steps)
        seconds[1] += torchrl_loop.run(episodes)
        seconds[2] += fast_loop.run(episodes)
    total = rounds * episodes * torchrl_loop.steps
    return tuple(total / s for s in seconds)


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
    print("\none simulation, whole episodes (the per-episode loop), env-steps/s:")
    print(f"{'task':<18} {'raw':>6} {'env.rollout':>12} {'rollout_with':>13} {'rollout_with / env.rollout':>27}")
    for name in args.tasks:
        raw, torchrl_loop, fast_loop = measure_episodes(name, args.steps, args.rounds)
        print(f"{name:<18} {raw:>6.0f} {torchrl_loop:>12.0f} {fast_loop:>13.0f} {fast_loop / torchrl_loop:>27.2f}")


if __name__ == "__main__":
    from report import run  # prints, and with --docs writes docs/benchmarks.md

    run(main, __file__)
