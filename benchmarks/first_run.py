"""The README's first command timed from the user's side: seconds per iteration against the fp32 floor, and time to 0.9.

    python benchmarks/first_run.py [--iterations 12]            # steady state of the default command
    python benchmarks/first_run.py --until 0.9 --seeds 0 1 2    # wall-clock to a success rate of 0.9

It runs ``python -m gchgg.train env=push_new algo=gchgg`` as a user would (default settings: background
evaluation where a core is free, checkpoints, the run's summary) in a temporary run folder, and notes the
wall-clock time at which each row of its ``metrics.csv`` appears. A row is written once its evaluation is
back, so the times lag the iterations by a constant: their differences are the seconds per iteration of the
run's steady state (from the 5th row on, after the warm-up's 10,000 steps and the update's first compile).
The fp32 floor is ``benchmarks/iteration.py``'s: the same 5,000 raw dm_control steps plus 1,000 bare
float32 DDPG updates on torch's default matmul, measured before and after the run (the median of the two).
Run it alone on the machine: it measures the machine too.

With ``--until R`` each seed runs with ``train.stop_success=R`` and the wall-clock from the command's start
to the row whose success rate first reaches R is printed (what RUNS.md records for issue 70).
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]
os.environ.setdefault("MUJOCO_GL", "disable")


def fp32_floor() -> float:
    """Seconds of the fp32 floor of one push_new iteration (``benchmarks/iteration.py``'s), on one torch thread
    as the run's (``threads=1``)."""
    import torch
    from iteration import floor_seconds

    torch.set_num_threads(1)
    env_seconds, update_seconds = floor_seconds(50, 100, 1000, 256, "default")
    return env_seconds + update_seconds


def timed_run(overrides: list[str], run_dir: Path, poll: float = 0.25) -> tuple[list[float], list[dict], float]:
    """Runs the training command; returns when each metrics row appeared (seconds from the start), the rows,
    and the command's whole wall-clock."""
    command = [sys.executable, "-m", "gchgg.train", *overrides, f"hydra.run.dir={run_dir}", "logging.progress=false"]
    start = time.perf_counter()
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    appeared: list[float] = []
    rows: list[dict] = []
    metrics = run_dir / "metrics.csv"
    while True:
        done = process.poll() is not None
        if metrics.exists():
            with open(metrics, newline="") as f:
                rows = list(csv.DictReader(f))
            now = time.perf_counter() - start
            appeared += [now] * (len(rows) - len(appeared))
        if done:
            break
        time.sleep(poll)
    if process.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{process.stderr.read()[-3000:]}")
    return appeared, rows, time.perf_counter() - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=12, help="iterations of the steady-state run")
    parser.add_argument("--until", type=float, default=None, help="run each seed until this success rate")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--env", default="push_new")
    args = parser.parse_args(argv)
    base = [f"env={args.env}", "algo=gchgg"]
    if args.until is None:
        floors = [fp32_floor()]
        with tempfile.TemporaryDirectory() as tmp:
            appeared, _, wall = timed_run([*base, f"train.iterations={args.iterations}"], Path(tmp) / "run")
        floors.append(fp32_floor())
        steady = [b - a for a, b in zip(appeared[4:], appeared[5:], strict=False)]
        if not steady:
            raise SystemExit(f"--iterations {args.iterations}: too few rows for a steady state (at least 7)")
        floor, seconds = statistics.median(floors), statistics.median(steady)
        print(f"the first command (python -m gchgg.train {' '.join(base)}), {args.iterations} iterations: "
              f"{seconds:.2f} s/iteration in its steady state (median over iterations 5-{len(appeared) - 1}), "
              f"{wall:.0f} s in all")
        print(f"fp32 floor {floor:.2f} s (before {floors[0]:.2f}, after {floors[1]:.2f}); "
              f"first command / fp32 floor = {seconds / floor:.2f} (target <= 1.0)")
        return
    for seed in args.seeds:
        with tempfile.TemporaryDirectory() as tmp:
            appeared, rows, wall = timed_run([*base, f"seed={seed}", f"train.stop_success={args.until}"],
                                             Path(tmp) / "run")
        first = next((i for i, row in enumerate(rows) if float(row.get("success_rate") or "nan") >= args.until), None)
        reached = (f"first >= {args.until} at iteration {first}, {appeared[first] / 60:.1f} min after the start"
                   if first is not None else f"never >= {args.until} in {len(rows)} iterations")
        print(f"seed {seed}: {reached}; the whole run {wall / 60:.1f} min ({len(rows)} iterations)", flush=True)


if __name__ == "__main__":
    main()
