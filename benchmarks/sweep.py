"""Wall-clock of one sweep with Hydra's basic launcher (jobs one after another) and with joblib (2 at once).

    python benchmarks/sweep.py [--iterations 5] [--algos her ghgg] [--seeds 0 1] [--jobs 2]

Runs ``python -m gchgg.train -m +experiment=fig5_reach`` reduced to ``--algos`` x ``--seeds`` and
``--iterations`` (the first 4 reach iterations are warm-up), once per launcher into a temporary
folder, and prints both wall-clock times and their ratio (target: joblib <= 0.6 x basic on 2 cores).
Needs ``pip install -e ".[cluster]"``; every job runs with one torch thread.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def sweep_seconds(launcher: list[str], folder: Path, args) -> float:
    command = [
        sys.executable, "-m", "gchgg.train", "-m", "+experiment=fig5_reach",
        f"algo={','.join(args.algos)}", f"seed={','.join(map(str, args.seeds))}",
        f"train.iterations={args.iterations}", "logging.progress=false", "logging.backend=csv",
        f"hydra.sweep.dir={folder}", *launcher,
    ]  # fmt: skip
    start = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT, env={**os.environ, "MUJOCO_GL": "disable"}, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"sweep failed ({' '.join(launcher) or 'basic'}):\n{done.stderr[-3000:]}")
    runs = list(folder.glob("*/metrics.csv"))
    if len(runs) != len(args.algos) * len(args.seeds):
        raise RuntimeError(f"expected {len(args.algos) * len(args.seeds)} runs under {folder}, found {len(runs)}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--algos", nargs="+", default=["her", "ghgg"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--jobs", type=int, default=2, help="joblib jobs at once")
    args = parser.parse_args()
    jobs = len(args.algos) * len(args.seeds)
    print(f"fig5_reach reduced to {jobs} jobs ({', '.join(args.algos)} x seeds {args.seeds}), "
          f"{args.iterations} iterations each")
    with tempfile.TemporaryDirectory() as tmp:
        basic = sweep_seconds([], Path(tmp) / "basic", args)
        print(f"basic launcher:           {basic:7.1f} s", flush=True)
        parallel = sweep_seconds(["hydra/launcher=joblib", f"hydra.launcher.n_jobs={args.jobs}"],
                                 Path(tmp) / "joblib", args)
        print(f"joblib, {args.jobs} jobs at once: {parallel:7.1f} s")
    print(f"joblib / basic = {parallel / basic:.2f} (target <= 0.6)")


if __name__ == "__main__":
    from report import run  # prints, and with --docs writes docs/benchmarks.md

    run(main, __file__)
