"""The training entry point: every algo on every task, exact resume, and bad configuration caught early."""

from __future__ import annotations

import csv
import logging
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException, MissingConfigException

from envs import TASKS
from gchgg import train
from gchgg.run import checkpoint, evaluator
from gchgg.run.parts import make_parts

CONF = str(Path(__file__).resolve().parents[1] / "conf")
ALGOS = ("her", "hgg", "ghgg", "cher", "gchgg", "gchgg_code")
DIAGNOSTICS = ("train_success_rate", "train_final_distance", "observation_clipped", "goal_clipped")
CURRICULUM = ("diversity", "proximity", "lambda_mean", "diversity_spread", "proximity_spread", "diversity_decided")


def expected_columns(task: str, algo: str) -> set[str]:
    """The metrics columns (besides timings) a run of ``algo`` on ``task`` writes."""
    columns = {"iteration", "success_rate", "env_steps", "warmup", "stopped", "loss_actor", "loss_value", *DIAGNOSTICS}
    columns |= {"pred_value", "target_value"}
    if task != "reach":
        columns |= {"object_off_table", "object_moved", "object_rose_2cm", "object_rose_10cm"}
    if algo in ("hgg", "ghgg", "gchgg", "gchgg_code"):
        columns.add("d_g")
    if algo in ("cher", "gchgg", "gchgg_code"):
        columns.add("lambda")
    if algo == "cher":
        columns |= {"diversity", "proximity", "lambda_mean"}  # CHER's greedy selection reports its scores too
    if algo.startswith("gchgg"):
        columns |= set(CURRICULUM)
    return columns


def tiny(tmp_path: Path, iterations: int = 1) -> list[str]:
    """Overrides for a run of seconds: 2 episodes, a few updates, a coarse graph cached under tmp_path."""
    return [
        f"train.iterations={iterations}",
        "train.episodes=2",
        "train.updates=3",
        "train.batch_size=16",
        "train.warmup_steps=0",
        "eval.episodes=2",
        "eval.background=false",  # auto would start an evaluator process per test where a core is free
        "buffer.episodes=8",
        "her.k=1",
        "graph.n=[11,11,5]",
        f"graph.cache_dir={tmp_path / 'graphs'}",
        "agent.hidden=[16,16]",
        "logging.progress=false",
        "logging.backend=csv",
    ]


TINY_CHER = "cher.pool_size=64"  # CHER's pool in a run of seconds (only algo=cher has a cher section)
EUCLIDEAN = ("algo=her", "algo=hgg", "algo=cher")  # algorithms without a graph section


def for_algo(overrides: list[str]) -> list[str]:
    """tiny()'s overrides fitted to the algorithm: :data:`TINY_CHER` for ``algo=cher`` (unless a pool is set),
    no ``graph.*`` for an algorithm without a graph metric."""
    if "algo=cher" in overrides and not any(o.startswith("cher.pool_size=") for o in overrides):
        overrides = [*overrides, TINY_CHER]
    if any(o in EUCLIDEAN for o in overrides) and not any(o.startswith(("algo.metric=", "graph=")) for o in overrides):
        overrides = [o for o in overrides if not o.startswith("graph.")]
    return overrides


def config(overrides: list[str]):
    """The composed config of ``overrides`` fitted to the algorithm (:func:`for_algo`)."""
    overrides = for_algo(overrides)
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose("config", overrides=overrides)


