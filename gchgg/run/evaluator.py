"""Evaluation during training: its schedule, the stop rule, and policies evaluated in line or in a second process.

:class:`Evaluations` is what the trainer holds: it evaluates an iteration's policy in line or hands
it to the background evaluator, puts each success rate into its iteration's metrics row, and says
whether the evaluations so far stop the run.

:class:`EvaluationSchedule` says which iterations end with an evaluation (``eval.every``, and the
last) and when the evaluations so far stop the run (``train.stop_success`` held for
``train.stop_patience`` evaluations).

:func:`resolve_background` reads ``eval.background=auto`` on this machine: in the background where
a core is free beside the run's torch threads, else in line.

:class:`BackgroundEvaluator` (``eval.background``): the trainer hands over each evaluated
iteration's actor (:meth:`gchgg.ddpg.agent.DDPGAgent.policy_state`) and goes on training; a spawned
process owns an evaluation env built exactly as the trainer builds its own, runs the deterministic
episodes and sends back the success rate and the env's random state after them. Snapshots are
evaluated in the order they were submitted, from the env state the first submission after a
(re)start carries, so the results are those in-line evaluation would give for the same snapshots
and seed.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import torch

from gchgg.run.rollout import evaluate

__all__ = ["BackgroundEvaluator", "EvaluationSchedule", "Evaluations", "env_state", "set_env_state"]


@dataclass(frozen=True)
class EvaluationSchedule:
    """Which iterations end with an evaluation, and when the evaluations so far stop the run.

    Args:
        iterations: the run's length; its last iteration always evaluates.
        every: iterations between evaluations (``eval.every``).
        stop_success: stop once the last ``stop_patience`` evaluations all had a success rate at least
            this (``train.stop_success``; ``None``: never stop early).
        stop_patience: evaluations the success rate must hold ``stop_success`` for.
    """

    iterations: int
    every: int = 1
    stop_success: float | None = None
    stop_patience: int = 5

    def evaluates(self, iteration: int) -> bool:
        """Whether ``iteration`` ends with an evaluation: every ``every``-th one, and the last."""
        return (iteration + 1) % self.every == 0 or iteration + 1 == self.iterations

    def reached_stop(self, evaluated: list[dict]) -> bool:
        """Whether the last ``stop_patience`` of the ``evaluated`` rows (oldest first) all reach ``stop_success``."""
        recent = evaluated[-self.stop_patience :]
        return (self.stop_success is not None and len(recent) == self.stop_patience
                and all(row["success_rate"] >= self.stop_success for row in recent))

    def may_stop_on_pending(self, evaluated: list[dict], pending: bool) -> bool:
        """Whether an evaluation still in flight (``pending``) could make :meth:`reached_stop` true: the
        loop then waits for it, so that a run stops where in-line evaluation would have stopped it."""
        if self.stop_success is None or not pending:
            return False
        recent = evaluated[-(self.stop_patience - 1) :] if self.stop_patience > 1 else []
        return all(row["success_rate"] >= self.stop_success for row in recent)


def env_state(env, noise: torch.Generator | None) -> dict[str, Any]:
    """The evaluation env's random state: its tasks' goal draws and its observation-noise generator."""
    return {"random": env.random_state(), "noise": None if noise is None else noise.get_state()}


def set_env_state(env, noise: torch.Generator | None, state: dict[str, Any]) -> None:
    """Restore :func:`env_state`'s output."""
    env.set_random_state(state["random"])
    if noise is not None:
        noise.set_state(state["noise"])


