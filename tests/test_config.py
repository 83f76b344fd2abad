"""Structured configs (gchgg/run/config.py): each setting and its default declared once, each algorithm's config
holding only what it reads, a bad setting named."""

from __future__ import annotations

import inspect
import re
from dataclasses import fields
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf
from test_train import config

from gchgg.ddpg.agent import DDPGConfig
from gchgg.run import builders
from gchgg.run import config as schema

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


def test_the_schema_takes_the_parts_defaults_and_the_builders_declare_none():
    assert schema.CurriculumConfig().num_candidates == inspect.signature(
        schema.GraphCurriculumSampler).parameters["num_candidates"].default
    assert schema.HGGConfig().c == inspect.signature(schema.HGGGoalGenerator).parameters["c"].default
    assert schema.GraphConfig().n == list(inspect.signature(schema.GoalGraph).parameters["n"].default)
    agent = {f.name for f in fields(schema.AgentConfig)}
    assert agent == {f.name for f in fields(DDPGConfig)} | {"normalizer_source"}
    assert schema.AgentConfig().ddpg() == DDPGConfig()  # the same defaults
    # not settings: a mode switch (observation noise) and the task geometry a Euclidean metric has no use for
    allowed = {("make_relabel", "true_achieved_goal_key"), ("make_metric", "field"), ("make_metric", "obstacles")}
    for name, builder in inspect.getmembers(builders, inspect.isfunction):
        if name.startswith("make_"):
            for parameter in inspect.signature(builder).parameters.values():
                if parameter.default is not inspect.Parameter.empty:
                    assert (name, parameter.name) in allowed, f"{name}({parameter.name}=...) declares a default"


def test_the_discount_is_declared_once():
    """The issue's example: gamma = 0.98 was declared in config.yaml, twice in agent.py and in hgg.py."""
    found = [(path.relative_to(ROOT), line) for path in [*ROOT.glob("gchgg/**/*.py"), *ROOT.glob("conf/**/*.yaml")]
             for line in path.read_text().splitlines() if re.search(r"gamma\W[^(]*0\.98", line)]
    assert [str(path) for path, _ in found] == ["gchgg/ddpg/agent.py"], found


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
