"""Structured configs (gchgg/run/config.py): each setting declared once in the run's schema, which imports nothing
of the library, with defaults, choices and rules held equal to the parts' own; each algorithm's config holding only
what it reads; a bad setting named before anything is built."""

from __future__ import annotations

import ast
import inspect
import math
import re
import typing
from dataclasses import fields, replace
from functools import partial
from pathlib import Path

import pytest
import torch
import yaml
from omegaconf import OmegaConf
from test_train import config

from gchgg.ddpg import DDPGConfig
from gchgg.ddpg.agent import GRADIENTS
from gchgg.fast.linear import MATMUL_BACKENDS, PRECISIONS
from gchgg.fast.subnormal import SUBNORMALS
from gchgg.graph import EuclideanMetric, GoalGraph, check_density_criterion
from gchgg.hgg import HGGGoalGenerator, TrajectoryPool
from gchgg.run import builders
from gchgg.run import config as schema
from gchgg.run.parts import ddpg_config
from gchgg.samplers import AdaptiveTradeoff, CherSampler, ExponentialTradeoff, FixedTradeoff, GraphCurriculumSampler
from gchgg.samplers.curriculum import SCALES
from gchgg.transforms import HerStrategy, HindsightRelabel

ROOT = Path(__file__).resolve().parents[1]


def test_config_yaml_holds_choices_not_values():
    text = yaml.safe_load((ROOT / "conf" / "config.yaml").read_text())
    assert set(text) == {"defaults", "hydra"}
    assert text["defaults"][0] == "base_config"


@pytest.mark.parametrize("path", sorted((ROOT / "conf" / "algo").glob("*.yaml")), ids=lambda p: p.stem)
def test_an_algorithm_file_restates_no_default(path):
    """What an algo file sets differs from the schema's default (else it is a second declaration)."""
    base = OmegaConf.structured(schema.RunConfig)
    own = yaml.safe_load(path.read_text())
    for section, values in own.items():
        if section in ("defaults", "algo") or values is None:
            continue
        defaults = {"tradeoff": OmegaConf.structured(schema.AdaptiveTradeoffConfig)}.get(section, base[section])
        for key, value in values.items():
            default = OmegaConf.to_container(defaults)[key]  # unresolved: ${algo.metric} stays a reference
            assert default != value, f"{path.name}: {section}.{key}={value!r} is the default"


def default(part, argument: str):
    """The default of ``argument`` in the signature of ``part`` (a class: its ``__init__``)."""
    return inspect.signature(part).parameters[argument].default