def read_metrics(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv") as f:
        return list(csv.DictReader(f))


@pytest.mark.parametrize("algo", ALGOS)
@pytest.mark.parametrize("task", TASKS)
def test_every_algo_runs_on_every_task_through_the_entry_point(task, algo, tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    argv = ["gchgg.train", *for_algo([f"env={task}", f"algo={algo}", *tiny(tmp_path, iterations=2)]),
            f"hydra.run.dir={run_dir}"]
    monkeypatch.setattr(sys, "argv", argv)
    train.main()
    rows = read_metrics(run_dir)
    assert [int(r["iteration"]) for r in rows] == [0, 1]
    steps = {"reach": 50}.get(task, 100)
    assert [int(r["env_steps"]) for r in rows] == [2 * steps, 4 * steps]
    for r in rows:
        assert 0.0 <= float(r["success_rate"]) <= 1.0
        assert {k for k in r if not k.startswith("seconds_")} == expected_columns(task, algo)
        for key, text in r.items():
            value = float(text)
            assert value == value and abs(value) != float("inf"), (key, value)  # finite, never NaN
        for key in ("train_success_rate", "observation_clipped", "goal_clipped", "object_off_table", "object_moved",
                    "object_rose_2cm", "object_rose_10cm", "diversity_decided"):
            assert key not in r or 0.0 <= float(r[key]) <= 1.0, (key, r[key])
    saved = (run_dir / "config.yaml").read_text()
    assert f"name: {task}" in saved and f"name: {algo}" in saved
    assert checkpoint.load(run_dir / "checkpoint.pt")["iteration"] == 2


@pytest.mark.parametrize("algo", ["her", "gchgg", "gchgg_code"])
def test_resumed_run_matches_uninterrupted_run(algo, tmp_path):
    base = ["env=reach", f"algo={algo}", *tiny(tmp_path)]
    whole, split = tmp_path / "whole", tmp_path / "split"
    train.run(config([*base, "train.iterations=3"]), whole)
    train.run(config([*base, "train.iterations=2"]), split)  # "killed" after iteration 1's checkpoint
    train.run(config([*base, "train.iterations=3", "resume=true"]), split)

    def results(run_dir):
        return [{k: v for k, v in row.items() if not k.startswith("seconds_")} for row in read_metrics(run_dir)]

    assert len(results(whole)) == 3
    assert results(split) == results(whole)


def test_run_killed_between_checkpoints_repeats_the_lost_iterations_identically(tmp_path, monkeypatch):
    base = ["env=reach", "algo=gchgg", *tiny(tmp_path), "checkpoint.every=2", "train.iterations=4"]
    whole, split = tmp_path / "whole", tmp_path / "split"
    train.run(config(base), whole)

    evaluate, calls = evaluator.evaluate, []

    def killed_in_the_fourth_iteration(*args):
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt
        return evaluate(*args)

    monkeypatch.setattr(evaluator, "evaluate", killed_in_the_fourth_iteration)
    with pytest.raises(KeyboardInterrupt):
        train.run(config(base), split)
    assert len(read_metrics(split)) == 3 and checkpoint.load(split / "checkpoint.pt")["iteration"] == 2
    monkeypatch.setattr(evaluator, "evaluate", evaluate)
    train.run(config([*base, "resume=true"]), split)

    def results(run_dir):
        return [{k: v for k, v in row.items() if not k.startswith("seconds_")} for row in read_metrics(run_dir)]

    assert results(split) == results(whole)


def test_existing_run_needs_resume(tmp_path):
    cfg = config(["env=reach", "algo=her", *tiny(tmp_path)])
    train.run(cfg, tmp_path / "run")
    with pytest.raises(FileExistsError, match="resume=true"):
        train.run(cfg, tmp_path / "run")


def test_a_requeued_slurm_job_resumes_by_itself(tmp_path, monkeypatch):
    train.run(config(["env=reach", "algo=her", *tiny(tmp_path)]), tmp_path / "run")
    monkeypatch.setenv("SLURM_RESTART_COUNT", "1")  # what SLURM sets in a requeued job
    rows = train.run(config(["env=reach", "algo=her", *tiny(tmp_path, iterations=2)]), tmp_path / "run")
    assert [row["iteration"] for row in rows] == [0, 1]


def test_corrupt_checkpoint_is_an_error_that_says_so(tmp_path):
    run_dir = tmp_path / "run"
    train.run(config(["env=reach", "algo=her", *tiny(tmp_path)]), run_dir)
    path = run_dir / "checkpoint.pt"
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(checkpoint.CorruptCheckpointError, match="corrupt"):
        train.run(config(["env=reach", "algo=her", *tiny(tmp_path, iterations=2), "resume=true"]), run_dir)


@pytest.mark.parametrize(
    "override, message",
    [
        ("train.episodes=0", "train.episodes must be an integer > 0, got 0"),
        ("train.batch_size=-5", "train.batch_size must be an integer > 0, got -5"),
        ("eval.episodes=0", "eval.episodes must be an integer > 0"),
        ("train.iterations=0", "train.iterations must be an integer > 0"),
        ("agent.actor_lr=0", "agent.actor_lr must be a number > 0"),
        ("agent.gamma=1.5", r"agent.gamma must be a number in \(0, 1\), got 1.5"),
        ("graph.n=[31,3,11]", "spacing"),
        ("graph.margin=-0.1", "margin"),
        ("matmul=mkl", "matmul must be one of 'auto', 'onednn', 'default', got 'mkl'"),
        ("gradients=manual", "gradients must be one of 'auto', 'fused', 'compiled', 'autograd', got 'manual'"),
        ("subnormals=off", "subnormals must be one of 'auto', 'flush', 'keep', got 'off'"),
    ],
)
def test_bad_configuration_fails_before_training_naming_the_setting(override, message, tmp_path):
    cfg = config(["env=push_new", "algo=gchgg", *tiny(tmp_path), override])
    with pytest.raises(ValueError, match=message):
        train.run(cfg, tmp_path / "run")
    assert not (tmp_path / "run" / "metrics.csv").exists()


def test_runs_with_the_update_by_hand_and_by_autograd_write_the_same_metrics(tmp_path, caplog):
    """``gradients`` is speed only: a tiny gchgg run writes the same metrics either way, and logs the path taken."""
    rows = {}
    for update in ("fused", "autograd"):
        overrides = ["env=push_new", "algo=gchgg", *tiny(tmp_path, iterations=2), "train.updates=8",
                     "matmul=default", "precision=float32", f"gradients={update}"]  # fmt: skip
        with caplog.at_level(logging.INFO, logger="gchgg.train"):
            train.run(config(overrides), tmp_path / update)
        rows[update] = [{k: v for k, v in row.items() if not k.startswith("seconds_")}
                        for row in read_metrics(tmp_path / update)]  # fmt: skip
        assert f"gradients: {update} -> {update}" in caplog.text
    assert rows["fused"] == rows["autograd"] and float(rows["fused"][-1]["loss_value"]) > 0


@pytest.mark.parametrize("override, choice", [("algo=sac", "gchgg"), ("env=fetch", "push_new")])
def test_unknown_env_or_algo_lists_the_choices(override, choice):
    with pytest.raises((MissingConfigException, ConfigCompositionException), match=choice):
        config([override])


def test_the_loop_switches_the_curriculum_off_when_hgg_reports_its_stop(tmp_path):
    """The goal generator only reports the stop (``stopped_now``); the loop switches GC-HGG's sampler."""
    import dataclasses

    trainer = train.Trainer(config(["env=reach", "algo=gchgg", *tiny(tmp_path, iterations=3)]), tmp_path / "run")
    generate, calls = trainer.goal_generator.generate, []

    def stops_at_the_second_call(*args, **kwargs):
        calls.append(None)
        return dataclasses.replace(generate(*args, **kwargs), stopped_now=len(calls) == 2)

    trainer.goal_generator.generate = stops_at_the_second_call
    trainer.iteration_step()
    assert trainer.sampler.num_candidates == trainer.cfg.curriculum.num_candidates > 1
    trainer.iteration_step()
    assert trainer.sampler.num_candidates == 1  # plain sampling from the reported stop on


@pytest.mark.parametrize("setting", ["flush", "keep"])
def test_the_subnormals_setting_reaches_the_agent(setting, tmp_path):
    cfg = config(["env=reach", "algo=her", *tiny(tmp_path), f"subnormals={setting}"])
    assert make_parts(cfg).agent.subnormals == setting
