"""A training run killed with SIGKILL at any moment resumes to the metrics of a run never killed.

Each case starts a tiny run in a subprocess that kills itself (SIGKILL: no cleanup, no exception
handler runs) at a chosen call, then resumes it in this process and compares ``metrics.csv`` with an
uninterrupted run of the same settings (timing columns aside). The settings have a warm-up, an HGG
stop that fires, and a replay buffer that wraps before the kill.
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from test_train import config, tiny  # noqa: E402

from gchgg import train  # noqa: E402
from gchgg.fast.linear import onednn_available, resolve_precision  # noqa: E402
from gchgg.run import checkpoint  # noqa: E402

ITERATIONS = 8


def overrides(tmp_path: Path) -> list[str]:
    return [
        "env=reach", "algo=gchgg", *tiny(tmp_path, iterations=ITERATIONS),
        "train.warmup_steps=200",  # two iterations of 2 x 50 steps
        "buffer.episodes=6",  # wraps after iteration 2
        "env.stop_threshold=0.5",  # HGG's stop fires within the run
    ]  # fmt: skip


# Runs the trainer in a child process and SIGKILLs it at the n-th call of a function.
CHILD = """
import os, signal, sys
sys.path.insert(0, {tests!r})
from pathlib import Path
from test_train import config
from gchgg import train
from gchgg.ddpg import agent
from gchgg.common import files
where, n, run_dir, overrides = sys.argv[1], int(sys.argv[2]), Path(sys.argv[3]), sys.argv[4:]
calls = [0]

def killing(original):
    def wrapper(*args, **kwargs):
        calls[0] += 1
        if calls[0] == n:
            os.kill(os.getpid(), signal.SIGKILL)
        return original(*args, **kwargs)
    return wrapper

if where == "update":  # inside an iteration, between two DDPG updates
    agent.DDPGAgent.update = killing(agent.DDPGAgent.update)
elif where == "rename":  # inside a checkpoint: a file written, not yet renamed into place
    class Os:
        def __getattr__(self, name):
            return getattr(os, name)
    proxy = Os()
    proxy.replace = killing(os.replace)
    files.os = proxy  # the atomic writer's rename (gchgg.common.files)
