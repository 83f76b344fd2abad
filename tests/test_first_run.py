"""The newcomer's first run: evaluation in the background where a core is free, and a summary of what the run made."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import pytest
from test_train import config, tiny

from gchgg import train
from gchgg.run import evaluator
from gchgg.run.evaluator import resolve_background
from gchgg.run.summary import summary


@pytest.mark.parametrize("cpus, load, threads, background", [
    (2, 0.0, 1, True),    # a 2-core machine, alone: the evaluator takes the second core
    (2, 0.4, 1, True),    # a little background load rounds away
    (2, 1.0, 1, False),   # another run holds the second core
    (2, 0.0, 2, False),   # the run's own threads take both
    (1, 0.0, 1, False),   # a SLURM job of one CPU
    (16, 3.0, 4, True),
])
def test_auto_evaluates_in_the_background_only_where_a_core_is_free(cpus, load, threads, background):
    chosen, why = resolve_background("auto", threads, cpus=cpus, load=load)
    assert chosen is background
    assert why.startswith(f"auto -> {str(background).lower()}: {cpus} CPU")


@pytest.mark.parametrize("setting", [True, False])
def test_a_set_value_is_kept_whatever_the_machine(setting):
    assert resolve_background(setting, 1, cpus=64, load=0.0 if not setting else 99.0)[0] is setting


def test_pending_evaluations_of_a_checkpoint_turn_auto_on_and_refuse_false():
    evaluations = evaluator.Evaluations.__new__(evaluator.Evaluations)
    evaluations.load_state_dict({"eval_pending": [(3, {"policy": 1})]})
    assert evaluations.require_background(False, "auto") is True
    assert evaluations.require_background(True, True) is True
    with pytest.raises(ValueError, match=r"evaluations of iterations \[3\] in flight.*eval.background=true or auto"):
        evaluations.require_background(False, False)
    evaluations.load_state_dict({})
    assert evaluations.require_background(False, "auto") is False


def test_a_bad_setting_is_refused_by_name(tmp_path):
    with pytest.raises(ValueError, match="eval.background must be one of 'auto', True, False, got 'sometimes'"):
        train.run(config(["env=reach", "algo=her", *tiny(tmp_path), "eval.background=sometimes"]), tmp_path / "run")


def test_the_run_logs_its_choice_and_ends_with_a_summary(tmp_path, capsys, caplog, monkeypatch):
    monkeypatch.setattr(evaluator, "resolve_background", lambda setting, threads: (False, "auto -> false: test"))
    monkeypatch.setattr(train, "resolve_background", evaluator.resolve_background)
    run_dir = tmp_path / "run"
    with caplog.at_level(logging.INFO, logger="gchgg.train"):
        history = train.run(config(["env=reach", "algo=her", *tiny(tmp_path, iterations=2), "eval.background=auto"]),
                            run_dir, ["env=reach", "algo=her", "train.iterations=2"])
    assert "eval.background: auto -> false: test" in caplog.text
    out = capsys.readouterr().out.splitlines()
    start = next(i for i, line in enumerate(out) if line.startswith("trained 2 iterations in "))
    final = history[-1]["success_rate"]
    assert out[start + 1].startswith(f"success rate: final {final:.2f}, best ")
    assert out[start + 2] == f"run folder: {run_dir} (metrics.csv, checkpoint.pt, policy.pt, config.yaml)"
    assert out[start + 6] == (f"  resume:   python -m gchgg.train env=reach algo=her resume=true "
                              f"hydra.run.dir={run_dir} train.iterations=<more>")
    for line in out[start + 3:start + 6]:  # plot, evaluate, export: commands that exist
        module = line.split("python -m ")[1].split()[0]
        assert module in ("gchgg.analysis.plot", "gchgg.analysis.evaluate", "gchgg.analysis.export")


def test_the_summary_of_an_interrupted_run_names_its_last_checkpoint():
    rows = [{"iteration": 0, "success_rate": 0.95}, {"iteration": 1}]  # the second evaluation in flight
    text = summary(rows, Path("runs/x"), 3725, interrupted=True, saved_at=1).splitlines()
    assert text[0] == "interrupted after 2 iterations in 1 h 02 min; its last checkpoint holds 1 iterations"
    assert text[1] == "success rate: final 0.95, best 0.95 (iteration 0), first >= 0.9 at iteration 0"
    assert text[-1].endswith("resume=true hydra.run.dir=runs/x")
    assert summary(rows, Path("r"), 1, resumed_at=1).startswith("trained iterations 1–1 (2 in all) in 0 min 01 s")
    assert "never >= 0.9" in summary([{"iteration": 0, "success_rate": math.nan}, {"iteration": 1,
                                      "success_rate": 0.5}], Path("r"), 1).splitlines()[1]
