"""Drive a KUKA task with an exported policy, the way a robot controller would: no gchgg, TorchRL or Hydra.

    python examples/run_policy.py push_new.onnx [--episodes 100] [--seed 0]

Loads the file written by ``python -m gchgg.analysis.export`` (ONNX through onnxruntime, or TorchScript
through plain torch) and its metadata (``FILE.json``: task, observation layout, action scale,
control rate), then runs a minimal observation -> action loop at the policy's control rate for
``--episodes`` episodes. The simulated task from ``envs`` (dm_control) stands in for the robot:
episode ``j`` uses task seed ``envs.episode_seeds(seed, episodes)[j]``, the same episodes
``python -m gchgg.analysis.evaluate RUN --episodes N --seed S`` runs, so the two success rates can be compared.
Prints the success rate (``is_success`` at the last step) and the policy's median latency per step.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # envs/, when run from a checkout
os.environ.setdefault("MUJOCO_GL", "disable")


def load_policy(path: Path):
    """``act(observation [1, obs_dim], goal [1, 3]) -> action [1, A]`` (float32 numpy) from the exported file."""
    if path.suffix == ".onnx":
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = 1  # one core: a controller's budget
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        return lambda observation, goal: session.run(None, {"observation": observation, "goal": goal})[0]
    import torch

    torch.set_num_threads(1)
    module = torch.jit.load(str(path)).eval()

    def act(observation, goal):
        with torch.no_grad():
            return module(torch.from_numpy(observation), torch.from_numpy(goal)).numpy()

    return act


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policy", type=Path,
                        help="an exported .onnx or TorchScript .pt file (with FILE.json beside it)")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    meta = json.loads(Path(f"{args.policy}.json").read_text())
    act = load_policy(args.policy)

    import envs  # the simulated robot

    task = meta["task"]
    env = envs.load(task, seed=0, threshold=meta["success_threshold_m"])
    successes, latencies = [], []
    for seed in envs.episode_seeds(args.seed, args.episodes):
        env.task.random.seed(seed)  # this episode's goal and object, as gchgg.analysis.evaluate draws them
        time_step = env.reset()
        while not time_step.last():
            observation = time_step.observation["observation"].astype(np.float32)[None]
            goal = time_step.observation["desired_goal"].astype(np.float32)[None]
            start = time.perf_counter()
            action = act(observation, goal)[0]
            latencies.append(time.perf_counter() - start)
            time_step = env.step(np.clip(action, -1.0, 1.0))
        successes.append(bool(time_step.observation["is_success"][0]))
    rate = float(np.mean(successes))
    period = 1.0 / meta["control_rate_hz"]
    latency = float(np.median(latencies))
    print(f"{task}: success rate {rate:.3f} over {args.episodes} episodes (seed {args.seed}); policy latency "
          f"{latency * 1e3:.3f} ms per step (median), {100 * latency / period:.2f} % of the "
          f"{period * 1e3:.0f} ms period")


if __name__ == "__main__":
    main()
