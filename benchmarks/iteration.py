"""Seconds per push_new training iteration of each of ``--algos`` against the floor, and per chunk count C.

An iteration is 50 episodes of 100 steps (collected in ``train.chunks`` chunks), HER relabelling
into the buffer, a normaliser update per chunk and 1,000 DDPG updates of 256 (plus goal generation
for ghgg / gchgg); evaluation and checkpointing are timed apart (not included). Each algorithm first
runs one untimed iteration (filling the buffer; the goal pool is filled with 1,000 synthetic
trajectories beforehand), then ``--iterations`` timed ones, the algorithms in alternating rounds so that a
change of the machine's load hits all; the median is printed, and gchgg / her (cher / her) as the median of
the ratios within a round. The floor is the
same work done bare, measured in the same run: 5,000 raw dm_control ``Environment.step`` calls on one
env and 1,000 plain-torch DDPG updates (``benchmarks/agent_update.py``'s ``BareDDPG``).

After the last algorithm's iterations its buffer is filled to 5,000 episodes and one checkpoint is
timed: seconds, bytes written and peak memory, against the full-buffer checkpoint written before
December 2026. Where gchgg's rollout and update phases go follows (:func:`where_it_goes`): the rollout
against the same episodes' physics replayed bare and the actor's calls alone, the update phase against
its samples, updates and diagnostics each alone and with one draw before each update, and the
iteration beside a second process evaluating against it paused, in alternating rounds. gchgg is then
timed with C = 1, 5 and 50 chunks (C = 50 is the default, the
original's per-episode loop; C = 1 collects all episodes with one policy, then runs all updates), one
trainer per C and their iterations in alternating rounds, and the ratio C=50 / C=1 printed. Then
wall-clock seconds per gchgg iteration with evaluation in-line, in the background process and
without evaluation (``--overlap``), the background line ("everything on": each iteration beside the
previous one's evaluation, as in a run's steady state) against the fp32 floor (the same raw steps plus
bare fp32 updates with torch's default matmul) in alternating rounds, the median of their ratios, and
how a round splits into the iteration and the wait after it for the evaluation; in the same rounds the
fp32 floor's work beside one evaluation in a second process (what such an evaluation costs bare work on
this machine, whose two cores may share one core's resources) and everything on against it; last,
two gchgg runs in two processes at once against one alone, each as training runs by default
(``--side-by-side``).

The networks' products run on ``--matmul`` (default ``auto``, the trainer's default: oneDNN where
measured faster, ``gchgg.fast.linear.ONEDNN_FASTER``, or for bfloat16 products), the bare updates of the
floor too; the trainers' updates in the training default ``precision=auto`` (bfloat16 where oneDNN
computes it natively) with ``gradients=auto`` (differentiated by hand, and compiled by ``torch.compile``
where the products are bfloat16 on oneDNN and a C++ compiler is found; the header says which), the
floors' bare updates in float32 with autograd.

    python benchmarks/iteration.py [--iterations 3] [--updates 1000] [--threads 1] [--chunks 1 5 50]
                                   [--matmul auto] [--overlap 3]
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import signal
import statistics
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]  # run from a checkout
os.environ.setdefault("MUJOCO_GL", "disable")
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from agent_update import BareDDPG  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402

import envs  # noqa: E402
from gchgg.ddpg.agent import DDPGAgent  # noqa: E402
from gchgg.fast.linear import MATMUL_BACKENDS, resolve_matmul, resolve_precision, use_onednn  # noqa: E402
from gchgg.run import checkpoint  # noqa: E402
from gchgg.run.evaluator import BackgroundEvaluator  # noqa: E402
from gchgg.run.metrics import IterationStats  # noqa: E402
from gchgg.run.parts import make_env  # noqa: E402
from gchgg.run.rollout import collect  # noqa: E402
from gchgg.train import BATCHES_AHEAD, CONF_DIR, Trainer  # noqa: E402

PHASES = ("goals", "rollout", "store", "update")  # what an iteration costs; eval and checkpoint apart


def floor_seconds(episodes: int, steps: int, updates: int, batch_size: int, matmul: str) -> tuple[float, float]:
    """Seconds of ``episodes * steps`` raw dm_control steps and of ``updates`` bare DDPG updates
    (their products on ``matmul``)."""
    env = envs.load("push_new", seed=0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, 3))
    env.reset()
    start = time.perf_counter()
    for i in range(episodes * steps):
        if i % steps == 0:
            env.reset()
        env.step(actions[i % steps])
    env_seconds = time.perf_counter() - start

    bare = BareDDPG(25, 3, 3)
    for network in (bare.actor, bare.critic, bare.target_actor, bare.target_critic):
        use_onednn(network, matmul)
    g = torch.Generator().manual_seed(0)
    batch = (
        torch.randn(batch_size, 25, generator=g),
        torch.randn(batch_size, 3, generator=g),
        torch.rand(batch_size, 3, generator=g) * 2 - 1,
        torch.randn(batch_size, 25, generator=g),
        -(torch.rand(batch_size, 1, generator=g) < 0.8).float(),
    )
    bare.update(*batch)  # warm-up
    start = time.perf_counter()
    for _ in range(updates):
        bare.update(*batch)
    return env_seconds, time.perf_counter() - start


def fill_pool(trainer: Trainer) -> None:
    """Fills the goal pool with 1,000 trajectories of 101 points (random walks of the object from its
    start), so that goal generation costs what it costs once training has moved the object."""
    pool = trainer.goal_generator.pool
    g = torch.Generator().manual_seed(0)
    start = torch.tensor(trainer.geometry.object_range.center)
    steps = torch.randn(pool.capacity, trainer.steps, 3, generator=g) * torch.tensor([0.01, 0.01, 0.0])
    walks = torch.cat([start.expand(pool.capacity, 1, 3), start + steps.cumsum(1)], dim=1)
    observations = torch.randn(pool.capacity, trainer.env.obs_dim, generator=g)
    pool.add(walks.float(), observations)


def _rss_mb(field: str = "VmRSS") -> float:
    """The process's resident memory (``VmRSS``) or its peak since the last reset (``VmHWM``), MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return math.nan


