"""Evaluation during training: its schedule and the early-stop rule, and snapshots evaluated in a second process.

:class:`EvaluationSchedule` says which iterations end with an evaluation (``eval.every``, and the
last) and when the evaluations so far stop the run (``train.stop_success`` held for
``train.stop_patience`` evaluations).

:class:`BackgroundEvaluator` (``eval.background``): the trainer hands over each evaluated
iteration's actor (:meth:`gchgg.agent.DDPGAgent.policy_state`) and goes on training; a spawned
process owns an evaluation env built exactly as the trainer builds its own, runs the deterministic
episodes and sends back the success rate and the env's random state after them. Snapshots are
evaluated in the order they were submitted, from the env state the first submission after a
(re)start carries, so the results are those in-line evaluation would give for the same snapshots
and seed.
"""

from __future__ import annotations

import multiprocessing
import queue
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

__all__ = ["BackgroundEvaluator", "EvaluationSchedule", "env_state", "set_env_state"]


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
        matmul: the backend of the policy's products (:func:`gchgg.agent.load_policy`), the trainer's, so
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
        from gchgg.agent import load_policy
        from gchgg.rollout import evaluate

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