def test_the_schema_imports_nothing_of_the_library():
    """Settings flow one way: the schema sits at the bottom of the import graph (gchgg/run/config.py's docstring)."""
    text = (ROOT / "gchgg" / "run" / "config.py").read_text()
    tree = ast.parse(text)
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    imported |= {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    assert {m for m in imported if m.split(".")[0] in ("gchgg", "envs")} == {"gchgg.common.validation", "gchgg.run"}
    assert "from gchgg.run import loggers\n" in text  # the trackers' own check, which imports the standard library only


def test_each_schema_default_is_the_parts_own():
    """A default written in the schema and in the part that takes the setting is the same default."""
    pairs = [
        (schema.GraphConfig().n, list(default(GoalGraph, "n"))),
        (schema.GraphConfig().margin, default(GoalGraph, "margin")),
        (schema.GraphConfig().snap, default(GoalGraph, "snap")),
        (schema.AdaptiveTradeoffConfig().eta, default(AdaptiveTradeoff, "eta")),
        (schema.AdaptiveTradeoffConfig().sigma, default(AdaptiveTradeoff, "sigma")),
        (schema.AdaptiveTradeoffConfig().update_every, default(AdaptiveTradeoff, "update_every")),
        (schema.ExponentialTradeoffConfig().lambda_0, default(ExponentialTradeoff, "lambda_0")),
        (schema.ExponentialTradeoffConfig().tau, default(ExponentialTradeoff, "tau")),
        (schema.FixedTradeoffConfig().value, default(FixedTradeoff, "value")),
        (schema.HGGConfig().pool_size, default(TrajectoryPool, "capacity")),
        (schema.HGGConfig().c, default(HGGGoalGenerator, "c")),
        (schema.HGGConfig().L, default(HGGGoalGenerator, "L")),
        (schema.CurriculumConfig().num_candidates, default(GraphCurriculumSampler, "num_candidates")),
        (schema.CurriculumConfig().scale, default(GraphCurriculumSampler, "scale")),
        (schema.CherConfig().pool_size, default(CherSampler, "pool_size")),
        (schema.HERConfig().k, default(HindsightRelabel, "k")),
        (HerStrategy(schema.HERConfig().strategy), HerStrategy(default(HindsightRelabel, "strategy"))),
    ]
    for ours, theirs in pairs:
        assert ours == theirs and type(ours) is type(theirs), (ours, theirs)
    assert {f.name for f in fields(schema.AgentConfig)} == {f.name for f in fields(DDPGConfig)} | {"normalizer_source"}
    assert ddpg_config(schema.AgentConfig()) == DDPGConfig()  # the same defaults, every one handed over
    changed = {"hidden": [8], "gamma": 0.5, "norm_clip": 3.0, "clip_return": False}
    assert ddpg_config(schema.AgentConfig(**changed)) == DDPGConfig(**changed)


def test_each_choice_list_is_the_parts_own():
    assert schema.SCALES == SCALES
    assert schema.UPDATE_EVERY == AdaptiveTradeoff.UPDATE_EVERY
    assert schema.SNAPS == typing.get_args(typing.get_type_hints(GoalGraph.__init__)["snap"])
    assert schema.HER_STRATEGIES == tuple(s.value for s in HerStrategy)
    assert (schema.MATMUL_BACKENDS, schema.PRECISIONS) == (MATMUL_BACKENDS, PRECISIONS)
    assert (schema.GRADIENTS, schema.SUBNORMALS) == (GRADIENTS, SUBNORMALS)
    assert tuple(builders.PROXIMITY_KEYS) == schema.PROXIMITIES
    assert tuple(builders.DIVERSITY_KEYS) == schema.DIVERSITY_OF
    assert tuple(builders.TRADEOFFS) == tuple(schema.TRADEOFFS)


def test_the_builders_build_each_choice_and_declare_no_default(tmp_path):
    euclidean, tradeoff = EuclideanMetric(), FixedTradeoff()
    graph = dict(n=(2, 2, 2), margin=0.0, snap="nearest", cache_dir=tmp_path)
    built = {kind: builders.make_metric(kind, ((0, 0, 0), (1, 1, 1)), **(graph if kind == "graph" else {}))
             for kind in schema.METRICS}
    assert isinstance(built["euclidean"], EuclideanMetric) and isinstance(built["graph"], GoalGraph)
    settings = {"curriculum": dict(num_candidates=2, proximity="goal_to_target", diversity_of="goal",
                                   diversity_metric=None, scale="raw"), "cher": dict(pool_size=4)}
    for kind in schema.SAMPLERS:
        for fast in (True, False):  # the speed devices, or the plain path (plain=true)
            builders.make_sampler(kind, euclidean, tradeoff, fast=fast, **settings.get(kind, {}))
    hgg = dict(max_dis=1.0, gamma=0.98, stop_threshold=None, success_threshold=0.05, pool_size=4, c=3.0, L=5.0)
    generators = [builders.make_goal_generator(kind, euclidean, **hgg) for kind in schema.GOAL_GENERATORS]
    assert generators[0] is None and isinstance(generators[1], HGGGoalGenerator)
    for call in (lambda: builders.make_metric("manhattan"),
                 lambda: builders.make_sampler("best", euclidean, None, fast=True),
                 lambda: builders.make_goal_generator("her", euclidean, **hgg)):
        with pytest.raises(KeyError):  # not a setting's check: config.check names the setting before any build
            call()
    # not settings: a mode switch (observation noise) and the task geometry a Euclidean metric has no use for
    allowed = {("make_relabel", "true_achieved_goal_key"), ("make_metric", "field"), ("make_metric", "obstacles")}
    for name, builder in inspect.getmembers(builders, inspect.isfunction):
        if name.startswith("make_"):
            for parameter in inspect.signature(builder).parameters.values():
                if parameter.default is not inspect.Parameter.empty:
                    assert (name, parameter.name) in allowed, f"{name}({parameter.name}=...) declares a default"


def _accepts(build) -> bool:
    try:
        build()
    except (ValueError, TypeError):
        return False
    return True


def _reward(achieved, goal):
    return torch.zeros(achieved.shape[:-1])


ENV = schema.EnvConfig(name="reach", start="original", threshold=0.05, buffer_episodes=8, stop_threshold=None)
EUCLIDEAN = EuclideanMetric()
FIELD = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
RULES = [  # (the schema's section, setting, values at the rule's edges, the part that takes the setting)
    (schema.HERConfig(), "k", [-1, 0, 1], lambda v: HindsightRelabel(_reward, v)),
    (schema.HERConfig(), "strategy", ["future", "final", "episode", "last"], lambda v: HindsightRelabel(_reward, 4, v)),
    (schema.HGGConfig(), "pool_size", [-1, 0, 1], TrajectoryPool),
    (schema.HGGConfig(), "c", [-0.1, 0.0, 3.0, math.inf], lambda v: HGGGoalGenerator(EUCLIDEAN, max_dis=1.0, c=v)),
    (schema.HGGConfig(), "L", [-1.0, 0.0, 5.0], lambda v: HGGGoalGenerator(EUCLIDEAN, max_dis=1.0, L=v)),
    (ENV, "stop_threshold", [None, -0.1, 0.0, 1.0, 1.1],
     lambda v: HGGGoalGenerator(EUCLIDEAN, max_dis=1.0, stop_threshold=v)),
    (schema.CurriculumConfig(diversity_metric="graph"), "num_candidates", [0, 1, 8],
     lambda v: GraphCurriculumSampler(EUCLIDEAN, v)),
    (schema.CurriculumConfig(diversity_metric="graph"), "scale", ["raw", "standardized", "z"],
     lambda v: GraphCurriculumSampler(EUCLIDEAN, scale=v)),
    (schema.CherConfig(), "pool_size", [0, 1, 5000], lambda v: CherSampler(EUCLIDEAN, v)),
    (schema.AdaptiveTradeoffConfig(), "eta", [-1.0, 0.0, 1000.0], lambda v: AdaptiveTradeoff(eta=v)),
    (schema.AdaptiveTradeoffConfig(), "sigma", [-0.1, 0.0, 0.3], lambda v: AdaptiveTradeoff(sigma=v)),
    (schema.AdaptiveTradeoffConfig(), "update_every", ["iteration", "episode", "chunk"],
     lambda v: AdaptiveTradeoff(update_every=v)),
    (schema.ExponentialTradeoffConfig(), "lambda_0", [-1.0, 0.0, 1.0], lambda v: ExponentialTradeoff(lambda_0=v)),
    (schema.ExponentialTradeoffConfig(), "tau", [-1.5, -1.0, -0.5, 0.005], lambda v: ExponentialTradeoff(tau=v)),
    (schema.FixedTradeoffConfig(), "value", [-1.0, 0.0, 1.0], FixedTradeoff),
    (schema.GraphConfig(), "n", [[31, 31, 11], [2, 2, 2], [1, 31, 11], [31, 31], [31, 31, 11, 2]],
     lambda v: check_density_criterion(FIELD, (), v)),
    (schema.GraphConfig(), "margin", [-0.01, 0.0, 0.02, math.nan],
     lambda v: check_density_criterion(FIELD, (), margin=v)),
    *[(schema.AgentConfig(), name, [-1.0, 0.0, 0.5, 1.0, 2.0], lambda v, name=name: DDPGConfig(**{name: v}))
      for name in ("actor_lr", "critic_lr", "gamma", "polyak", "action_l2", "random_eps", "noise_std", "norm_std_min",
                   "norm_clip")],
    (schema.AgentConfig(), "target_update_every", [0, 1, 20], lambda v: DDPGConfig(target_update_every=v)),
    (schema.AgentConfig(), "hidden", [[], [0, 16], [16], [256, 256, 256]], lambda v: DDPGConfig(hidden=v)),
]


@pytest.mark.parametrize("section, setting, values, part", RULES, ids=[f"{type(r[0]).__name__}.{r[1]}" for r in RULES])
def test_each_rule_is_the_parts_own(section, setting, values, part):
    """A setting the schema checks and a part checks again (its contract as a library) has one rule: at the
    rule's edges, the schema takes a value exactly where the part does."""
    for value in values:
        ours, theirs = _accepts(replace(section, **{setting: value}).check), _accepts(partial(part, value))
        assert ours == theirs, f"{setting}={value!r}: the schema {'takes' if ours else 'refuses'} it, the part not"


def test_the_discount_is_declared_in_the_part_and_in_the_schema_alone():
    """The issue's example: gamma = 0.98 was declared in config.yaml, twice in agent.py and in hgg.py. Now in
    DDPGConfig (the part) and in the run's schema, which test_each_schema_default_is_the_parts_own holds equal."""
    found = [(path.relative_to(ROOT), line) for path in [*ROOT.glob("gchgg/**/*.py"), *ROOT.glob("conf/**/*.yaml")]
             for line in path.read_text().splitlines() if re.search(r"gamma\W[^(]*0\.98", line)]
    part = Path(inspect.getsourcefile(DDPGConfig)).relative_to(ROOT)
    assert sorted(str(path) for path, _ in found) == sorted([str(part), "gchgg/run/config.py"]), found


def test_each_algorithm_holds_only_the_sections_it_reads():
    curriculum = {"graph", "tradeoff", "curriculum"}
    reads = {"her": set(), "hgg": set(), "ghgg": {"graph"}, "cher": {"tradeoff", "cher"},
             "gchgg": curriculum, "gchgg_code": curriculum}
    for algo, sections in reads.items():
        cfg = config([f"algo={algo}"])
        assert {s for s in ("graph", "tradeoff", "curriculum", "cher") if cfg[s] is not None} == sections, algo
        schema.check(cfg)
    with pytest.raises(ValueError, match="a graph metric .* needs the graph section, which algo=hgg leaves out"):
        schema.check(config(["algo=hgg", "algo.metric=graph"]))
    schema.check(config(["algo=hgg", "algo.metric=graph", "graph=default"]))  # G-HGG by hand


@pytest.mark.parametrize(
    "override, message",
    [
        ("train.chunks=7", "train.chunks must divide train.episodes"),
        ("eval.every=0", "eval.every must be an integer > 0, got 0"),
        ("her.k=-1", "her.k must be an integer >= 0, got -1"),
        ("hgg.pool_size=0", "hgg.pool_size must be an integer > 0, got 0"),
        ("env.stop_threshold=1.5", r"env.stop_threshold \(a fraction, or null\) must be a number in \[0, 1\]"),
        ("algo.sampler=best", "algo.sampler must be one of"),
        ("precision=fp16", "precision must be one of 'auto', 'float32', 'bfloat16', got 'fp16'"),
        ("agent.polyak=2", r"agent.polyak must be a number in \[0, 1\], got 2"),
        ("curriculum.scale=z", "curriculum.scale must be one of 'raw', 'standardized', got 'z'"),
        ("curriculum.proximity=near", "curriculum.proximity must be one of 'goal_to_target', 'achieved_to_goal'"),
        ("tradeoff.sigma=0", "tradeoff.sigma must be a number > 0, got 0"),
        ("graph.snap=round", "graph.snap must be one of 'nearest', 'floor', got 'round'"),
        ("hgg.L=0", "hgg.L must be a number > 0, got 0"),
        ("her.strategy=last", "her.strategy must be one of 'future', 'final', 'episode', got 'last'"),
        ("seed=-1", "seed must be an integer >= 0, got -1"),
    ],
)
def test_a_bad_setting_is_named_where_it_is_declared(override, message):
    with pytest.raises(ValueError, match=message):
        schema.check(config([override]))


def test_a_trainer_is_built_and_trains_from_the_schema_without_hydra(tmp_path):
    """The schema is plain dataclasses: a notebook or a test builds a run's config without Hydra's composition."""
    from gchgg import train

    run = schema.RunConfig(
        env=schema.EnvConfig(name="reach", start="original", threshold=0.05, buffer_episodes=8, stop_threshold=1.0),
        algo=schema.AlgoConfig(name="her", goal_generator="none", metric="euclidean", sampler="ebp"),
        train=schema.TrainConfig(iterations=2, episodes=2, updates=3, batch_size=16, warmup_steps=0),
        eval=schema.EvalConfig(episodes=2), her=schema.HERConfig(k=1), agent=schema.AgentConfig(hidden=[16, 16]),
        logging=schema.LoggingConfig(progress=False), curriculum=None, cher=None,
    )  # fmt: skip
    rows = train.Trainer(OmegaConf.structured(run), tmp_path).train()
    assert [row["iteration"] for row in rows] == [0, 1] and (tmp_path / "metrics.csv").is_file()