class BackgroundEvaluator:
    """A worker process that evaluates policy snapshots in submission order.

    Args:
        build_env: picklable callable returning ``(env, noise_generator or None)``, the evaluation env
            as the trainer builds it (called once, in the worker).
        steps: episode length.
        threads: torch threads in the worker.
        matmul: the backend of the policy's products (:func:`gchgg.ddpg.agent.load_policy`), the trainer's, so
            that a background evaluation equals the in-line one.
    """

    def __init__(
        self, build_env: Callable[[], tuple[Any, torch.Generator | None]], steps: int, threads: int,
        matmul: str = "auto",
    ) -> None:
        context = multiprocessing.get_context("spawn")  # no fork of a process holding MuJoCo and OpenMP state
        self._requests, self._results = context.Queue(), context.Queue()
        self._process = context.Process(
            target=_serve, args=(build_env, steps, threads, matmul, self._requests, self._results), daemon=True
        )
        self._process.start()
        self.in_flight = 0

    @property
    def pid(self) -> int | None:
        """The worker's process id (``benchmarks/iteration.py`` pauses it while it times the floor)."""
        return self._process.pid

    def submit(self, iteration: int, policy_state: dict, state: dict | None) -> None:
        """Queue an evaluation of ``policy_state`` (``state``: the env state to start from, or ``None`` to
        go on from the previous evaluation's)."""
        self._requests.put((iteration, policy_state, state))
        self.in_flight += 1

    def results(self, wait: bool = False) -> list[tuple[int, float, float, dict]]:
        """Finished evaluations ``(iteration, success rate, seconds, env state after)``, oldest first;
        with ``wait``, all of those in flight.

        Raises:
            RuntimeError: the worker failed (its traceback is in the message) or died.
        """
        done = []
        while self.in_flight:
            try:
                item = self._results.get(timeout=5.0) if wait else self._results.get_nowait()
            except queue.Empty:
                if not wait:
                    break
                if not self._process.is_alive():
                    raise RuntimeError(f"the background evaluator died (exit code {self._process.exitcode})") from None
                continue
            if item[0] == "error":
                raise RuntimeError(f"the background evaluator failed:\n{item[1]}")
            done.append(item)
            self.in_flight -= 1
        return done

    def close(self) -> None:
        """Stop the worker (evaluations in flight are dropped)."""
        if self._process.is_alive():
            self._requests.put(None)
            self._process.join(timeout=10)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join()


def _serve(build_env, steps: int, threads: int, matmul: str, requests, results) -> None:
    try:
        torch.set_num_threads(threads)
        from gchgg.ddpg.agent import load_policy

        env, noise = build_env()
        while (request := requests.get()) is not None:
            iteration, policy_state, state = request
            if state is not None:
                set_env_state(env, noise, state)
            actor = load_policy(policy_state, matmul)
            start = time.perf_counter()
            success = evaluate(env, actor, steps)
            results.put((iteration, success, time.perf_counter() - start, env_state(env, noise)))
    except BaseException:  # reported to the trainer, which raises it
        results.put(("error", traceback.format_exc()))


def resolve_background(setting: Any, threads: int, *, cpus: int | None = None,
                       load: float | None = None) -> tuple[bool, str]:
    """Whether to evaluate in a second process, and why: ``eval.background`` as set, or for ``"auto"``,
    background where a core is free for the evaluator beside the run's ``threads`` torch threads.

    The free cores are the CPUs this process may run on (its affinity: what ``taskset``, a cgroup
    cpuset or SLURM's ``--cpus-per-task`` grant) less the machine's load (the 1-minute load average,
    rounded: the other runs and jobs already there). A SLURM job of one CPU, or a run started beside
    another on a 2-core machine, evaluates in line; a run alone on 2 cores with one thread, in the
    background. Either way the metrics are the same (``tests/test_kill.py``).

    >>> resolve_background("auto", 1, cpus=2, load=0.2)
    (True, 'auto -> true: 2 CPUs, load 0.2, 1 torch thread: a core is free for the evaluator')
    >>> resolve_background("auto", 1, cpus=2, load=1.1)[0]  # another run holds the second core
    False
    """
    if setting is True or setting is False:
        return setting, f"{str(setting).lower()} (set)"
    if cpus is None:
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if load is None:
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0
    free = cpus - round(load)
    background = free >= threads + 1
    why = (f"{cpus} CPU{'s' * (cpus != 1)}, load {load:.1f}, {threads} torch thread{'s' * (threads != 1)}: "
           + ("a core is free for the evaluator" if background else "no core is free for an evaluator"))
    return background, f"auto -> {str(background).lower()}: {why}"


