"""The run's settings as structured configs: each one declared once, with its default, its meaning and its check.

``python -m gchgg.train`` composes ``conf/config.yaml``, which holds no values. It starts from the
schema :class:`RunConfig`, registered with Hydra's ConfigStore as ``base_config``. It then takes one
choice per group:

- ``env/<task>.yaml`` and ``algo/<method>.yaml``: each task's and each method's own values, typed
  by :class:`EnvConfig` and :class:`AlgoConfig`;
- ``graph`` and ``tradeoff``: the schemas :class:`GraphConfig`, :class:`AdaptiveTradeoffConfig`,
  :class:`ExponentialTradeoffConfig` and :class:`FixedTradeoffConfig`, registered as the groups'
  options.

An algorithm's config holds only what it reads. The ``algo`` files of the methods without a
curriculum, a λ, CHER's pool or a graph metric set ``curriculum``, ``tradeoff``, ``cher`` and
``graph`` to ``null``.

Settings flow one way: this module imports nothing from the library (only the check helpers of
:mod:`gchgg.common.validation` and the trackers' own check, :func:`gchgg.run.loggers.check_backends`,
which import nothing of the project). Every default and every choice list is written here as a
literal, and :func:`gchgg.run.parts.make_parts` hands each value of the checked :class:`RunConfig` to
the parts explicitly. Reading the defaults from the parts' signatures instead put the schema above
nine library modules, so that a reader of the settings met the whole algorithm first; a reusable part
keeps its own defaults and checks for those who build it by hand. Where a part has a default, a
choice list or a rule for the same setting (the HER ``k``, the curriculum's K, eq. 20's η and σ,
DDPG's hyperparameters, the graph's lattice), ``tests/test_config.py`` holds the two equal, so they
cannot drift.

:func:`check` validates a composed config before anything is built: every setting once, by the rule
of the part that takes it, in the section's ``check`` method, which names it ``<section>.<setting>``;
then the settings that depend on each other. The builders and :func:`~gchgg.run.parts.make_parts`
check no setting again; the parts check their own arguments when they are built, their contract as a
library.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from gchgg.common.validation import check_choice, check_number
from gchgg.run import loggers

__all__ = [
    "AdaptiveTradeoffConfig", "AgentConfig", "AlgoConfig", "BufferConfig", "CheckpointConfig", "CherConfig",
    "CurriculumConfig", "EnvConfig", "EvalConfig", "ExponentialTradeoffConfig", "FixedTradeoffConfig", "GraphConfig",
    "HERConfig", "HGGConfig", "LoggingConfig", "NoiseConfig", "RunConfig", "TrainConfig", "check", "register",
]  # fmt: skip

# The choices of each setting that picks one (the parts' own lists where a part takes the setting).
GOAL_GENERATORS = ("none", "hgg")  # algo.goal_generator
METRICS = ("euclidean", "graph")  # algo.metric, curriculum.diversity_metric
SAMPLERS = ("uniform", "ebp", "curriculum", "cher")  # algo.sampler
UPDATE_EVERY = ("iteration", "episode")  # tradeoff.update_every (AdaptiveTradeoff.UPDATE_EVERY)
SNAPS = ("nearest", "floor")  # graph.snap (GoalGraph's snap)
PROXIMITIES = ("goal_to_target", "achieved_to_goal")  # curriculum.proximity (gchgg.run.builders.PROXIMITY_KEYS)
DIVERSITY_OF = ("goal", "achieved")  # curriculum.diversity_of (gchgg.run.builders.DIVERSITY_KEYS)
SCALES = ("raw", "standardized")  # curriculum.scale (gchgg.samplers.curriculum.SCALES)
HER_STRATEGIES = ("future", "final", "episode")  # her.strategy (gchgg.transforms.HerStrategy)
NORMALIZER_SOURCES = ("sampled", "collected")  # agent.normalizer_source
MATMUL_BACKENDS = ("auto", "onednn", "default")  # matmul (gchgg.fast.linear.MATMUL_BACKENDS)
PRECISIONS = ("auto", "float32", "bfloat16")  # precision (gchgg.fast.linear.PRECISIONS)
GRADIENTS = ("auto", "fused", "compiled", "autograd")  # gradients (the agent's GRADIENTS)
SUBNORMALS = ("auto", "flush", "keep")  # subnormals (gchgg.fast.subnormal.SUBNORMALS)
PLAIN = {"matmul": "default", "precision": "float32", "gradients": "autograd", "subnormals": "keep"}
"""What ``plain=true`` sets (the agent's ``fast=False``: gchgg.ddpg.agent.PLAIN); each one's ``auto`` resolves to it."""
BACKGROUND = ("auto", True, False)  # eval.background (gchgg.run.evaluator.resolve_background)


def _positive(section: str, config: Any, names: tuple[str, ...], *, allow_zero: bool = False) -> None:
    for name in names:
        check_number(f"{section}.{name}", getattr(config, name), integer=True, low=0, low_open=not allow_zero)


@dataclass
class EnvConfig:
    """A task (``conf/env/<task>.yaml`` sets every value)."""

    name: str = MISSING  # reach | push_new | pick_no_obstacle | pick_obstacle
    start: str = MISSING  # the task's start state (original: the authors')
    threshold: float = MISSING  # success distance in metres (eq. 23)
    buffer_episodes: int = MISSING  # replay capacity in episodes
    stop_threshold: float | None = MISSING  # HGG stop: fraction of intermediate goals at their target (null: never)

    def check(self) -> None:
        check_number("env.threshold", self.threshold, low=0, low_open=True)
        _positive("env", self, ("buffer_episodes",))
        if self.stop_threshold is not None:
            check_number("env.stop_threshold (a fraction, or null)", self.stop_threshold, low=0, high=1)


@dataclass
class AlgoConfig:
    """A method (``conf/algo/<method>.yaml`` sets every value; DESIGN's table of algorithms)."""

    name: str = MISSING  # her | hgg | ghgg | cher | gchgg | gchgg_code
    goal_generator: str = MISSING  # none | hgg
    metric: str = MISSING  # euclidean | graph (goal generation and the sampler's distances)
    sampler: str = MISSING  # uniform | ebp | curriculum | cher

    def check(self) -> None:
        check_choice("algo.goal_generator", self.goal_generator, GOAL_GENERATORS)
        check_choice("algo.metric", self.metric, METRICS)
        check_choice("algo.sampler", self.sampler, SAMPLERS)


@dataclass
class GraphConfig:
    """The obstacle-aware goal graph (``graph=default``), for a graph metric (``algo.metric`` or
    ``curriculum.diversity_metric``)."""

    n: list[int] = field(default_factory=lambda: [31, 31, 11])  # lattice vertices per axis (eqs. 9-10, 12)
    margin: float = 0.02  # safety margin added to every obstacle half-size (m)
    snap: str = "nearest"  # goal -> vertex (eq. 14): nearest | floor
    cache_dir: str | None = None  # the distance tables' cache; null: $GCHGG_CACHE_DIR or ~/.cache/gchgg

    def check(self) -> None:
        """The graph's own settings; the density criterion (eq. 12) needs the task's obstacles and is the graph's."""
        if len(self.n) != 3 or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 2 for v in self.n):
            raise ValueError(f"graph.n must be three integers (n_x, n_y, n_z), each >= 2 (vertices per axis), "
                             f"got {self.n!r}")
        check_number("graph.margin", self.margin, low=0)
        check_choice("graph.snap", self.snap, SNAPS)


@dataclass
class AdaptiveTradeoffConfig:
    """λ from eq. 20 (``tradeoff=adaptive``, GC-HGG's)."""

    name: str = "adaptive"
    eta: float = 1000.0  # scale η of eq. 20
    sigma: float = 0.3  # width σ of eq. 20 (m)
    update_every: str = "iteration"  # iteration (the paper) | episode (the code)

    def check(self) -> None:
        check_number("tradeoff.eta", self.eta, low=0)
        check_number("tradeoff.sigma", self.sigma, low=0, low_open=True)
        check_choice("tradeoff.update_every", self.update_every, UPDATE_EVERY)


@dataclass
class ExponentialTradeoffConfig:
    """λ from eq. 4 (``tradeoff=exponential``, CHER's)."""

    name: str = "exponential"
    lambda_0: float = 1.0  # λ at iteration 0
    tau: float = 0.005  # growth per iteration

    def check(self) -> None:
        check_number("tradeoff.lambda_0", self.lambda_0, low=0)
        check_number("tradeoff.tau", self.tau, low=-1, low_open=True)


@dataclass
class FixedTradeoffConfig:
    """A constant λ (``tradeoff=fixed``)."""

    name: str = "fixed"
    value: float = 1.0

    def check(self) -> None:
        check_number("tradeoff.value", self.value, low=0)


TRADEOFFS = {"adaptive": AdaptiveTradeoffConfig, "exponential": ExponentialTradeoffConfig,
             "fixed": FixedTradeoffConfig}  # the tradeoff group's options (tradeoff.name) and their sections' schemas


@dataclass
class TrainConfig:
    """The training loop (Alg. 2)."""

    iterations: int = 200  # training iterations ("cycles", the x-axis of the paper's plots)
    episodes: int = 50  # episodes collected per iteration
    # C: an iteration collects its episodes in C batched chunks, each followed by its share of the updates
    # and a normaliser update (C = episodes: the original per-episode loop); must divide episodes
    chunks: int = "${train.episodes}"  # type: ignore[assignment]  # an interpolation
    updates: int = 1000  # DDPG updates per iteration, spread over the chunks
    batch_size: int = 256  # transitions per DDPG update
    warmup_steps: int = 10000  # env steps of uniform random actions before the policy acts
    update_during_warmup: bool = False  # also update on warm-up data (the original does not)
    stop_success: float | None = None  # stop once the success rate holds this for stop_patience evaluations
    stop_patience: int = 5  # evaluations the success rate must hold stop_success for

    def check(self) -> None:
        _positive("train", self, ("iterations", "episodes", "chunks", "batch_size", "stop_patience"))
        _positive("train", self, ("updates", "warmup_steps"), allow_zero=True)
        if self.episodes % self.chunks:
            raise ValueError(
                f"train.chunks must divide train.episodes (each chunk collects the same number of episodes), "
                f"got train.chunks={self.chunks} for train.episodes={self.episodes}"
            )
        if self.stop_success is not None:
            check_number("train.stop_success (a success rate, or null)", self.stop_success, low=0, high=1)


@dataclass
class EvalConfig:
    """Evaluation on target goals."""

    episodes: int = 100  # deterministic evaluation episodes
    every: int = 1  # iterations between evaluations (and after the last); the early stop counts evaluations
    # evaluate each policy snapshot in a second process while training goes on: true | false | auto (where a
    # core is free beside the run's torch threads; gchgg.run.evaluator.resolve_background). Same metrics.
    background: Any = "auto"
    noise_std: float = 0.0  # metres: the observation noise (noise.object_std) in evaluation episodes too

    def check(self) -> None:
        _positive("eval", self, ("episodes", "every"))
        check_choice("eval.background", self.background, BACKGROUND)
        check_number("eval.noise_std", self.noise_std, low=0)


@dataclass
class NoiseConfig:
    """Observation noise in training rollouts (a camera's error)."""

    object_std: float = 0.0  # metres of Gaussian noise on the observed object (reach: grip) position; 0: off

    def check(self) -> None:
        check_number("noise.object_std", self.object_std, low=0)


@dataclass
class BufferConfig:
    """The replay buffer."""

    episodes: int = "${env.buffer_episodes}"  # type: ignore[assignment]  # FIFO capacity in episodes

    def check(self) -> None:
        _positive("buffer", self, ("episodes",))


@dataclass
class HGGConfig:
    """HGG's goal generator (eqs. 5-7), for ``algo.goal_generator=hgg``."""

    pool_size: int = 1000  # trajectories kept in the pool (FIFO)
    c: float = 3.0  # weight of the initial-state distance in eq. 6
    L: float = 5.0  # Lipschitz constant of eqs. 5-7

    def check(self) -> None:
        _positive("hgg", self, ("pool_size",))
        check_number("hgg.c", self.c, low=0)
        check_number("hgg.L", self.L, low=0, low_open=True)


@dataclass
class CurriculumConfig:
    """The graph-curriculum sampler (Alg. 1), for ``algo.sampler=curriculum``."""

    num_candidates: int = 8  # K candidate batches per sample
    proximity: str = "goal_to_target"  # goal_to_target (eq. 15) | achieved_to_goal (the authors' code)
    diversity_of: str = "goal"  # goal (eq. 19) | achieved (the transitions' achieved goals: the code)
    diversity_metric: str = "${algo.metric}"  # graph | euclidean: metric of F_div's nearest neighbours
    scale: str = "raw"  # raw | standardized (each term over its std)

    def check(self) -> None:
        _positive("curriculum", self, ("num_candidates",))
        check_choice("curriculum.proximity", self.proximity, PROXIMITIES)
        check_choice("curriculum.diversity_of", self.diversity_of, DIVERSITY_OF)
        check_choice("curriculum.diversity_metric", self.diversity_metric, METRICS)
        check_choice("curriculum.scale", self.scale, SCALES)


@dataclass
class CherConfig:
    """CHER's greedy selection, for ``algo.sampler=cher``."""

    pool_size: int = 5000  # transitions each batch is picked from

    def check(self) -> None:
        _positive("cher", self, ("pool_size",))


@dataclass
class HERConfig:
    """HER relabelling."""

    k: int = 4  # relabelled copies per step (ratio k/(k+1))
    strategy: str = "future"  # future | final | episode

    def check(self) -> None:
        _positive("her", self, ("k",), allow_zero=True)
        check_choice("her.strategy", self.strategy, HER_STRATEGIES)


@dataclass
class AgentConfig:
    """DDPG's hyperparameters (those of :class:`gchgg.ddpg.DDPGConfig`, with its defaults: the original code's)
    and where the normalisers' statistics come from."""

    hidden: list[int] = field(default_factory=lambda: [256, 256, 256])  # hidden sizes of actor and critic
    actor_lr: float = 1e-3  # Adam learning rate of the actor
    critic_lr: float = 1e-3  # Adam learning rate of the critic
    gamma: float = 0.98  # discount
    polyak: float = 0.95  # target <- polyak * target + (1 - polyak) * online
    target_update_every: int = 20  # updates between two soft target updates
    action_l2: float = 1.0  # weight of mean(pi^2) in the actor loss
    clip_return: bool = True  # clip the bootstrapped Q' to [-1/(1-gamma), 0]
    random_eps: float = 0.3  # probability of a uniform random action while exploring
    noise_std: float = 0.2  # std of the Gaussian exploration noise (eq. 22)
    norm_std_min: float = 1e-2  # std floor of the normalisers
    norm_clip: float = 5.0  # normalised inputs are clipped to +-norm_clip
    normalizer_source: str = "sampled"  # sampled: from a batch drawn after each chunk (the original) | collected

    def check(self) -> None:
        if not self.hidden or not all(isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in self.hidden):
            raise ValueError(f"agent.hidden must be a non-empty list of positive layer widths, got {self.hidden!r}")
        for name in ("actor_lr", "critic_lr", "norm_std_min", "norm_clip"):
            check_number(f"agent.{name}", getattr(self, name), low=0, low_open=True)
        check_number("agent.gamma", self.gamma, low=0, high=1, low_open=True, high_open=True)
        check_number("agent.polyak", self.polyak, low=0, high=1)
        _positive("agent", self, ("target_update_every",))
        check_number("agent.action_l2", self.action_l2, low=0)
        check_number("agent.random_eps", self.random_eps, low=0, high=1)
        check_number("agent.noise_std", self.noise_std, low=0)
        check_choice("agent.normalizer_source", self.normalizer_source, NORMALIZER_SOURCES)


@dataclass
class CheckpointConfig:
    """Checkpoints."""

    every: int = 1  # iterations between checkpoints (and after the last); a resumed run repeats the rest

    def check(self) -> None:
        _positive("checkpoint", self, ("every",))


@dataclass
class LoggingConfig:
    """Trackers and progress output (:mod:`gchgg.run.loggers`)."""

    backend: Any = "csv"  # csv | tensorboard | wandb | mlflow, or a list: [csv,tensorboard,wandb]
    project: str = "gchgg"  # W&B project (a sweep's runs are grouped by its folder's name)
    mlflow_uri: str | None = None  # MLflow tracking URI (null: $MLFLOW_TRACKING_URI, else a SQLite file)
    progress: bool = True  # show a progress bar

    def check(self) -> None:
        loggers.check_backends(self.backend)  # a known name, its package installed


@dataclass
class RunConfig:
    """One training run: the top-level settings and one section per part."""

    seed: int = 0  # seeds the env, the networks and every generator of the run (gchgg.run.parts.SEEDS)
    resume: bool = False  # continue the run in the run folder from its last checkpoint
    init_from: str | None = None  # a run folder: start from its last checkpoint with these settings (a fork)
    threads: int = 1  # torch CPU threads (1: fastest for these small nets on a shared machine; 0: torch's)
    matmul: str = "auto"  # the wide layers' products: auto (oneDNN for bfloat16, or where faster) | onednn | default
    precision: str = "auto"  # their dtype in updates: auto (bfloat16 where native) | float32 | bfloat16
    gradients: str = "auto"  # of the updates: auto (by hand wherever the networks allow) | fused | compiled | autograd
    # in updates: flush (to zero: fast, same networks; gchgg.fast.subnormal) | keep | auto (flush; keep if plain)
    subnormals: str = "auto"
    # the algorithm alone, no speed device of gchgg.fast: float32 products on torch's matmul, autograd, subnormals
    # kept, the samplers' plain paths, TorchRL's LazyTensorStorage, the actor module and eq. 22 on every batch,
    # torch.optim.Adam.step. The same numbers (tests/test_plain.py); slower. A contrary matmul, precision,
    # gradients or subnormals is refused (auto resolves to the plain choice: PLAIN)
    plain: bool = False
    env: EnvConfig = field(default_factory=EnvConfig)
    algo: AlgoConfig = field(default_factory=AlgoConfig)
    graph: GraphConfig | None = None  # the graph=default group; null where no metric is the graph
    tradeoff: Any = None  # the λ schedule's section (tradeoff=adaptive | exponential | fixed); null: no λ
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    buffer: BufferConfig = field(default_factory=BufferConfig)
    hgg: HGGConfig = field(default_factory=HGGConfig)
    curriculum: CurriculumConfig | None = field(default_factory=CurriculumConfig)
    cher: CherConfig | None = field(default_factory=CherConfig)
    her: HERConfig = field(default_factory=HERConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)

    def check(self) -> None:
        """Each section's settings (its ``check``; the optional sections where present), then the top-level ones."""
        if self.tradeoff is not None and type(self.tradeoff) is not TRADEOFFS.get(getattr(self.tradeoff, "name", None)):
            raise ValueError(f"the tradeoff section is one of the group's options, tradeoff={' | '.join(TRADEOFFS)}, "
                             f"got {self.tradeoff!r}")
        for section in (self.env, self.algo, self.graph, self.tradeoff, self.train, self.eval, self.noise, self.buffer,
                        self.hgg, self.curriculum, self.cher, self.her, self.agent, self.checkpoint, self.logging):
            if section is not None:
                section.check()
        check_number("seed", self.seed, integer=True, low=0)
        check_number("threads (0: torch's own count)", self.threads, integer=True, low=0)
        check_choice("matmul", self.matmul, MATMUL_BACKENDS)
        check_choice("precision", self.precision, PRECISIONS)
        check_choice("gradients", self.gradients, GRADIENTS)
        check_choice("subnormals", self.subnormals, SUBNORMALS)
        check_choice("plain", self.plain, (False, True))


def register() -> None:
    """Register the schema (``base_config``) and the schema-only group options with Hydra's ConfigStore."""
    store = ConfigStore.instance()
    store.store(name="base_config", node=RunConfig)
    store.store(group="graph", name="default", node=GraphConfig)
    for name, node in TRADEOFFS.items():
        store.store(group="tradeoff", name=name, node=node)


def check(cfg: DictConfig | RunConfig) -> RunConfig:
    """Check a composed config (or a :class:`RunConfig` built by hand) before anything is built: each
    section's settings (its ``check``), then those that depend on each other. Returns it as a resolved
    :class:`RunConfig`, what :func:`~gchgg.run.parts.make_parts` reads; a bad setting is a ``ValueError``
    naming it, its value and what is allowed."""
    run = OmegaConf.to_object(OmegaConf.structured(cfg) if isinstance(cfg, RunConfig) else cfg)
    if not isinstance(run, RunConfig):
        raise TypeError(f"a training config is composed from conf/config.yaml (base_config), got {type(run).__name__}")
    run.check()
    if run.plain:  # the plain path fixes how the products, gradients and subnormals are computed
        for name, value in PLAIN.items():
            if getattr(run, name) not in ("auto", value):
                raise ValueError(f"plain=true runs the algorithm alone, with {name}={value}, but {name}="
                                 f"{getattr(run, name)} was set: drop {name} (auto is {value} under plain=true), "
                                 "or set plain=false")
    algo = run.algo
    if run.train.episodes < 2 and algo.goal_generator == "hgg":
        raise ValueError(f"train.episodes must be >= 2 with a goal generator, got {run.train.episodes}")
    metrics = {algo.metric, *([run.curriculum.diversity_metric] if algo.sampler == "curriculum" else [])}
    if "graph" in metrics and run.graph is None:
        raise ValueError(f"a graph metric (algo.metric or curriculum.diversity_metric) needs the graph section, "
                         f"which algo={algo.name} leaves out: add graph=default")
    for section, sampler in (("curriculum", "curriculum"), ("cher", "cher")):
        if algo.sampler == sampler and getattr(run, section) is None:
            raise ValueError(f"algo.sampler={sampler} reads the {section} section, which algo={algo.name} sets to null")
    if algo.sampler in ("curriculum", "cher") and run.tradeoff is None:
        raise ValueError(f"algo.sampler={algo.sampler} weighs diversity against proximity and needs a λ schedule: "
                         "tradeoff=adaptive | exponential | fixed")
    return run


register()
