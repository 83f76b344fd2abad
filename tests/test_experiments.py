"""Paper experiments as configs, sweeps through a cluster launcher, and evaluating / recording a trained policy."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from test_train import CONF, config, tiny

from gchgg import train

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml"))


def test_there_is_one_experiment_per_paper_figure_panel():
    assert EXPERIMENTS == [
        "fig5_pick_no_obstacle", "fig5_pick_obstacle", "fig5_push_new", "fig5_reach",
        "fig6_eta", "fig6_metric", "fig6_sigma", "fig6_tradeoff",
    ]  # fmt: skip


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_composes_into_its_sweep(name):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("config", overrides=[f"+experiment={name}"], return_hydra_config=True)
    params = dict(cfg.hydra.sweeper.params)
    assert params["seed"] == "0,1,2" and cfg.resume is True
    assert cfg.hydra.sweep.dir == f"multirun/{name}"
    if name.startswith("fig5_"):
        assert cfg.env.name == name[len("fig5_") :]
        assert params["algo"] == "her,hgg,ghgg,cher,gchgg"
    else:
        assert cfg.env.name == "pick_no_obstacle" and cfg.algo.name == "gchgg" and cfg.train.iterations == 200
        assert len(params) == 2  # the ablated setting and the seeds


def sweep(tmp_path: Path, iterations: int) -> subprocess.CompletedProcess:
    overrides = [o for o in tiny(tmp_path, iterations) if not o.startswith("graph.")]
    command = [sys.executable, "-m", "gchgg.train", "-m", "env=reach", "algo=her", "seed=0,1", "resume=true",
               "hydra/launcher=submitit_local", f"hydra.sweep.dir={tmp_path / 'sweep'}", *overrides]
    env = {**os.environ, "MUJOCO_GL": "disable"}
    return subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)


def test_a_sweep_runs_its_jobs_through_submitit_and_a_rerun_resumes_them(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason='needs pip install -e ".[cluster]"')
    done = sweep(tmp_path, iterations=1)
    assert done.returncode == 0, done.stderr[-2000:]
    runs = sorted((tmp_path / "sweep").glob("reach/her/*/metrics.csv"))
    assert [("seed=0" in str(p), "seed=1" in str(p)) for p in runs] == [(True, False), (False, True)]
    first = [list(csv.DictReader(open(p))) for p in runs]
    assert all(len(rows) == 1 for rows in first)
    # A re-launched (or requeued) job finds its checkpoint and continues.
    done = sweep(tmp_path, iterations=2)
    assert done.returncode == 0, done.stderr[-2000:]
    for path, before in zip(runs, first, strict=True):
        rows = list(csv.DictReader(open(path)))
        assert [r["iteration"] for r in rows] == ["0", "1"]
        assert rows[0]["success_rate"] == before[0]["success_rate"]


def test_evaluate_prints_the_success_rate_and_records_a_gif(tmp_path):
    iio = pytest.importorskip("imageio.v3", reason='needs pip install -e ".[video]"')
    run_dir = tmp_path / "run"
    train.run(config(["env=push_new", "algo=her", *tiny(tmp_path)]), run_dir)
    saved = (run_dir / "checkpoint.pt").stat().st_size + sum(p.stat().st_size for p in (run_dir / "replay").iterdir())
    assert (run_dir / "policy.pt").stat().st_size < saved / 10  # evaluation reads the small file only
    video = tmp_path / "push.gif"
    command = [sys.executable, "-m", "gchgg.analysis.evaluate", str(run_dir), "--episodes", "3", "--video", str(video),
               "--video-episodes", "1", "--camera", "top"]
    done = subprocess.run(command, env={**os.environ, "MUJOCO_GL": "egl"}, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "push_new: success rate" in done.stdout and "over 3 episodes" in done.stdout
    frames = iio.imread(video)
    assert frames.shape[0] == 101  # the reset and 100 steps
    assert frames.shape[1:] == (240, 320, 3)
    assert (frames[0] != frames[-1]).any()  # the arm moved


def test_evaluate_without_a_policy_or_a_renderer_says_what_to_do(tmp_path):
    from gchgg.analysis.evaluate import load_policy_file

    with pytest.raises(FileNotFoundError, match="no policy at"):
        load_policy_file(tmp_path)
    run_dir = tmp_path / "run"
    train.run(config(["env=reach", "algo=her", *tiny(tmp_path)]), run_dir)
    command = [sys.executable, "-m", "gchgg.analysis.evaluate", str(run_dir), "--episodes", "1",
               "--video", str(tmp_path / "v.gif")]
    done = subprocess.run(command, env={**os.environ, "MUJOCO_GL": "disable"}, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode != 0 and "MUJOCO_GL" in done.stderr
