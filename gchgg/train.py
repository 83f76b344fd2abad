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
   atomic checkpoint: the iterations' new replay rows into ``replay/`` (:mod:`gchgg.replay_log`),
   then ``checkpoint.pt`` with everything else.

All algorithm logic lives in the parts (``envs``, ``gchgg.graph``, ``gchgg.hgg``, ``gchgg.samplers``,
``gchgg.transforms``, ``gchgg.agent``), which :mod:`gchgg.parts` builds from the config; this module
runs the loop over them (the evaluation schedule and stop rule: :mod:`gchgg.evaluator`; the metrics
row: :mod:`gchgg.metrics`; what a run records about itself: :mod:`gchgg.run_info`).
"""

from __future__ import annotations

import logging
import math
import os
import time
from functools import partial
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
from gchgg import checkpoint, fork, loggers, metrics  # noqa: E402
from gchgg.evaluator import BackgroundEvaluator, EvaluationSchedule, env_state  # noqa: E402
from gchgg.parts import Parts, check_config, make_parts  # noqa: E402
from gchgg.replay_log import ReplayLog  # noqa: E402
from gchgg.rollout import collect, evaluate  # noqa: E402
from gchgg.run_info import open_loggers, requeued, startup_record  # noqa: E402

log = logging.getLogger(__name__)
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"  # the repository's Hydra configs
CHECKPOINT = "checkpoint.pt"
POLICY = "policy.pt"  # the actor alone, beside each checkpoint: what evaluation and export load
REPLAY = "replay"  # folder of the replay files (gchgg.replay_log): each iteration's stored rows, once
METRICS = "metrics.csv"


class Trainer:
    """The state of one training run and the loop of Algorithm 2 over it.

    Args:
        cfg: the composed config: the loop's settings (``train``, ``eval``, ``checkpoint``, ``logging``).
        run_dir: folder of ``metrics.csv``, ``checkpoint.pt``, the replay files and the saved config.
        parts: what the run trains with (default: :func:`gchgg.parts.make_parts` of ``cfg``).
    """

    def __init__(self, cfg: DictConfig, run_dir: Path, parts: Parts | None = None) -> None:
        self.cfg, self.run_dir = cfg, run_dir
        parts = make_parts(cfg) if parts is None else parts
        self.parts = parts
        self.env, self.eval_env, self.build_eval_env = parts.env, parts.eval_env, parts.build_eval_env
        self.metric, self.tradeoff, self.sampler = parts.metric, parts.tradeoff, parts.sampler
        self.buffer, self.relabel, self.agent = parts.buffer, parts.relabel, parts.agent
        self.goal_generator = parts.goal_generator
        self.explore_rng, self.noise_generators, self.achieved_key = (
            parts.streams["explore"], parts.noise_generators, parts.achieved_key)
        self.geometry, self.steps = envs.geometry(cfg.env.name), parts.steps
        self.chunk_size = cfg.train.episodes // cfg.train.chunks
        self.replay_log = ReplayLog(run_dir / REPLAY, parts.buffer_rows)
        self.schedule = EvaluationSchedule(cfg.train.iterations, cfg.eval.get("every", 1), cfg.train.stop_success,
                                           cfg.train.stop_patience)
        self.evaluator: BackgroundEvaluator | None = None  # started by train() with eval.background
        self.eval_pending: dict[int, dict] = {}  # iteration -> policy snapshot, submitted, not yet back
        self.eval_state: dict | None = None  # the eval env's state before the pending evaluations
        self._logged = 0  # history rows already sent to the trackers (logging.backend)
        self.iteration, self.env_steps, self.history = 0, 0, []

    # -- one iteration ----------------------------------------------------------------------------

    def iteration_step(self) -> dict[str, float]:
        """Runs one iteration of Algorithm 2 and returns its metrics row."""
        cfg, row, clock = self.cfg, {"iteration": self.iteration}, time.perf_counter()
        timing = {"goals": 0.0, "rollout": 0.0, "store": 0.0, "update": 0.0}

        def lap(phase: str) -> None:
            nonlocal clock
            now = time.perf_counter()
            timing[phase] += now - clock
            clock = now

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
        lap("goals")

        # 3. Chunks: collect with the current policy, store, update the normalisers, train.
        stats = metrics.IterationStats()
        warmup_at_start = self.env_steps < cfg.train.warmup_steps
        chunks, n = cfg.train.chunks, self.chunk_size
        for chunk in range(chunks):
            rows = slice(chunk * n, (chunk + 1) * n)
            reset = {"desired_goal": goals[rows]}
            if self.env.has_object:
                reset["object_position"] = starts[rows]  # the target task's own initial state
            start = self.env.reset(TensorDict(reset, batch_size=[n]))
            with torch.inference_mode():
                if self.env_steps < cfg.train.warmup_steps:
                    act = lambda obs, goal: self.agent.random_action(len(obs), self.explore_rng)  # noqa: E731
                else:
                    act = partial(self.agent.act, explore=True, generator=self.explore_rng)
                rollout = collect(self.env, act, self.steps, start)
            self.env_steps += rollout.numel()
            stats.add_episodes(rollout, self.geometry if self.env.has_object else None, self.achieved_key)
            lap("rollout")

            if self.goal_generator is not None:  # collected for intermediate goals: each episode's T* (eq. 15)
                rollout.set("task_goal", targets[rows].unsqueeze(1).expand(n, self.steps, 3))
            transitions = self.relabel(rollout)
            self.replay_log.record(self.iteration, self.buffer.extend(transitions), transitions)
            if cfg.agent.normalizer_source == "collected":
                self.agent.update_normalizer(transitions["observation"], transitions["desired_goal"])
            else:  # the original: statistics from one batch drawn as the updates draw them
                batch = self.buffer.sample()
                self.agent.update_normalizer(batch["observation"], batch["desired_goal"])
            lap("store")

            if self.env_steps >= cfg.train.warmup_steps or cfg.train.update_during_warmup:
                share = (chunk + 1) * cfg.train.updates // chunks - chunk * cfg.train.updates // chunks
                for _ in range(share):
                    batch = self.buffer.sample()
                    stats.add_update(self.agent.update(batch), batch, self.agent)
            if self.tradeoff is not None:
                self.tradeoff.after_episodes((chunk + 1) * n)
            lap("update")

        # 4. The iteration's trajectories into the goal generator's pool.
        if self.goal_generator is not None:
            self.goal_generator.pool.add(stats.achieved(), stats.initial_observations())
        row.update(stats.row())
        lap("store")

        # 5. Evaluation on target goals (in-line, or handed to the background evaluator).
        if self.schedule.evaluates(self.iteration):
            if self.evaluator is None:
                row["success_rate"] = evaluate(self.eval_env, partial(self.agent.act, explore=False), self.steps)
            else:
                self.submit_evaluation(self.iteration)
        row.update({f"seconds_{phase}": seconds for phase, seconds in timing.items()})
        row["seconds_eval"] = time.perf_counter() - clock
        row.update(
            env_steps=self.env_steps,
            warmup=float(warmup_at_start),
            stopped=float(bool(self.goal_generator and self.goal_generator.stopped)),
        )
        self.iteration += 1
        return row

    def _target_tasks(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Initial achieved goals and target goals ``[episodes, 3]`` of this iteration's target tasks T*,
        from one reset of the env per chunk."""
        starts, targets = [], []
        for _ in range(self.cfg.train.chunks):
            td = self.env.reset()
            starts.append(td["achieved_goal"])
            targets.append(td["desired_goal"])
        return torch.cat(starts), torch.cat(targets)

    # -- checkpoints ------------------------------------------------------------------------------

    def state_dict(self) -> dict:
        """The loop's state (iteration, history, evaluations in flight, the replay files' manifest) and the
        parts' (:func:`gchgg.checkpoint.parts_state`): everything but the replay rows."""
        return {
            "run": self.identity(),
            "iteration": self.iteration,
            "env_steps": self.env_steps,
            "history": self.history,
            "replay": self.replay_log.manifest(),
            "eval_pending": list(self.eval_pending.items()),
            **checkpoint.parts_state(self.parts, self.eval_state),
        }

    def identity(self) -> dict:
        """What a checkpoint must agree on to be resumed by this trainer: task, algorithm, seed and the
        products' dtype as resolved (``precision=auto`` resolves by machine; checkpoints from before it
        was recorded were float32)."""
        return {"env": self.cfg.env.name, "algo": self.cfg.algo.name, "seed": int(self.cfg.seed),
                "precision": self.agent.precision}

    def load_state_dict(self, state: dict) -> None:
        saved = state.get("run")
        if saved is not None:
            saved = {"precision": "float32", **saved}
        if saved is not None and saved != self.identity():
            differences = ", ".join(
                f"{key}: checkpoint {saved.get(key)!r}, this run {value!r}"
                for key, value in self.identity().items() if saved.get(key) != value
            )
            raise ValueError(f"the checkpoint in {self.run_dir} belongs to another run ({differences}); "
                             "resume it with its own settings, or start this one in another folder")
        self.iteration, self.env_steps, self.history = state["iteration"], state["env_steps"], state["history"]
        checkpoint.load_parts_state(self.parts, state, self.replay_log)
        # evaluations in flight when the checkpoint was written: submitted again when training goes on
        self.eval_pending = dict(state.get("eval_pending", []))
        self._logged = len(self.evaluated()) if self.eval_pending else len(self.history)  # logged by the first run
        if self.eval_pending and not self.cfg.eval.get("background", False):
            raise ValueError(
                f"the checkpoint in {self.run_dir} has evaluations of iterations {sorted(self.eval_pending)} in flight "
                "(eval.background=true): resume it with eval.background=true"
            )

    def save(self) -> None:
        """The iterations' replay files, the checkpoint (megabytes: no replay rows), the superseded replay
        files removed, then the policy snapshot (task, config and actor)."""
        self.replay_log.flush()
        checkpoint.save(self.state_dict(), self.run_dir / CHECKPOINT)
        self.replay_log.prune()
        policy = {
            "iteration": self.iteration,
            "task": self.cfg.env.name,
            "threshold": float(self.cfg.env.threshold),
            "config": OmegaConf.to_container(self.cfg, resolve=True),
            "policy": self.agent.policy_state(),
        }
        checkpoint.save(policy, self.run_dir / POLICY)

    def write_metrics(self) -> None:
        """Rewrites ``metrics.csv`` from the history (so a resumed run never holds rows twice), up to the
        first row whose background evaluation is still in flight."""
        first = min(self.eval_pending) if self.eval_pending else None
        metrics.write_csv(self.history, self.run_dir / METRICS, before=first)

    # -- the loop ---------------------------------------------------------------------------------

    def submit_evaluation(self, iteration: int, policy: dict | None = None) -> None:
        """Hand this iteration's policy (or ``policy``) to the background evaluator; the first hand-over
        after a start carries the eval env's state, and the worker goes on from there."""
        start = None
        if self.eval_state is None:
            start = self.eval_state = env_state(self.eval_env, self.noise_generators.get("eval_env"))
        self.eval_pending[iteration] = self.agent.policy_state() if policy is None else policy
        self.evaluator.submit(iteration, self.eval_pending[iteration], start)

    def log_rows(self, trackers: loggers.RunLoggers | None) -> None:
        """The rows complete since the last call (a row waits for its evaluation) to the trackers, each
        row whole at step = its iteration."""
        while self._logged < len(self.history):
            row = self.history[self._logged]
            if row["iteration"] in self.eval_pending:
                break
            if trackers is not None:
                trackers.log_row(row, step=row["iteration"])
            self._logged += 1

    def collect_evaluations(self, wait: bool = False) -> None:
        """Put finished background evaluations into their rows (``wait``: all of those in flight)."""
        if self.evaluator is None:
            return
        for iteration, success, seconds, after in self.evaluator.results(wait):
            row = next(r for r in self.history if r["iteration"] == iteration)
            row["success_rate"], row["seconds_eval_background"] = success, seconds
            del self.eval_pending[iteration]
            self.eval_state = after

    def evaluated(self) -> list[dict]:
        """The rows whose evaluation is done, oldest first."""
        return [row for row in self.history if "success_rate" in row]

    def reached_stop(self) -> bool:
        """Whether the evaluations so far stop the run (``train.stop_success``, see :class:`EvaluationSchedule`)."""
        return self.schedule.reached_stop(self.evaluated())

    def train(self) -> list[dict[str, float]]:
        """Runs the remaining iterations, checkpointing after each; returns the metrics history."""
        cfg = self.cfg
        trackers = open_loggers(cfg, self.run_dir)  # logging.backend; hyperparameters logged once
        bar = tqdm(
            total=cfg.train.iterations,
            initial=self.iteration,
            desc=f"{cfg.env.name}/{cfg.algo.name}",
            unit="it",
            disable=not cfg.logging.progress,
        )
        if cfg.eval.get("background", False):
            self.evaluator = BackgroundEvaluator(
                self.build_eval_env, self.steps, int(cfg.threads or torch.get_num_threads()), cfg.matmul
            )
            for iteration, policy in sorted(self.eval_pending.items()):  # in flight when a resumed run was saved
                self.submit_evaluation(iteration, policy=policy)
        saved_at = self.iteration
        try:
            while self.iteration < cfg.train.iterations:
                if self.schedule.may_stop_on_pending(self.evaluated(), bool(self.eval_pending)):
                    self.collect_evaluations(wait=True)
                if self.reached_stop():
                    break
                row = self.iteration_step()
                tick = time.perf_counter()
                self.history.append(row)
                self.collect_evaluations()
                if (self.iteration % cfg.checkpoint.every == 0 or self.iteration == cfg.train.iterations
                        or self.reached_stop()):
                    self.collect_evaluations(wait=self.iteration == cfg.train.iterations)  # the last one: complete
                    self.save()
                    saved_at = self.iteration
                row["seconds_checkpoint"] = time.perf_counter() - tick  # in the CSV; in the next checkpoint
                self.write_metrics()
                self.log_rows(trackers)
                postfix = {"success": f"{row.get('success_rate', math.nan):.2f}",
                           "train": f"{row['train_success_rate']:.2f}"}
                postfix.update({key: f"{row[key]:.3g}" for key in ("lambda", "d_g") if key in row})
                bar.set_postfix(postfix)
                bar.update(1)
            self.collect_evaluations(wait=True)
            if saved_at != self.iteration:  # the stop fired on an evaluation that came back after the checkpoint
                self.save()
            self.write_metrics()
            self.log_rows(trackers)
        finally:
            if self.evaluator is not None:
                self.evaluator.close()
                self.evaluator = None
            trackers.close()
        bar.close()
        if self.reached_stop():
            print(
                f"stopped early after iteration {self.iteration - 1}: success rate >= {cfg.train.stop_success} "
                f"for {cfg.train.stop_patience} iterations (train.stop_success)"
            )
        return self.history