train.run(config(overrides), run_dir)
"""


def metrics(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return [{k: v for k, v in row.items() if not k.startswith("seconds_")} for row in csv.DictReader(f)]


def kill_and_resume(tmp_path: Path, where: str, n: int, extra: tuple[str, ...] = ()) -> Path:
    run_dir = tmp_path / f"killed-{where}-{n}-{len(extra)}"
    child = CHILD.format(tests=str(ROOT / "tests"))
    env = dict(os.environ, MUJOCO_GL="disable", RL_LOGGING_LEVEL="WARNING")
    result = subprocess.run([sys.executable, "-c", child, where, str(n), str(run_dir), *overrides(tmp_path), *extra],
                            env=env, capture_output=True, text=True, timeout=600)  # fmt: skip
    assert result.returncode == -9, result.stderr[-2000:]  # killed by SIGKILL, not finished or failed
    train.run(config([*overrides(tmp_path), *extra, "resume=true"]), run_dir)
    return run_dir


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("whole")
    run_dir = tmp_path / "whole"
    history = train.run(config(overrides(tmp_path)), run_dir)
    assert any(row["stopped"] for row in history[:-1]) and not history[0]["stopped"]  # the stop fired mid-run
    assert history[0]["warmup"] and not history[-1]["warmup"]
    return metrics(run_dir), tmp_path


@pytest.mark.parametrize(
    ("where", "n"),
    [
        ("update", 7),  # during iteration 4 (3 updates per iteration after the 2 warm-up iterations)
        ("rename", 14),  # iteration 4's checkpoint.pt written to its temporary file, not renamed
        ("rename", 13),  # iteration 4's replay file written, the checkpoint not
        ("rename", 18),  # iteration 5's policy.pt: the checkpoint is in place
    ],
)
def test_a_run_killed_anywhere_resumes_to_identical_metrics(uninterrupted, tmp_path, where, n):
    whole, graphs = uninterrupted
    # the same graph cache as the uninterrupted run: tiny() names it after its tmp_path
    resumed = kill_and_resume(graphs, where, n)
    assert metrics(resumed) == whole
    assert not list(resumed.glob(".*.tmp")) and not list((resumed / "replay").glob(".*.tmp"))


def test_background_evaluation_gives_the_metrics_of_inline_evaluation(uninterrupted):
    whole, graphs = uninterrupted
    run_dir = graphs / "background"
    train.run(config([*overrides(graphs), "eval.background=true"]), run_dir)
    assert metrics(run_dir) == whole


def test_a_run_with_background_evaluation_killed_with_one_in_flight_resumes_identically(uninterrupted):
    whole, graphs = uninterrupted
    # killed in iteration 4: iteration 3's evaluation may still be running, its row not yet written
    resumed = kill_and_resume(graphs, "update", 8, ("eval.background=true",))
    assert metrics(resumed) == whole


@pytest.mark.parametrize("background", ["false", "true"])
def test_an_early_stop_fires_at_the_same_iteration_with_background_evaluation(tmp_path, background):
    stop = ["train.stop_success=0.0", "train.stop_patience=3", "eval.noise_std=0.01"]  # fires after 3 evaluations
    inline = train.run(config([*overrides(tmp_path), *stop]), tmp_path / "inline")
    rows = train.run(config([*overrides(tmp_path), *stop, f"eval.background={background}", "eval.every=1"]),
                     tmp_path / f"run-{background}")  # fmt: skip
    assert len(inline) == 3
    assert metrics(tmp_path / f"run-{background}") == metrics(tmp_path / "inline") and len(rows) == 3


def test_eval_every_evaluates_every_kth_iteration_and_the_last(tmp_path):
    rows = train.run(config([*overrides(tmp_path), "train.iterations=5", "eval.every=2"]), tmp_path / "run")
    assert ["success_rate" in row for row in rows] == [False, True, False, True, True]


def test_a_missing_or_truncated_replay_file_is_named_and_never_used(tmp_path):
    run_dir = tmp_path / "run"
    train.run(config(overrides(tmp_path)[:-1] + ["train.iterations=3"]), run_dir)  # noqa: RUF005
    listed = checkpoint.load(run_dir / "checkpoint.pt")["replay"]
    path = run_dir / "replay" / listed[-1]
    data = path.read_bytes()
    path.write_bytes(data[:-50])
    with pytest.raises(checkpoint.CorruptCheckpointError, match=listed[-1]):
        train.run(config(overrides(tmp_path)[:-1] + ["train.iterations=4", "resume=true"]), run_dir)  # noqa: RUF005
    path.unlink()
    with pytest.raises(FileNotFoundError, match=f"replay file .*{listed[-1]} is missing"):
        train.run(config(overrides(tmp_path)[:-1] + ["train.iterations=4", "resume=true"]), run_dir)  # noqa: RUF005


@pytest.mark.parametrize(("override", "named"), [("seed=1", "seed"), ("algo=ghgg", "algo"), ("env=push_new", "env")])
def test_resuming_another_runs_checkpoint_is_refused_naming_the_difference(tmp_path, override, named):
    run_dir = tmp_path / "run"
    base = ["env=reach", "algo=gchgg", *tiny(tmp_path)]
    train.run(config(base), run_dir)
    with pytest.raises(ValueError, match=f"another run .*{named}: checkpoint"):
        train.run(config([*base, override, "train.iterations=2", "resume=true"]), run_dir)


@pytest.mark.skipif(resolve_precision("auto") == "float32", reason="precision=auto is float32 on this machine")
def test_a_run_keeps_its_precision_when_resumed(tmp_path):
    """precision=auto resolves by machine: a float32 run resumed under the bfloat16 default is refused, and
    a checkpoint from before the precision was recorded counts as float32."""
    run_dir = tmp_path / "run"
    base = ["env=reach", "algo=her", *tiny(tmp_path), "precision=float32"]
    train.run(config(base), run_dir)
    with pytest.raises(ValueError, match="another run .*precision: checkpoint 'float32', this run 'bfloat16'"):
        train.run(config([*base[:-1], "train.iterations=2", "resume=true"]), run_dir)
    state = checkpoint.load(run_dir / "checkpoint.pt")
    del state["run"]["precision"]  # as written before 2026-12-04
    checkpoint.save(state, run_dir / "checkpoint.pt")
    train.run(config([*base, "train.iterations=2", "resume=true"]), run_dir)
    assert checkpoint.load(run_dir / "checkpoint.pt")["run"]["precision"] == "float32"


ONEDNN = ("agent.hidden=[64,64]", "train.batch_size=64", "eval.episodes=64", "matmul=onednn")  # oneDNN engaged


@pytest.mark.skipif(not onednn_available(), reason="this torch build has no oneDNN linear")
def test_with_onednn_layers_a_killed_run_resumes_identically_and_background_evaluation_matches(tmp_path):
    """The same guarantees with layers and batches wide enough for oneDNN (gchgg.fast.linear), in the
    updates, HGG's values and the 64-episode evaluations alike."""
    whole_dir = tmp_path / "whole"
    train.run(config([*overrides(tmp_path), *ONEDNN]), whole_dir)
    whole = metrics(whole_dir)
    assert kill_and_resume(tmp_path, "update", 7, ONEDNN).exists()
    assert metrics(tmp_path / f"killed-update-7-{len(ONEDNN)}") == whole
    train.run(config([*overrides(tmp_path), *ONEDNN, "eval.background=true"]), tmp_path / "background")
    assert metrics(tmp_path / "background") == whole