class Evaluations:
    """A run's evaluations on target goals, in line or in a :class:`BackgroundEvaluator`, and the stop rule.

    In line, :meth:`after` writes the success rate into the iteration's row at once. In the
    background (:meth:`start_background`), it hands the policy over and :meth:`collect` writes the
    rate into the row when it comes back. Until then the row is *pending*: ``metrics.csv`` and the
    trackers stop before it, and a checkpoint records the pending policies (:meth:`state_dict`),
    which a resumed run submits again.

    Args:
        schedule: which iterations evaluate, and the stop rule.
        env: the evaluation env; noise: its observation-noise generator (``None`` without noise).
        build_env: builds ``(env, noise)`` as the trainer built them (for the background process).
        steps: episode length.
    """

    def __init__(self, schedule: EvaluationSchedule, env, noise: torch.Generator | None,
                 build_env: Callable, steps: int) -> None:
        self.schedule, self.env, self.noise, self.build_env, self.steps = schedule, env, noise, build_env, steps
        self.background: BackgroundEvaluator | None = None
        self.pending: dict[int, dict] = {}  # iteration -> policy snapshot, submitted, not yet back
        self.env_before: dict | None = None  # the eval env's state before the pending evaluations

    def start_background(self, threads: int, matmul: str) -> None:
        """Evaluate in a second process from now on; policies pending in a resumed run go to it first."""
        self.background = BackgroundEvaluator(self.build_env, self.steps, threads, matmul)
        for iteration, policy in sorted(self.pending.items()):
            self._submit(iteration, policy)

    def after(self, iteration: int, agent, row: dict) -> None:
        """Evaluate ``agent``'s policy after ``iteration`` if the schedule says so: in line into ``row``, or
        submitted to the background process."""
        if not self.schedule.evaluates(iteration):
            return
        if self.background is None:
            row["success_rate"] = evaluate(self.env, partial(agent.act, explore=False), self.steps)
        else:
            self._submit(iteration, agent.policy_state())

    def _submit(self, iteration: int, policy: dict) -> None:
        """The first hand-over after a start carries the eval env's state; the worker goes on from there."""
        start = None
        if self.env_before is None:
            start = self.env_before = env_state(self.env, self.noise)
        self.pending[iteration] = policy
        self.background.submit(iteration, policy, start)

    def collect(self, history: list[dict], wait: bool = False) -> None:
        """Put finished background evaluations into their rows of ``history`` (``wait``: all in flight)."""
        if self.background is None:
            return
        for iteration, success, seconds, after in self.background.results(wait):
            row = next(r for r in history if r["iteration"] == iteration)
            row["success_rate"], row["seconds_eval_background"] = success, seconds
            del self.pending[iteration]
            self.env_before = after

    def reached_stop(self, history: list[dict], settle: bool = False) -> bool:
        """Whether the evaluations in ``history`` stop the run; with ``settle``, first wait for a pending
        evaluation that could stop it, so a run stops where in-line evaluation would have stopped it."""
        if settle and self.schedule.may_stop_on_pending(self.evaluated(history), bool(self.pending)):
            self.collect(history, wait=True)
        return self.schedule.reached_stop(self.evaluated(history))

    @staticmethod
    def evaluated(history: list[dict]) -> list[dict]:
        """The rows whose evaluation is done, oldest first."""
        return [row for row in history if "success_rate" in row]

    def first_pending(self) -> int | None:
        """The first iteration whose evaluation is in flight (its row and those after it are incomplete)."""
        return min(self.pending) if self.pending else None

    def state_dict(self) -> dict:
        return {"eval_pending": list(self.pending.items())}

    def load_state_dict(self, state: dict) -> None:
        """The pending evaluations of a checkpoint, submitted again by :meth:`start_background` (a run saved
        with some in flight resumes in the background: :meth:`require_background`)."""
        self.pending = dict(state.get("eval_pending", []))

    def require_background(self, background: bool, setting: Any) -> bool:
        """``background`` as resolved, unless evaluations are pending from a checkpoint: then the background
        evaluator must take them (``eval.background=auto`` turns it on; ``false`` is refused)."""
        if not self.pending or background:
            return background
        if setting is False:
            raise ValueError(
                f"the checkpoint has evaluations of iterations {sorted(self.pending)} in flight "
                "(eval.background=true): resume it with eval.background=true or auto"
            )
        return True

    def close(self) -> None:
        if self.background is not None:
            self.background.close()
            self.background = None