def run(cfg: DictConfig, run_dir: Path) -> list[dict[str, float]]:
    """Trains with ``cfg`` in ``run_dir``, resuming from its checkpoint when ``cfg.resume`` or when
    the job was requeued by SLURM (:func:`requeued`). With ``init_from=<run folder>`` a new run starts
    from that run's checkpoint (:mod:`gchgg.fork`: its metrics rows, then this run's); once it has
    its own checkpoint, ``resume=true`` continues it from there."""
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / CHECKPOINT
    resume = bool(cfg.resume) or requeued()
    if path.exists() and not resume:
        raise FileExistsError(
            f"run folder {run_dir} already holds a checkpoint: pass resume=true to continue that run, "
            f"or hydra.run.dir=<folder> (or another seed) for a new one"
        )
    source = None
    if cfg.get("init_from") is not None and not path.exists():
        check_config(cfg)
        source = fork.prepare(cfg, run_dir, CHECKPOINT)  # refuses incompatible settings before anything is built
    elif cfg.get("init_from") is not None:
        fork.check_resume(cfg, run_dir)  # the folder holds a fork of this source, not another run
    for folder in (run_dir, run_dir / REPLAY):  # what a save killed before its rename left behind
        checkpoint.remove_temporaries(folder)
    trainer = Trainer(cfg, run_dir)
    OmegaConf.save(cfg, run_dir / "config.yaml", resolve=True)
    log.info(startup_record(cfg))
    if resume and path.exists():
        trainer.load_state_dict(checkpoint.load(path))
        print(f"resumed {run_dir} after iteration {trainer.iteration}")
    elif source is not None:
        fork.start(source, trainer)
        trainer.save()  # the fork's own checkpoint: resume=true continues it from here
        trainer.write_metrics()
    return trainer.train()


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def main(cfg: DictConfig) -> None:
    history = run(cfg, Path(HydraConfig.get().runtime.output_dir))
    if history:
        print(f"final success rate {history[-1]['success_rate']:.2f} after {len(history)} iterations")


if __name__ == "__main__":
    main()
