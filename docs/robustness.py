"""Success of trained policies under observation noise: the README's robustness table.

    python docs/robustness.py LABEL=RUN_DIR ... [--sigmas 0 0.005 0.01 0.02] [--episodes 100] [--seed 0]

Each run's ``policy.pt`` is evaluated with ``gchgg.analysis.evaluate`` (deterministic episodes on target
goals, the same episodes for every σ and run) with N(0, σ²) noise on the observed object position
(the grip in reach), and a Markdown table of success rates is printed: one row per run, one
column per σ.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("MUJOCO_GL", "disable")
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")


def main() -> None:
    from gchgg.analysis.evaluate import evaluate_policy, load_policy_file
    from gchgg.ddpg.agent import load_policy

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="LABEL=RUN_DIR pairs")
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.0, 0.005, 0.01, 0.02])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print("| policy | task | trained with σ | iteration | " + " | ".join(f"σ = {s:g} m" for s in args.sigmas) + " |")
    print("|---|---|---|---|" + "---|" * len(args.sigmas))
    for item in args.runs:
        label, _, run_dir = item.partition("=")
        saved = load_policy_file(run_dir)
        actor = load_policy(saved["policy"])
        trained = saved["config"].get("noise", {}).get("object_std", 0.0)
        start = saved["config"].get("env", {}).get("start", "original")
        rates = [
            evaluate_policy(actor, saved["task"], args.episodes, args.seed, saved["threshold"], noise_std=s,
                            start=start).success_rate
            for s in args.sigmas
        ]
        print(f"| {label} | {saved['task']} | {trained:g} | {saved['iteration'] - 1} | "
              + " | ".join(f"{r:.2f}" for r in rates) + " |", flush=True)


if __name__ == "__main__":
    main()
