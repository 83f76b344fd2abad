"""`python -m gchgg.train env=<task> algo=<method>`: the Hydra app that wires the parts into Algorithm 2.

One iteration, top to bottom (``Trainer.iteration_step``), as the authors' ``learner/hgg.py``:

1. target tasks T* (initial achieved goal, desired goal) from resets of the env, one per episode;
2. intermediate goals from the HGG goal generator (eqs. 6-7), or the targets themselves (HER, CHER);
   the trade-off λ starts the iteration (eq. 20 from D_G, or eq. 4 at iteration k);
3. for each of ``train.chunks`` chunks of the episodes, in turn: one batched rollout with the
   *current* policy (uniform random actions during warm-up, else eq. 22) for the chunk's goals;
   EBP energy + HER relabelling into the replay buffer; a normaliser update (from a batch drawn
   from the buffer, or from the collected transitions); once warm-up is over, the chunk's share
   of ``train.updates`` DDPG updates on batches from the buffer's sampler (EBP, Alg. 1 or CHER);
   the trade-off hears how many episodes are done;
4. the iteration's trajectories into the goal generator's pool;
5. evaluation on target goals, a ``metrics.csv`` row (with the diagnostics the README lists), an
   atomic checkpoint: the iterations' new replay rows into ``replay/`` (:mod:`gchgg.run.replay_log`),
   then ``checkpoint.pt`` with everything else.

All algorithm logic lives in the parts (``envs``, ``gchgg.graph``, ``gchgg.hgg``, ``gchgg.samplers``,
``gchgg.transforms``, ``gchgg.ddpg.agent``), which :mod:`gchgg.run.parts` builds from the config; this module
runs the loop over them (evaluations and the stop rule: :mod:`gchgg.run.evaluator`; timings and the
metrics row: :mod:`gchgg.run.metrics`; checkpoints: :mod:`gchgg.run.checkpoint`; what a run records about
itself: :mod:`gchgg.run.run_info`).
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Sequence
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "disable")
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")

import hydra  # noqa: E402
import torch  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from tensordict import TensorDict  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

import envs  # noqa: E402
from gchgg.common import files  # noqa: E402
from gchgg.run import checkpoint, config, fork, metrics  # noqa: E402
from gchgg.run.evaluator import Evaluations, EvaluationSchedule, resolve_background  # noqa: E402
from gchgg.run.lock import RunLock  # noqa: E402
from gchgg.run.parts import Parts, make_parts  # noqa: E402
from gchgg.run.replay_log import ReplayLog  # noqa: E402
from gchgg.run.rollout import collect  # noqa: E402
from gchgg.run.run_info import open_loggers, requeued, resolved_settings, startup_record  # noqa: E402
from gchgg.run.summary import summary  # noqa: E402

log = logging.getLogger(__name__)
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"  # the repository's Hydra configs
CHECKPOINT = "checkpoint.pt"
POLICY = "policy.pt"  # the actor alone, beside each checkpoint: what evaluation and export load
REPLAY = "replay"  # folder of the replay files (gchgg.run.replay_log): each iteration's stored rows, once
METRICS = "metrics.csv"
BATCHES_AHEAD = 20  # batches drawn before their updates (Trainer.updates): one chunk's at the defaults


class Trainer:
    """The state of one training run and the loop of Algorithm 2 over it.

    Args:
        cfg: the composed config: the loop's settings (``train``, ``eval``, ``checkpoint``, ``logging``).
        run_dir: folder of ``metrics.csv``, ``checkpoint.pt``, the replay files and the saved config.
        parts: what the run trains with (default: :func:`gchgg.run.parts.make_parts` of ``cfg``).
    """

    def __init__(self, cfg: DictConfig, run_dir: Path, parts: Parts | None = None) -> None:
        self.cfg, self.run_dir = cfg, run_dir
        self.parts = parts = make_parts(cfg) if parts is None else parts
        self.env, self.agent, self.buffer, self.sampler = parts.env, parts.agent, parts.buffer, parts.sampler
        self.tradeoff, self.goal_generator, self.steps = parts.tradeoff, parts.goal_generator, parts.steps
        self.geometry = envs.geometry(cfg.env.name) if parts.env.has_object else None  # object diagnostics
        self.replay_log = ReplayLog(run_dir / REPLAY, parts.buffer_rows)
        schedule = EvaluationSchedule(cfg.train.iterations, cfg.eval.every, cfg.train.stop_success,
                                      cfg.train.stop_patience)
        self.evaluations = Evaluations(schedule, parts.eval_env, parts.noise_generators.get("eval_env"),
                                       parts.build_eval_env, parts.steps)
        self.iteration, self.env_steps, self.history, self.logged = 0, 0, [], 0  # logged: rows sent to trackers

    def iteration_step(self) -> dict[str, float]:
        """Runs one iteration of Algorithm 2 and returns its metrics row."""
        cfg, p, row, timer = self.cfg.train, self.parts, {"iteration": self.iteration}, metrics.PhaseTimer()

        # 1-2. Target tasks, intermediate goals, the trade-off's start of the iteration.
        starts, targets = self._target_tasks()
        goals, distances = targets, None
        if self.goal_generator is not None:
            generation = self.goal_generator.generate(starts, targets, self.agent.value)
            if generation.stopped_now and self.cfg.algo.sampler == "curriculum":
                self.sampler.stop_curriculum()  # GC-HGG: once HGG stops, plain sampling (the original's rule)
            row["d_g"] = generation.d_g
            goals, distances = generation.goals, generation.tradeoff_distances
        if self.tradeoff is not None:
            row["lambda"] = float(self.tradeoff.begin_iteration(self.iteration, distances))
        timer.lap("goals")

        # 3. Chunks: collect with the current policy, store, update the normalisers, train.
        stats, n = metrics.IterationStats(), cfg.episodes // cfg.chunks
        warmup_at_start = self.env_steps < cfg.warmup_steps
        for chunk in range(cfg.chunks):
            rows = slice(chunk * n, (chunk + 1) * n)
            reset = {"desired_goal": goals[rows]}
            if self.env.has_object:
                reset["object_position"] = starts[rows]  # the target task's own initial state
            start = self.env.reset(TensorDict(reset, batch_size=[n]))
            with torch.inference_mode():
                if self.env_steps < cfg.warmup_steps:
                    act = lambda obs, goal: self.agent.random_action(len(obs), p.streams["explore"])  # noqa: E731
                else:
                    act = self.agent.rollout_policy(p.streams["explore"])  # = act(..., explore=True, ...)
                rollout = collect(self.env, act, self.steps, start)
            self.env_steps += rollout.numel()
            stats.add_episodes(rollout, self.geometry, p.achieved_key)
            timer.lap("rollout")

            if self.goal_generator is not None:  # collected for intermediate goals: each episode's T* (eq. 15)
                rollout.set("task_goal", targets[rows].unsqueeze(1).expand(n, self.steps, 3))
            transitions = p.relabel(rollout)
            self.replay_log.record(self.iteration, self.buffer.extend(transitions), transitions)
            if self.cfg.agent.normalizer_source == "collected":
                self.agent.update_normalizer(transitions["observation"], transitions["desired_goal"])
            else:  # the original: statistics from one batch drawn as the updates draw them
                batch = self.buffer.sample()
                self.agent.update_normalizer(batch["observation"], batch["desired_goal"])
            timer.lap("store")

            if self.env_steps >= cfg.warmup_steps or cfg.update_during_warmup:
                self.updates((chunk + 1) * cfg.updates // cfg.chunks - chunk * cfg.updates // cfg.chunks, stats)
            if self.tradeoff is not None:
                self.tradeoff.after_episodes((chunk + 1) * n)
            timer.lap("update")

        # 4. The iteration's trajectories into the goal generator's pool.
        if self.goal_generator is not None:
            self.goal_generator.pool.add(stats.achieved(), stats.initial_observations())
        row.update(stats.row())
        timer.lap("store")

        # 5. Evaluation on target goals (in line, or handed to the background evaluator).
        self.evaluations.after(self.iteration, self.agent, row)
        stopped = bool(self.goal_generator and self.goal_generator.stopped)
        row.update(timer.columns(), seconds_eval=timer.since_lap(), env_steps=self.env_steps,
                   warmup=float(warmup_at_start), stopped=float(stopped))
        self.iteration += 1
        return row

    def updates(self, count: int, stats: metrics.IterationStats) -> None:
        """``count`` DDPG updates, each on a batch from the buffer's sampler, their diagnostics into ``stats``.

        The batches are drawn in groups of up to :data:`BATCHES_AHEAD`, then the group's updates run, then
        its diagnostics are taken: the same batches, updates and diagnostics as one draw before each update
        and its diagnostics after it, since no update changes what a sampler reads (the stored rows, their
        energies, λ, which moves only between chunks) nor what the diagnostics read (the batch, the
        normalisers); only faster (``python benchmarks/iteration.py`` prints both orders)."""
        for first in range(0, count, BATCHES_AHEAD):
            batches = [self.buffer.sample() for _ in range(min(BATCHES_AHEAD, count - first))]
            losses = [self.agent.update(batch) for batch in batches]
            for loss, batch in zip(losses, batches, strict=True):
                stats.add_update(loss, batch, self.agent)

    def _target_tasks(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Initial achieved goals and target goals ``[episodes, 3]`` of this iteration's target tasks T*,
        from one reset of the env per chunk."""
        resets = [self.env.reset() for _ in range(self.cfg.train.chunks)]
        return torch.cat([td["achieved_goal"] for td in resets]), torch.cat([td["desired_goal"] for td in resets])

    def step(self, trackers=None) -> dict[str, float]:
        """One iteration as training runs it: :meth:`iteration_step`, its row into the history, finished
        background evaluations collected, the checkpoint (every ``checkpoint.every`` iterations, the last,
        and where the run stops), ``metrics.csv`` and the trackers. Returns the row."""
        row = self.iteration_step()
        tick = time.perf_counter()
        self.history.append(row)
        self.evaluations.collect(self.history)
        last = self.iteration == self.cfg.train.iterations
        if self.iteration % self.cfg.checkpoint.every == 0 or last or self.evaluations.reached_stop(self.history):
            self.evaluations.collect(self.history, wait=last)  # the last one: complete
            self.save()
        row["seconds_checkpoint"] = time.perf_counter() - tick  # in the CSV; in the next checkpoint
        self.write_metrics(trackers)
        return row

    def train(self) -> list[dict[str, float]]:
        """Runs the remaining iterations (:meth:`step`); returns the metrics history."""
        cfg = self.cfg
        trackers = open_loggers(cfg, self.run_dir, resolved_settings(self.agent))  # logging.backend; hparams once
        bar = tqdm(total=cfg.train.iterations, initial=self.iteration, desc=f"{cfg.env.name}/{cfg.algo.name}",
                   unit="it", disable=not cfg.logging.progress)
        threads = int(cfg.threads or torch.get_num_threads())
        background, why = resolve_background(cfg.eval.background, threads)
        if self.evaluations.require_background(background, cfg.eval.background) != background:
            background, why = True, f"{why}; true: the checkpoint has evaluations in flight"
        log.info(f"eval.background: {why}")
        if background:  # the agent's resolved backend, not cfg.matmul: "auto" resolves by the products' precision
            self.evaluations.start_background(threads, self.agent.matmul)
        self.saved_at = self.iteration
        try:
            while self.iteration < cfg.train.iterations and not self.evaluations.reached_stop(self.history, True):
                row = self.step(trackers)
                bar.set_postfix({"success": f"{row.get('success_rate', math.nan):.2f}",
                                 "train": f"{row['train_success_rate']:.2f}",
                                 **{key: f"{row[key]:.3g}" for key in ("lambda", "d_g") if key in row}})
                bar.update(1)
            self.evaluations.collect(self.history, wait=True)
            if self.saved_at != self.iteration:  # the stop fired on an evaluation that came back after the checkpoint
                self.save()
            self.write_metrics(trackers)
        finally:
            self.evaluations.close()
            trackers.close()
        bar.close()
        if self.evaluations.reached_stop(self.history):
            print(f"stopped early after iteration {self.iteration - 1}: success rate >= {cfg.train.stop_success} "
                  f"for {cfg.train.stop_patience} iterations (train.stop_success)")
        return self.history

    # -- checkpoints and the run's record ----------------------------------------------------------

    def state_dict(self) -> dict:
        """The loop's state (iteration, history, evaluations in flight, the replay files' manifest) and the
        parts' (:func:`gchgg.run.checkpoint.parts_state`): everything but the replay rows."""
        return {"run": self.identity(), "iteration": self.iteration, "env_steps": self.env_steps,
                "history": self.history, "replay": self.replay_log.manifest(), **self.evaluations.state_dict(),
                **checkpoint.parts_state(self.parts, self.evaluations.env_before)}

    def identity(self) -> dict:
        """What a checkpoint must agree on to be resumed by this trainer: task, algorithm, seed and the
        products' dtype as resolved (``precision=auto`` resolves by machine)."""
        return {"env": self.cfg.env.name, "algo": self.cfg.algo.name, "seed": int(self.cfg.seed),
                "precision": self.agent.precision}

    def load_state_dict(self, state: dict) -> None:
        checkpoint.check_identity(state.get("run"), self.identity(), self.run_dir)
        self.iteration, self.env_steps, self.history = state["iteration"], state["env_steps"], state["history"]
        checkpoint.load_parts_state(self.parts, state, self.replay_log)
        # evaluations in flight when the checkpoint was written: submitted again when training goes on
        self.evaluations.load_state_dict(state)
        self.logged = len(Evaluations.evaluated(self.history)) if self.evaluations.pending else len(self.history)

    def save(self) -> None:
        """The iterations' replay files, the checkpoint (megabytes: no replay rows), the superseded replay
        files removed, then the policy snapshot."""
        self.replay_log.flush()
        checkpoint.save(self.state_dict(), self.run_dir / CHECKPOINT)
        self.replay_log.prune()
        checkpoint.save_policy(self.run_dir / POLICY, self.cfg, self.iteration, self.agent)
        self.saved_at = self.iteration

    def write_metrics(self, trackers=None) -> None:
        """Rewrites ``metrics.csv`` from the history (so a resumed run never holds rows twice) and sends the
        rows complete since the last call to ``trackers``, up to the first row whose evaluation is in flight."""
        first = self.evaluations.first_pending()
        metrics.write_csv(self.history, self.run_dir / METRICS, before=first)
        self.logged = metrics.log_complete(self.history, self.logged, first, trackers)


