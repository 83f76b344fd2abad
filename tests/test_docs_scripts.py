"""The scripts behind docs/results' diagnostics run on a run folder of today's trainer and print their tables."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from test_train import for_algo, tiny

from gchgg import train

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A tiny GC-HGG run and a tiny G-HGG run (no curriculum section), 3 iterations each, with their replay files."""
    root = tmp_path_factory.mktemp("runs")
    folders = {}
    for algo in ("gchgg", "ghgg"):
        folders[algo] = root / algo
        argv = ["gchgg.train", *for_algo(["env=push_new", f"algo={algo}", *tiny(root, iterations=3)]),
                f"hydra.run.dir={folders[algo]}"]
        saved, sys.argv = sys.argv, argv
        try:
            train.main()
        finally:
            sys.argv = saved
    return folders


def script(name: str, *args) -> str:
    done = subprocess.run([sys.executable, str(REPO / "docs" / name), *map(str, args)], capture_output=True, text=True,
                          cwd=REPO, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


@pytest.mark.parametrize("algo", ["gchgg", "ghgg"])
def test_curriculum_choice_compares_the_samplers_on_any_runs_buffer(runs, algo, tmp_path):
    out = script("curriculum_choice.py", runs[algo], "--iterations", 2, "--samples", 2, "--tradeoff", 1.0,
                 "--out", tmp_path / "choice.md")
    assert "| 2 | 1 | goal to target |" in out and (tmp_path / "choice.md").read_text().strip() == out.strip()


def test_fig6_settings_prints_each_settings_lambda_and_share(runs):
    out = script("fig6_settings.py", runs["gchgg"], "--iteration", 2, "--samples", 2)
    for setting in ("| eta | 500 |", "| sigma | 0.37 |", "| tradeoff | exponential |", "| metric | euclidean |"):
        assert setting in out


def test_iteration_rounds_pools_the_committed_runs_and_refuses_other_files(tmp_path):
    """docs/iteration_rounds.py reads each run's rounds from benchmarks/iteration.py's output and pools them."""
    out = script("iteration_rounds.py")
    assert "4221258.txt: median 1.01 of 5 rounds (1.01, 0.99, 0.99, 1.01, 1.01)" in out
    assert "pooled: everything on / fp32 floor = 1.01 [" in out and "median of 15 rounds of 3 runs" in out
    other = tmp_path / "other.txt"
    other.write_text("floor: 8.00 s\n")
    done = subprocess.run([sys.executable, str(REPO / "docs" / "iteration_rounds.py"), str(other)],
                          capture_output=True, text=True, cwd=REPO, timeout=60)
    assert done.returncode != 0 and "no 'everything on / fp32 floor' line" in done.stderr