def _reset_peak() -> bool:
    """Reset the peak-RSS counter (Linux: ``/proc/self/clear_refs``); False where that is not possible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _written(folder: Path, since: float) -> int:
    """Bytes of the files under ``folder`` modified after ``since`` (``time.time()``)."""
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file() and p.stat().st_mtime >= since)


def checkpoint_cost(trainer: Trainer, run_dir: Path) -> None:
    """Checkpoint seconds, bytes written and peak memory per iteration with a full buffer of 5,000
    push_new episodes, against the full-buffer checkpoint written before (one run, same buffer)."""
    template = trainer.parts.relabel(trainer_rollout(trainer))  # one chunk's transitions, as stored
    per_iteration = trainer.cfg.train.episodes // trainer.env.num_envs  # chunks of one iteration
    capacity_episodes = trainer.cfg.buffer.episodes
    iterations_to_fill = capacity_episodes // trainer.cfg.train.episodes
    for k in range(iterations_to_fill):  # the buffer as a long run leaves it, its files written
        for _ in range(per_iteration):
            trainer.replay_log.record(1000 + k, trainer.buffer.extend(template), template)
        trainer.replay_log.flush()
    trainer.replay_log.prune()
    trainer.iteration = 1000 + iterations_to_fill
    for _ in range(per_iteration):  # one more iteration's new rows
        trainer.replay_log.record(trainer.iteration, trainer.buffer.extend(template), template)
    new_rows = per_iteration * template.bytes()
    print(f"checkpoint with a full buffer ({len(trainer.buffer):,} rows of {capacity_episodes:,} episodes); "
          f"the iteration's new rows: {new_rows / 1e6:.1f} MB")
    before, tracked = _rss_mb(), _reset_peak()
    since, start = time.time() - 1e-3, time.perf_counter()
    trainer.save()
    seconds = time.perf_counter() - start
    peak = _rss_mb("VmHWM") if tracked else math.nan
    written = _written(run_dir, since)
    print(f"  incremental: {seconds:.2f} s, {written / 1e6:.1f} MB written "
          f"(target <= 1.5 x new rows + 10 MB = {(1.5 * new_rows + 10e6) / 1e6:.1f} MB), "
          f"peak memory {peak / before:.2f} x before ({before:.0f} MB; target <= 1.1)")
    legacy = run_dir / "full-buffer-checkpoint.pt"
    before, tracked = _rss_mb(), _reset_peak()
    start = time.perf_counter()
    checkpoint.save({"buffer": trainer.buffer.state_dict(), "agent": trainer.agent.state_dict()}, legacy)
    full_seconds = time.perf_counter() - start
    peak = _rss_mb("VmHWM") if tracked else math.nan
    print(f"  full-buffer checkpoint (before Dec 2026): {full_seconds:.2f} s, {legacy.stat().st_size / 1e6:.0f} MB "
          f"written, peak memory {peak / before:.2f} x before")
    legacy.unlink()
    return seconds


def trainer_rollout(trainer: Trainer):
    """One chunk of random-action episodes from the trainer's env."""
    start = trainer.env.reset()
    explore = trainer.parts.streams["explore"]
    return collect(trainer.env, lambda obs, goal: trainer.agent.random_action(len(obs), explore), trainer.steps, start)