def run(cfg: DictConfig, run_dir: Path, overrides: Sequence[str] = ()) -> list[dict[str, float]]:
    """Trains with ``cfg`` in ``run_dir``, resuming from its checkpoint when ``cfg.resume`` or when
    the job was requeued by SLURM (:func:`requeued`). With ``init_from=<run folder>`` a new run starts
    from that run's checkpoint (:mod:`gchgg.run.fork`: its metrics rows, then this run's); once it has
    its own checkpoint, ``resume=true`` continues it from there. At the end, and on Ctrl-C, it prints
    what it made (:func:`gchgg.run.summary.summary`; ``overrides``: the command line's, for the resume
    command it prints).

    The folder is locked for the run's life (:mod:`gchgg.run.lock`) before anything in it is read or
    written, and let go however the run ends: a second process on it is refused at once
    (:class:`gchgg.run.lock.RunFolderLocked`, naming the holder's pid and host); a lock left by a killed
    run is taken over, with a warning in the log. A fork takes no lock on its ``init_from`` folder."""
    run_dir.mkdir(parents=True, exist_ok=True)
    with RunLock(run_dir):
        return _run(cfg, run_dir, overrides)


def _run(cfg: DictConfig, run_dir: Path, overrides: Sequence[str]) -> list[dict[str, float]]:
    """:func:`run` in its locked folder."""
    path = run_dir / CHECKPOINT
    resume = bool(cfg.resume) or requeued()
    if path.exists() and not resume:
        raise FileExistsError(
            f"run folder {run_dir} already holds a checkpoint: pass resume=true to continue that run, "
            f"or hydra.run.dir=<folder> (or another seed) for a new one"
        )
    source = None
    if cfg.init_from is not None and not path.exists():
        config.check(cfg)
        source = fork.prepare(cfg, run_dir, CHECKPOINT)  # refuses incompatible settings before anything is built
    elif cfg.init_from is not None:
        fork.check_resume(cfg, run_dir)  # the folder holds a fork of this source, not another run
    for folder in (run_dir, run_dir / REPLAY):  # what a save killed before its rename left behind
        checkpoint.remove_temporaries(folder)
    trainer = Trainer(cfg, run_dir)
    files.write_text(run_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))  # atomic: a fork reads it
    log.info(startup_record(cfg, resolved_settings(trainer.agent)))
    if resume and path.exists():
        trainer.load_state_dict(checkpoint.load(path))
        print(f"resumed {run_dir} after iteration {trainer.iteration}")
    elif source is not None:
        fork.start(source, trainer)
        trainer.save()  # the fork's own checkpoint: resume=true continues it from here
        trainer.write_metrics()
    started, resumed_at = time.perf_counter(), trainer.iteration
    threshold = cfg.train.stop_success if cfg.train.stop_success is not None else 0.9
    try:
        history = trainer.train()
    except KeyboardInterrupt:
        print("\n" + summary(trainer.history, run_dir, time.perf_counter() - started, threshold=threshold,
                             overrides=overrides, interrupted=True,
                             saved_at=getattr(trainer, "saved_at", trainer.iteration), resumed_at=resumed_at),
              flush=True)
        raise
    print(summary(history, run_dir, time.perf_counter() - started, threshold=threshold, overrides=overrides,
                  resumed_at=resumed_at))
    return history


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def main(cfg: DictConfig) -> None:
    run(cfg, Path(HydraConfig.get().runtime.output_dir), list(HydraConfig.get().overrides.task))


if __name__ == "__main__":
    main()
