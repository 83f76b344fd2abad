"""Per-step latency of an exported policy on one observation, one core: ONNX (onnxruntime) and TorchScript.

    python benchmarks/export_latency.py [RUN_DIR] [--task push_new] [--calls 2000]

Exports RUN_DIR's policy (or, without one, a freshly initialised agent of the paper's size, 3 x 256,
for ``--task``: latency does not depend on the weights) in both formats, then times ``--calls``
single-observation calls of each (after 100 warm-up calls) with one thread, and prints the median,
the 99th percentile and the median as a share of the 50 ms control period (target <= 1 ms, 2 %).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("MUJOCO_GL", "disable")

import numpy as np  # noqa: E402
import torch  # noqa: E402


def fresh_run(task: str, folder: Path) -> Path:
    """A folder with the ``policy.pt`` of an untrained agent of the default size for ``task``."""
    import envs
    from gchgg.ddpg.agent import DDPGAgent
    from gchgg.run import checkpoint

    env = envs.make(task, num_envs=1, seed=0)
    agent = DDPGAgent(env.obs_dim, 3, env.action_dim, generator=torch.Generator().manual_seed(0))
    state = {"iteration": 0, "task": task, "threshold": 0.05, "config": {}, "policy": agent.policy_state()}
    checkpoint.save(state, folder / "policy.pt")
    return folder


def timed(act, observation, goal, calls: int) -> np.ndarray:
    for _ in range(100):
        act(observation, goal)
    out = np.empty(calls)
    for i in range(calls):
        start = time.perf_counter()
        act(observation, goal)
        out[i] = time.perf_counter() - start
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", nargs="?", help="a training run folder (default: an untrained agent)")
    parser.add_argument("--task", default="push_new")
    parser.add_argument("--calls", type=int, default=2000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    sys.path.insert(0, str(ROOT / "examples"))
    from run_policy import load_policy

    from gchgg.analysis.export import export

    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(args.run_dir) if args.run_dir else fresh_run(args.task, Path(tmp))
        rng = np.random.default_rng(0)
        for fmt, suffix in (("onnx", ".onnx"), ("torchscript", ".pt")):
            path = export(run_dir, fmt, Path(tmp) / f"policy{suffix}")
            act = load_policy(path)
            obs_dim = int(__import__("json").loads(Path(f"{path}.json").read_text())["inputs"]["observation"][1])
            observation = rng.standard_normal((1, obs_dim)).astype(np.float32)
            goal = rng.standard_normal((1, 3)).astype(np.float32)
            seconds = timed(act, observation, goal, args.calls)
            median = float(np.median(seconds))
            print(f"{fmt:12s} median {median * 1e3:.3f} ms, p99 {np.percentile(seconds, 99) * 1e3:.3f} ms per step "
                  f"({100 * median / 0.05:.2f} % of the 50 ms period; target <= 1 ms)")


if __name__ == "__main__":
    from report import run  # prints, and with --docs writes docs/benchmarks.md

    run(main, __file__)