def _config(algo: str, updates: int, threads: int, chunks: int, matmul: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(
            "config",
            overrides=[
                "env=push_new",
                f"algo={algo}",
                f"train.updates={updates}",
                f"train.chunks={chunks}",
                "train.warmup_steps=0",  # the policy acts, as after warm-up
                "eval.episodes=1",  # evaluation is not part of the timed work
                f"threads={threads}",
                f"matmul={matmul}",
            ],
        )


def _ready_trainer(algo: str, updates: int, threads: int, chunks: int, matmul: str, run_dir: str) -> Trainer:
    """A trainer after one untimed iteration (its buffer filled; the goal pool filled first)."""
    trainer = Trainer(_config(algo, updates, threads, chunks, matmul), Path(run_dir))
    if trainer.goal_generator is not None:
        fill_pool(trainer)
    trainer.iteration_step()
    return trainer


def _medians(rows: list[dict]) -> tuple[float, dict[str, float]]:
    phases = {p: statistics.median(r[f"seconds_{p}"] for r in rows) for p in PHASES}
    return statistics.median(sum(r[f"seconds_{p}"] for p in PHASES) for r in rows), phases


def algo_seconds(
    algos: list[str], iterations: int, updates: int, threads: int, floor: float, matmul: str = "auto",
) -> tuple[dict[str, tuple[float, dict[str, float]]], dict[str, list[float]]]:
    """Median seconds per timed iteration (and per phase) of each of ``algos`` on push_new at C = 50, one
    trainer each, their iterations timed in alternating rounds so that a change of the machine's load hits
    all (as :func:`chunk_seconds`); and each algorithm's seconds per round, to compare them within a round.
    Prints each algorithm's line (against ``floor`` seconds), then :func:`checkpoint_cost` on the last
    algorithm's trainer (the others freed first, so that its memory figures are those of one trainer)."""
    with tempfile.TemporaryDirectory() as run_dir:
        trainers = {algo: _ready_trainer(algo, updates, threads, 50, matmul, f"{run_dir}/{algo}") for algo in algos}
        rows = _alternating_rounds(trainers, iterations)
        medians = {algo: _medians(r) for algo, r in rows.items()}
        for algo, (total, phases) in medians.items():
            detail = ", ".join(f"{p} {s:.2f}" for p, s in phases.items())
            print(f"{algo:6s} {total:6.2f} s/iteration  {total / floor:.2f}x floor  ({detail})", flush=True)
        last = trainers.pop(algos[-1])
        trainers.clear()
        gc.collect()
        seconds = checkpoint_cost(last, Path(run_dir) / algos[-1])
        print(f"  checkpoint / iteration = {seconds / medians[algos[-1]][0]:.3f} (target <= 0.02)")
    return medians, _round_seconds(rows)


def where_it_goes(updates: int, threads: int, matmul: str = "auto", rounds: int = 4) -> None:
    """Where a gchgg iteration's rollout and update phases spend their time beyond the floor's two parts
    (:func:`rollout_split` and :func:`update_split`), and what an evaluation in a second process costs the
    iteration beside it (:func:`evaluation_beside`), on one trainer (after one untimed iteration), the
    median of ``rounds`` rounds of each part."""
    with tempfile.TemporaryDirectory() as run_dir:
        trainer = _ready_trainer("gchgg", updates, threads, 50, matmul, f"{run_dir}/gchgg")
        rollout_split(trainer, rounds)
        update_split(trainer, updates, rounds)
        evaluation_beside(trainer, threads, rounds)


def rollout_split(trainer: Trainer, rounds: int) -> None:
    """The iteration's episodes as it collects them (the policy acting between the physics steps), and the
    same episodes through ``agent.act`` instead of the trainer's
    :meth:`~gchgg.ddpg.agent.DDPGAgent.rollout_policy` and with the policy's calls timed (each way first in
    turn); then the same episodes' physics replayed bare (the same resets and actions, open loop: the same
    trajectories, checked equal) and the policy's calls alone on the recorded observations. What the
    closed loop costs beyond the last two is each slowing the other down."""
    env, agent, steps, explore = trainer.env, trainer.agent, trainer.steps, trainer.parts.streams["explore"]
    episodes = trainer.cfg.train.episodes // env.num_envs  # the per-episode loop: one env, 50 resets
    parts: dict[str, list[float]] = {key: [] for key in ("closed", "through act", "timed", "acting", "replay", "actor")}
    acting = [0.0]  # seconds in the policy's calls during a closed-loop rollout

    def timed(policy):
        def timed_policy(observation, goal):
            tick = time.perf_counter()
            action = policy(observation, goal)
            acting[0] += time.perf_counter() - tick
            return action

        return timed_policy

    def episodes_with(policy) -> tuple[float, list]:  # a closed-loop rollout with a new policy() per episode
        recorded, start = [], time.perf_counter()
        with torch.inference_mode():
            for _ in range(episodes):
                recorded.append(collect(env, policy(), steps, env.reset()))
        return time.perf_counter() - start, recorded

    ways = {"closed": lambda: agent.rollout_policy(explore),  # as the trainer acts
            "through act": lambda: partial(agent.act, explore=True, generator=explore),
            "timed": lambda: timed(agent.rollout_policy(explore))}  # the trainer's, its calls timed
    for turn in range(rounds):
        resets, draws = env.random_state(), explore.get_state()
        for way in (ways if turn % 2 else reversed(ways)):  # each first in turn
            env.set_random_state(resets)
            explore.set_state(draws)  # the same episodes each way (the same actions and draws, call for call)
            acting[0] = 0.0
            seconds, recorded = episodes_with(ways[way])
            parts[way].append(seconds)
            if way == "timed":
                parts["acting"].append(acting[0])
        act = agent.rollout_policy(explore)

        env.set_random_state(resets)
        same = True
        start = time.perf_counter()
        with torch.inference_mode():
            for episode in recorded:
                actions = iter(episode["action"].unbind(1))
                replayed = collect(env, lambda observation, goal, a=actions: next(a), steps, env.reset())
                same = same and torch.equal(replayed["next", "observation"], episode["next", "observation"])
        parts["replay"].append(time.perf_counter() - start)
        if not same:
            raise RuntimeError("replaying the recorded actions did not give the recorded trajectories")

        inputs = [pair for episode in recorded
                  for pair in zip(episode["observation"].unbind(1), episode["desired_goal"].unbind(1), strict=True)]
        start = time.perf_counter()
        with torch.inference_mode():
            for observation, goal in inputs:
                act(observation, goal)
        parts["actor"].append(time.perf_counter() - start)
    m = {key: statistics.median(values) for key, values in parts.items()}
    print(f"where gchgg's rollout goes ({episodes} episodes, one trainer, the median of {rounds} rounds): "
          f"{m['closed']:.2f} s = the same episodes' physics replayed bare {m['replay']:.2f} s + the actor's "
          f"{episodes * steps:,} calls alone {m['actor']:.2f} s + {m['closed'] - m['replay'] - m['actor']:.2f} s "
          f"of the two slowing each other (timed call by call: the actor's calls between the physics steps "
          f"{m['acting']:.2f} s, the physics beside them {m['timed'] - m['acting']:.2f} s)", flush=True)
    print(f"  the same episodes through agent.act (explore=True) instead of DDPGAgent.rollout_policy (the trainer's): "
          f"{m['through act']:.2f} s against {m['closed']:.2f} s", flush=True)


def update_split(trainer: Trainer, updates: int, rounds: int) -> None:
    """``updates`` updates as the trainer runs them (:meth:`Trainer.updates`: groups of batches drawn, then
    their updates, then their diagnostics) and with one draw before each update, each first in turn; then
    ``updates`` samples, ``updates`` DDPG updates on them and their diagnostics
    (:class:`gchgg.run.metrics.IterationStats`), each timed alone."""
    agent, buffer = trainer.agent, trainer.buffer

    def one_by_one() -> None:  # one draw before each update, its diagnostics after it
        stats = IterationStats()
        for _ in range(updates):
            batch = buffer.sample()
            stats.add_update(agent.update(batch), batch, agent)

    orders = {"grouped": lambda: trainer.updates(updates, IterationStats()), "one by one": one_by_one}
    parts: dict[str, list[float]] = {key: [] for key in (*orders, "sample", "update", "diagnostics")}
    for turn in range(rounds):
        for order in (orders if turn % 2 else reversed(orders)):
            start = time.perf_counter()
            orders[order]()
            parts[order].append(time.perf_counter() - start)
        start = time.perf_counter()
        batches = [buffer.sample() for _ in range(updates)]
        parts["sample"].append(time.perf_counter() - start)
        start = time.perf_counter()
        losses = [agent.update(batch) for batch in batches]
        parts["update"].append(time.perf_counter() - start)
        stats, start = IterationStats(), time.perf_counter()
        for loss, batch in zip(losses, batches, strict=True):
            stats.add_update(loss, batch, agent)
        parts["diagnostics"].append(time.perf_counter() - start)
    m = {key: statistics.median(values) for key, values in parts.items()}
    print(f"where gchgg's update phase goes: {updates:,} samples {m['sample']:.2f} s + {updates:,} DDPG updates "
          f"{m['update']:.2f} s + their diagnostics {m['diagnostics']:.2f} s, each alone; together "
          f"{m['grouped']:.2f} s as the trainer orders them ({BATCHES_AHEAD} batches drawn, then their updates, "
          f"then their diagnostics), {m['one by one']:.2f} s with one draw before each update", flush=True)


def evaluation_beside(trainer: Trainer, threads: int, rounds: int, episodes: int = 100) -> None:
    """What an evaluation in a second process costs the iteration beside it, with the machine's drift
    cancelled: one trainer's iterations alternately beside a worker evaluating the trainer's policy
    (``episodes`` episodes at a time, one evaluation after another, as ``eval.background`` evaluates) and
    with that worker paused (SIGSTOP), each first in turn, ``rounds`` rounds; the median of the rounds'
    ratios of the iteration's seconds (its four phases) beside the worker to without it."""
    build = partial(make_env, trainer.cfg.env.name, episodes, 0, {"threshold": trainer.cfg.env.threshold}, 0.0, 0)
    worker = BackgroundEvaluator(build, trainer.steps, threads, trainer.agent.matmul)
    policy = trainer.agent.policy_state()
    for _ in range(3 * rounds + 2):  # queued: more than the rounds' iterations beside the worker last
        worker.submit(0, policy, None)
    seconds: dict[str, list[float]] = {"beside": [], "paused": []}
    try:
        while worker.in_flight and not worker.results():  # the worker has built its env and evaluated once
            time.sleep(0.05)
        for turn in range(rounds):
            for mode in (("beside", "paused") if turn % 2 == 0 else ("paused", "beside")):
                os.kill(worker.pid, signal.SIGCONT if mode == "beside" else signal.SIGSTOP)
                row = trainer.iteration_step()
                seconds[mode].append(sum(row[f"seconds_{p}"] for p in PHASES))
        worker.results()  # those done: what is left must still be in flight, or the worker idled beside some rounds
        if not worker.in_flight:
            raise RuntimeError("the evaluating worker ran out of evaluations before the last round: queue more")
    finally:
        os.kill(worker.pid, signal.SIGCONT)
        os.kill(worker.pid, signal.SIGTERM)  # its queued evaluations are not needed
        worker.close()
    ratios = [b / p for b, p in zip(seconds["beside"], seconds["paused"], strict=True)]
    print(f"what an evaluation beside costs an iteration: {statistics.median(seconds['beside']):.2f} s beside a "
          f"second process evaluating {episodes} episodes at a time, {statistics.median(seconds['paused']):.2f} s with "
          f"it paused; beside / paused = {statistics.median(ratios):.2f} (the median of {rounds} alternating rounds' "
          f"ratios: {', '.join(f'{r:.2f}' for r in ratios)})", flush=True)


def chunk_seconds(
    chunk_counts: list[int], iterations: int, updates: int, threads: int, matmul: str = "auto",
) -> tuple[dict[int, tuple[float, dict[str, float]]], dict[int, list[float]]]:
    """Median seconds per gchgg iteration (and per phase) for each chunk count C, one trainer per C,
    their iterations timed in alternating rounds so that a change of the machine's load hits all;
    and each C's seconds per round, to compare C's within a round."""
    with tempfile.TemporaryDirectory() as run_dir:
        trainers = {c: _ready_trainer("gchgg", updates, threads, c, matmul, f"{run_dir}/{c}") for c in chunk_counts}
        rows = _alternating_rounds(trainers, iterations)
    return {c: _medians(r) for c, r in rows.items()}, _round_seconds(rows)


def _alternating_rounds(trainers: dict, iterations: int) -> dict:
    """Each trainer's metrics rows of ``iterations`` iterations, run in rounds of one iteration per trainer."""
    rows: dict = {key: [] for key in trainers}
    for _ in range(iterations):
        for key, trainer in trainers.items():
            rows[key].append(trainer.iteration_step())
    return rows


def _round_seconds(rows: dict) -> dict:
    """Each key's seconds per round (the phases' sum) from :func:`_alternating_rounds`' rows."""
    return {key: [sum(row[f"seconds_{p}"] for p in PHASES) for row in r] for key, r in rows.items()}


def evaluation_overlap(iterations: int, updates: int, threads: int, matmul: str = "auto") -> tuple[float, float]:
    """Wall-clock seconds per gchgg iteration with evaluation in-line, in the background process
    (``eval.background=true``) and without evaluation, in one run (after one untimed iteration each);
    each iteration also writes its checkpoint and metrics, as training does by default, so the
    background line is an iteration with everything on. Returns the background line's seconds and
    ``everything on / fp32 floor``.

    The background iterations are timed as a run's steady state, in rounds against the fp32 floor
    (this machine drifts between minutes): each round times the floor (raw steps plus bare fp32
    updates) with the evaluation worker paused (SIGSTOP), then the floor again beside one evaluation of
    the trainer's policy in a second worker (:func:`_floor_beside_evaluation`), then one iteration beside
    the previous iteration's evaluation, until both are done (an evaluation slower than an iteration
    counts whole). The ratios are the medians of the rounds' ratios; the last evaluation, which a run
    waits for once at its end, is not timed."""
    wall = {}
    for mode, extra in (("without evaluation", ["eval.every=1000"]), ("in-line evaluation", []),
                        ("background evaluation", ["eval.background=true"])):  # fmt: skip
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose("config", overrides=["env=push_new", "algo=gchgg", f"train.updates={updates}",
                                               "train.warmup_steps=0", f"threads={threads}", f"matmul={matmul}",
                                               "train.iterations=1000", *extra])  # fmt: skip
        with tempfile.TemporaryDirectory() as run_dir:
            trainer = Trainer(cfg, Path(run_dir))
            fill_pool(trainer)
            probe = None
            if cfg.eval.background:
                trainer.evaluations.start_background(threads, trainer.agent.matmul)
                evaluations = trainer.evaluations  # a second worker of the same kind, for the floor beside it
                probe = BackgroundEvaluator(evaluations.build_env, evaluations.steps, threads, trainer.agent.matmul)
            try:
                trainer.step()  # untimed: fills the buffer; in the background its evaluation runs beside the next
                if cfg.eval.background:
                    rounds = [_steady_round(trainer, updates, probe) for _ in range(iterations)]
                else:
                    start = time.perf_counter()
                    for _ in range(iterations):  # as training runs each iteration (checkpoint.every=1)
                        trainer.step()
                    wall[mode] = (time.perf_counter() - start) / iterations
            finally:
                trainer.evaluations.close()
                if probe is not None:
                    probe.close()
        if cfg.eval.background:
            floor, beside, wall[mode], step_s, wait_s = (statistics.median(c) for c in zip(*rounds, strict=True))
            ratios = [seconds / round_floor for round_floor, _, seconds, _, _ in rounds]
            beside_ratios = [round_beside / round_floor for round_floor, round_beside, _, _, _ in rounds]
            against_beside = [seconds / round_beside for _, round_beside, seconds, _, _ in rounds]
            print(f"gchgg {mode:22s} {wall[mode]:6.2f} s/iteration (wall clock, median of {iterations} rounds, each "
                  f"beside the previous iteration's evaluation, with its checkpoint; the fp32 floor in those "
                  f"rounds: {floor:.2f} s)", flush=True)
            print(f"  in those rounds: the iteration {step_s:.2f} s, then {wait_s:.2f} s waiting for the evaluation "
                  f"beside it (each the median of {iterations})", flush=True)
        else:
            print(f"gchgg {mode:22s} {wall[mode]:6.2f} s/iteration (wall clock, {iterations} iterations, "
                  "each with its checkpoint)", flush=True)
    base = wall["without evaluation"]
    print(f"in-line / without = {wall['in-line evaluation'] / base:.2f}; "
          f"background / without = {wall['background evaluation'] / base:.2f} (target <= 1.1)")
    print(f"everything on (background evaluation, checkpoints): {wall['background evaluation']:.2f} s/iteration "
          "(target <= 18 s on a 2-core machine)")
    ratio = statistics.median(ratios)
    listed = lambda values: ", ".join(f"{r:.2f}" for r in values)  # noqa: E731
    print(f"everything on / fp32 floor = {ratio:.2f} (target <= 1.0; the median of {iterations} rounds' ratios: "
          f"{listed(ratios)})")
    print(f"where the rest goes: the fp32 floor beside one evaluation in a second process {beside:.2f} s, "
          f"{statistics.median(beside_ratios):.2f}x the floor alone (the median of the rounds' ratios: "
          f"{listed(beside_ratios)})")
    print(f"everything on / fp32 floor beside one evaluation = {statistics.median(against_beside):.2f} "
          f"(the median of the rounds' ratios: {listed(against_beside)})")
    return wall["background evaluation"], ratio


def _steady_round(trainer: Trainer, updates: int, probe: BackgroundEvaluator) -> tuple[float, ...]:
    """One round of :func:`evaluation_overlap`'s background timing: seconds of ``(fp32 floor, fp32 floor
    beside one evaluation, round, the iteration in it, the wait after the iteration for the evaluation
    beside it)``; the round lasts until both are done."""
    worker = trainer.evaluations.background.pid
    os.kill(worker, signal.SIGSTOP)  # the previous iteration's evaluation waits while the floors run
    try:
        env_s, update_s = floor_seconds(50, 100, updates, 256, "default")
        beside = _floor_beside_evaluation(probe, trainer.agent.policy_state(), updates)
    finally:
        os.kill(worker, signal.SIGCONT)
    previous = trainer.history[-1]
    start = time.perf_counter()
    trainer.step()
    step_s = time.perf_counter() - start
    while "success_rate" not in previous:  # its evaluation, beside this iteration, is done too
        if time.perf_counter() - start > 900:
            raise RuntimeError(f"the evaluation of iteration {previous['iteration']} did not come back in 15 minutes")
        time.sleep(0.005)
        trainer.evaluations.collect(trainer.history)  # raises if the worker failed
    round_s = time.perf_counter() - start
    return env_s + update_s, beside, round_s, step_s, round_s - step_s


def _floor_beside_evaluation(probe: BackgroundEvaluator, policy: dict, updates: int) -> float:
    """Seconds of the fp32 floor's work (:func:`floor_seconds`) while ``probe`` evaluates ``policy`` beside it
    (``eval.episodes`` episodes, 100 by default), the evaluation handed over as the floor starts, as an iteration
    starts beside the previous iteration's; waits for the evaluation to end before it returns."""
    probe.submit(0, policy, None)
    env_s, update_s = floor_seconds(50, 100, updates, 256, "default")
    probe.results(wait=True)
    return env_s + update_s


def everything_on(iterations: int, updates: int, threads: int, matmul: str = "auto") -> float:
    """Wall-clock seconds per gchgg iteration as training runs by default (in-line evaluation of 100
    episodes, a checkpoint and metrics after each iteration), after one untimed iteration."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["env=push_new", "algo=gchgg", f"train.updates={updates}",
                                           "train.warmup_steps=0", f"threads={threads}", f"matmul={matmul}",
                                           "train.iterations=1000"])  # fmt: skip
    with tempfile.TemporaryDirectory() as run_dir:
        trainer = Trainer(cfg, Path(run_dir))
        fill_pool(trainer)
        trainer.step()
        start = time.perf_counter()
        for _ in range(iterations):
            trainer.step()
        return (time.perf_counter() - start) / iterations


def side_by_side(iterations: int, updates: int, threads: int, matmul: str = "auto") -> None:
    """Two gchgg runs at once, each in its own process (as two training runs share this machine), against
    one alone, everything as training runs by default (:func:`everything_on`)."""
    import subprocess

    command = [sys.executable, __file__, "--one", str(iterations), f"--updates={updates}", f"--threads={threads}",
               f"--matmul={matmul}"]

    def seconds(processes: list) -> list[float]:
        return [float(p.communicate()[0].strip().splitlines()[-1]) for p in processes]

    def start() -> subprocess.Popen:
        return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)

    alone = seconds([start()])[0]
    both = seconds([start(), start()])
    each = statistics.mean(both)
    print(f"gchgg alone: {alone:.2f} s/iteration (in-line evaluation, checkpoints; {iterations} iterations)")
    print(f"side by side: {each:.2f} s/iteration each ({both[0]:.2f}, {both[1]:.2f}), {each / alone:.2f}x one alone "
          "(target <= 1.3)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=3, help="timed iterations per algorithm")
    parser.add_argument("--updates", type=int, default=1000, help="DDPG updates per iteration")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--chunks", type=int, nargs="*", default=[1, 5, 50],
                        help="chunk counts C timed for gchgg")
    parser.add_argument("--algos", nargs="*", default=["her", "ghgg", "gchgg"], help="algorithms timed at C = 50")
    parser.add_argument("--matmul", default="auto", choices=MATMUL_BACKENDS,
                        help="the networks' products (gchgg.fast.linear)")
    parser.add_argument("--overlap", type=int, default=3, metavar="N",
                        help="iterations timed with in-line, background and no evaluation (0: skip)")
    parser.add_argument("--side-by-side", type=int, default=3, metavar="N",
                        help="iterations of two gchgg runs at once against one alone, everything on (0: skip)")
    parser.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)  # a --side-by-side child
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    if args.one is not None:  # a child of --side-by-side: one run's iterations, its seconds on the last line
        print(everything_on(args.one, args.updates, args.threads, args.matmul))
        return
    env_s, update_s = floor_seconds(50, 100, args.updates, 256, args.matmul)
    floor = env_s + update_s
    _, fp32_update_s = floor_seconds(1, 1, args.updates, 256, "default")
    fp32_floor = env_s + fp32_update_s
    precision = resolve_precision("auto", args.matmul)
    gradients = DDPGAgent(25, 3, 3, matmul=args.matmul, precision="auto").gradients  # the trainers' update, resolved
    print(f"push_new, 50 episodes x 100 steps + {args.updates} updates of 256, threads={args.threads}, "
          f"matmul={args.matmul} ({resolve_matmul(args.matmul, precision)}), precision=auto "
          f"({precision}, the training default), gradients=auto ({gradients})")
    print(f"floor: {floor:.2f} s  (raw dm_control steps {env_s:.2f} s + bare DDPG updates {update_s:.2f} s)")
    print(f"fp32 floor: {fp32_floor:.2f} s  (raw dm_control steps {env_s:.2f} s + bare fp32 DDPG updates with "
          f"torch's default matmul {fp32_update_s:.2f} s)")
    by_algo, algo_rounds = algo_seconds(args.algos, args.iterations, args.updates, args.threads, floor, args.matmul)
    seconds = {algo: total for algo, (total, _) in by_algo.items()}
    if "her" in seconds:
        print(f"her / floor = {seconds['her'] / floor:.2f} (target <= 1.3)")

    def within_rounds(a: str, b: str) -> str:  # the median of a / b within each round, and the rounds' ratios
        ratios = [x / y for x, y in zip(algo_rounds[a], algo_rounds[b], strict=True)]
        return (f"{statistics.median(ratios):.2f}, the median over {len(ratios)} alternating rounds of the ratio "
                f"within a round ({', '.join(f'{r:.2f}' for r in ratios)})")

    if {"her", "gchgg"} <= set(seconds):
        print(f"gchgg / her = {within_rounds('gchgg', 'her')} (target <= 1.25; the paper: 179 s / 52 s = 3.4)")
    if {"her", "cher"} <= set(seconds):
        print(f"cher / her = {within_rounds('cher', 'her')} (target <= 1.3)")
    if "gchgg" in seconds:
        where_it_goes(args.updates, args.threads, args.matmul)
    by_chunks, rounds = chunk_seconds(args.chunks, args.iterations, args.updates, args.threads, args.matmul)
    for chunks, (total, phases) in by_chunks.items():
        detail = ", ".join(f"{p} {s:.2f}" for p, s in phases.items())
        print(f"gchgg C={chunks:<3d} {total:6.2f} s/iteration  ({detail})", flush=True)
    if {1, 50} <= set(by_chunks):
        ratios = [c50 / c1 for c50, c1 in zip(rounds[50], rounds[1], strict=True)]
        print(f"gchgg C=50 / C=1 = {statistics.median(ratios):.2f} (target <= 1.2): the median over "
              f"{len(ratios)} alternating rounds of the ratio within a round ({', '.join(f'{r:.2f}' for r in ratios)})")
    if args.overlap:
        evaluation_overlap(args.overlap, args.updates, args.threads, args.matmul)
    if args.side_by_side:
        side_by_side(args.side_by_side, args.updates, args.threads, args.matmul)


if __name__ == "__main__":
    from report import run  # prints, and with --docs writes docs/benchmarks.md

    run(main, __file__)
