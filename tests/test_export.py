"""Exported policies: parity with the agent in both formats, metadata, and the standalone runner."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from test_train import config, tiny

import envs
from gchgg import train
from gchgg.analysis import export
from gchgg.analysis.evaluate import evaluate_policy, load_policy_file
from gchgg.ddpg.agent import load_policy

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """The run folder of a small agent (16 x 16) trained for 2 tiny iterations on push_new."""
    tmp = tmp_path_factory.mktemp("export")
    run_dir = tmp / "run"
    train.run(config(["env=push_new", "algo=her", *tiny(tmp, iterations=2), "train.updates=20"]), run_dir)
    return run_dir


def recorded_pairs(task: str, actor, n: int = 1000) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` (observation, goal) pairs the policy met in rollouts of the task (10 envs x 100 steps)."""
    from gchgg.run.rollout import collect

    env = envs.make(task, num_envs=10, seed=11)
    with torch.inference_mode():
        rollout = collect(env, actor, 100, env.reset())
    return (rollout["observation"].reshape(-1, env.obs_dim)[:n].clone(),
            rollout["desired_goal"].reshape(-1, 3)[:n].clone())


@pytest.mark.parametrize("fmt", export.FORMATS)
def test_exported_actions_equal_the_agents(fmt, trained, tmp_path):
    if fmt == "onnx":
        ort = pytest.importorskip("onnxruntime", reason='needs pip install -e ".[export]"')
    saved = load_policy_file(trained)
    actor = load_policy(saved["policy"])
    observation, goal = recorded_pairs("push_new", actor)
    assert observation.shape == (1000, 25)
    with torch.no_grad():
        expected = actor(observation, goal).numpy()
    path = export.export(trained, fmt, tmp_path / f"policy.{'onnx' if fmt == 'onnx' else 'pt'}")
    if fmt == "onnx":
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        got = session.run(None, {"observation": observation.numpy(), "goal": goal.numpy()})[0]
    else:
        with torch.no_grad():
            got = torch.jit.load(str(path))(observation, goal).numpy()
    assert np.abs(got - expected).max() <= 1e-5
    assert np.abs(expected).max() <= 1.0
    meta = json.loads(Path(f"{path}.json").read_text())
    assert meta["task"] == "push_new" and meta["control_rate_hz"] == 20 and meta["action_scale_m_per_unit"] == 0.05
    assert meta["observation_layout"]["object_position"] == [3, 6] and meta["inputs"]["observation"] == [None, 25]
    assert meta["checkpoint"]["iteration"] == 1


def test_export_refuses_a_run_without_a_policy(tmp_path):
    with pytest.raises(FileNotFoundError, match="no policy at"):
        export.export(tmp_path, "torchscript", tmp_path / "x.pt")
    with pytest.raises(ValueError, match="format must be one of"):
        export.export(tmp_path, "tflite", tmp_path / "x.tflite")


def test_runner_reproduces_evaluate_without_importing_gchgg(trained, tmp_path):
    pytest.importorskip("onnxruntime", reason='needs pip install -e ".[export]"')
    path = export.export(trained, "onnx", tmp_path / "policy.onnx")
    probe = (
        "import runpy, sys; sys.argv = ['run_policy.py', sys.argv[1], '--episodes', '20', '--seed', '3'];"
        f"runpy.run_path({str(ROOT / 'examples' / 'run_policy.py')!r}, run_name='__main__');"
        "print('gchgg modules:', sorted(m for m in sys.modules if m.split('.')[0] == 'gchgg'))"
    )
    done = subprocess.run([sys.executable, "-c", probe, str(path)], cwd=tmp_path, capture_output=True, text=True,
                          env={**os.environ, "MUJOCO_GL": "disable"}, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "gchgg modules: []" in done.stdout
    rate = float(done.stdout.split("success rate ")[1].split()[0])
    saved = load_policy_file(trained)
    reference = evaluate_policy(load_policy(saved["policy"]), "push_new", episodes=20, seed=3,
                                threshold=saved["threshold"])
    assert abs(rate - reference.success_rate) <= 0.02
