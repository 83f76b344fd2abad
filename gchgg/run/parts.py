"""The parts of one training run, built from its config: envs, metric, sampler, buffer, relabelling, agent, goals.

:func:`make_parts` checks the composed config (:func:`gchgg.run.config.check`) and reads the checked
:class:`~gchgg.run.config.RunConfig` it returns (and only it) into the explicit arguments of the parts and
of the builders in :mod:`gchgg.run.builders`; it checks no setting again. The :class:`~gchgg.train.Trainer`
only runs the loop over what it returns, so a test or a notebook can build a trainer from parts it
made itself. Every random stream of a run comes from one named seed table (:func:`seed_table`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from functools import partial

import numpy as np
import torch
from omegaconf import DictConfig
from torchrl.envs import TransformedEnv

import envs
from gchgg.ddpg import DDPGAgent, DDPGConfig
from gchgg.hgg import estimate_max_distance
from gchgg.run import config
from gchgg.run.builders import (
    make_goal_generator,
    make_metric,
    make_observation_noise,
    make_relabel,
    make_replay_buffer,
    make_sampler,
    make_tradeoff,
)

__all__ = ["SEEDS", "Parts", "ddpg_config", "make_env", "make_parts", "seed_table"]

MAX_DIS_RESETS = 1000  # resets over which HGG's max_dis (largest initial-to-target distance) is taken
SEEDS = ("explore", "her", "buffer", "eval_env", "agent", "env_noise", "eval_noise")
"""The run's random streams, in the order ``np.random.SeedSequence(seed)`` hands out their seeds (the
order is the recorded runs' and must not change; a new stream goes at the end). The training env's
tasks are seeded with ``seed`` itself."""


def seed_table(seed: int) -> dict[str, int]:
    """The seed of each of the run's random streams (:data:`SEEDS`), derived from the run's ``seed``."""
    return dict(zip(SEEDS, (int(s) for s in np.random.SeedSequence(seed).generate_state(len(SEEDS))), strict=True))


@dataclass
class Parts:
    """What one run trains with, built by :func:`make_parts`.

    Attributes:
        env: the batched training env (one simulation per episode of a chunk), with observation noise
            when ``noise.object_std`` is set; ``eval_env`` the evaluation env, and ``build_eval_env`` the
            function that builds it (the background evaluator builds its own).
        noise_generators: the observation noise's generators by env (``"env"``, ``"eval_env"``), where
            there is noise.
        achieved_key: where the true achieved goal is (``true_achieved_goal`` under observation noise).
        metric, tradeoff, sampler, buffer: the goal metric, the λ schedule (``None`` for samplers
            without one), the replay sampler and the replay buffer.
        relabel: the energy + HER relabelling transform.
        agent: the DDPG learner; goal_generator: HGG's (``None`` without one).
        streams: the loop's own generators by name (``"explore"``).
        steps: the episode length T; buffer_rows: the buffer's capacity in rows.
    """

    env: object
    eval_env: object
    build_eval_env: object
    noise_generators: dict
    achieved_key: str
    metric: object
    tradeoff: object
    sampler: object
    buffer: object
    relabel: object
    agent: DDPGAgent
    goal_generator: object
    streams: dict
    steps: int
    buffer_rows: int


def make_parts(cfg: DictConfig | config.RunConfig) -> Parts:
    """Check the config (:func:`gchgg.run.config.check`) and build a run's parts from the checked
    :class:`~gchgg.run.config.RunConfig`. Sets torch's thread count (``threads``) and its global seed; the
    order of the builds is that of the recorded runs."""
    run = config.check(cfg)
    if run.threads:
        torch.set_num_threads(run.threads)
    torch.manual_seed(run.seed)
    seeds = seed_table(run.seed)
    name, algo, graph, noise_std = run.env.name, run.algo, run.graph, run.noise.object_std
    geometry = envs.geometry(name)
    steps, chunk_size = geometry.episode_length, run.train.episodes // run.train.chunks
    options = {"threshold": run.env.threshold, "start": run.env.start}
    # Observation noise (a camera's error): the policy sees noisy positions; rewards, energy and the
    # goal pool read the true achieved goal the noise transform keeps.
    env, noise = make_env(name, chunk_size, run.seed, options, noise_std, seeds["env_noise"])
    build_eval_env = partial(make_env, name, run.eval.episodes, seeds["eval_env"], options, run.eval.noise_std,
                             seeds["eval_noise"])
    eval_env, eval_noise = build_eval_env()
    achieved_key = "true_achieved_goal" if noise_std else "achieved_goal"

    def metric_of(kind: str):
        if kind != "graph":
            return make_metric(kind)
        return make_metric(kind, geometry.field, geometry.obstacles, n=tuple(graph.n), margin=graph.margin,
                           snap=graph.snap, cache_dir=graph.cache_dir)

    metric = metric_of(algo.metric)
    tradeoff = None  # only samplers that weigh diversity against proximity have a λ (config.check)
    if algo.sampler in ("curriculum", "cher"):
        tradeoff = make_tradeoff(run.tradeoff.name, **{k: v for k, v in asdict(run.tradeoff).items() if k != "name"})
    options = {}  # what the sampler reads: its own section
    if algo.sampler == "curriculum":
        curriculum = run.curriculum
        other = curriculum.diversity_metric != algo.metric
        diversity_metric = metric_of(curriculum.diversity_metric) if other else None
        options = dict(num_candidates=curriculum.num_candidates, proximity=curriculum.proximity,
                       diversity_of=curriculum.diversity_of, diversity_metric=diversity_metric, scale=curriculum.scale)
    elif algo.sampler == "cher":
        options = dict(pool_size=run.cher.pool_size)
    fast = not run.plain  # the speed devices, or the algorithm alone (each part's own plain path)
    sampler = make_sampler(algo.sampler, metric, tradeoff, fast=fast, **options)
    copies = run.her.k + 1
    buffer = make_replay_buffer(run.buffer.episodes, copies * steps, sampler, batch_size=run.train.batch_size,
                                generator=torch.Generator().manual_seed(seeds["buffer"]), fast=fast)
    relabel = make_relabel(
        partial(envs.reward, threshold=run.env.threshold), k=run.her.k, strategy=run.her.strategy,
        generator=torch.Generator().manual_seed(seeds["her"]),
        true_achieved_goal_key=achieved_key if noise_std else None,
    )  # fmt: skip
    agent = DDPGAgent(env.obs_dim, 3, env.action_dim, ddpg_config(run.agent),
                      generator=torch.Generator().manual_seed(seeds["agent"]), matmul=run.matmul,
                      precision=run.precision, gradients=run.gradients, subnormals=run.subnormals, fast=fast)
    goal_generator = None
    if algo.goal_generator != "none":
        goal_generator = make_goal_generator(
            algo.goal_generator, metric, max_dis=max_distance(metric, eval_env), gamma=run.agent.gamma,
            stop_threshold=run.env.stop_threshold, success_threshold=run.env.threshold, pool_size=run.hgg.pool_size,
            c=run.hgg.c, L=run.hgg.L,
        )  # fmt: skip
    return Parts(
        env=env, eval_env=eval_env, build_eval_env=build_eval_env,
        noise_generators={key: g for key, g in (("env", noise), ("eval_env", eval_noise)) if g is not None},
        achieved_key=achieved_key, metric=metric, tradeoff=tradeoff, sampler=sampler, buffer=buffer,
        relabel=relabel, agent=agent, goal_generator=goal_generator,
        streams={"explore": torch.Generator().manual_seed(seeds["explore"])},
        steps=steps, buffer_rows=run.buffer.episodes * copies * steps,
    )  # fmt: skip


def ddpg_config(agent: config.AgentConfig) -> DDPGConfig:
    """The learner's own hyperparameters, each from the ``agent`` section (all its settings but
    ``normalizer_source``, which the loop reads)."""
    return DDPGConfig(**{f.name: getattr(agent, f.name) for f in fields(DDPGConfig)})


def max_distance(metric, env) -> float:
    """HGG's max_dis: the largest metric distance from initial achieved goal to target over
    :data:`MAX_DIS_RESETS` resets of ``env`` (the evaluation env: its draws move on)."""
    starts, targets = [], []
    for _ in range(math.ceil(MAX_DIS_RESETS / env.num_envs)):
        td = env.reset()
        starts.append(td["achieved_goal"])
        targets.append(td["desired_goal"])
    return estimate_max_distance(metric, torch.cat(starts), torch.cat(targets))


def make_env(name: str, num_envs: int, seed: int, options: dict, noise_std: float, noise_seed: int):
    """A batched env with observation noise of ``noise_std`` (a camera's error) and the noise's generator
    (``None`` without noise): the training and the evaluation env, the latter built the same in the
    trainer and in the background evaluator's process."""
    env = envs.make(name, num_envs=num_envs, seed=seed, **options)
    if not noise_std:
        return env, None
    generator = torch.Generator().manual_seed(noise_seed)
    noise = make_observation_noise(envs.observation_layout(name), env.has_object, noise_std, generator)
    return TransformedEnv(env, noise), generator
