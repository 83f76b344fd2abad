"""Seconds per training iteration of two checkouts, in alternating rounds: ``python benchmarks/ab_iteration.py A B``.

A refactor should not slow an iteration. Each round builds one trainer per checkout, in a fresh
process of its own (so each imports its own ``gchgg``), runs one untimed iteration and then
``--iterations`` timed ``Trainer.iteration_step`` calls with the training defaults at the sizes of a
real push_new GC-HGG iteration (50 episodes in 50 chunks, 1,000 updates of 256); evaluation and
checkpoints are left out. The checkouts alternate round by round, so a change of the machine's load
hits both, and the ratio B / A of each round's medians is printed with its median over the rounds
and a bootstrap interval over them.

    git worktree add /tmp/before <commit>
    python benchmarks/ab_iteration.py /tmp/before . [--rounds 3] [--iterations 2] [--algo gchgg]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CHILD = r"""
import json, os, sys, tempfile, time
from pathlib import Path
sys.path.insert(0, os.getcwd())
os.environ.setdefault("MUJOCO_GL", "disable")
import torch
torch.set_num_threads(1)
from hydra import compose, initialize_config_dir
from gchgg.train import CONF_DIR, Trainer
algo, iterations = sys.argv[1], int(sys.argv[2])
with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
    cfg = compose("config", overrides=[f"env=push_new", f"algo={algo}", "train.warmup_steps=0", "eval.every=1000",
                                       "logging.progress=false", "threads=1"])
with tempfile.TemporaryDirectory() as run_dir:
    trainer = Trainer(cfg, Path(run_dir))
    trainer.iteration_step()
    seconds = []
    for _ in range(iterations):
        start = time.perf_counter()
        trainer.iteration_step()
        seconds.append(time.perf_counter() - start)
print("AB " + json.dumps(seconds))
"""


def one(checkout: Path, algo: str, iterations: int) -> list[float]:
    """Seconds of ``iterations`` timed iterations of a trainer built from ``checkout``."""
    env = dict(os.environ, MUJOCO_GL="disable", RL_LOGGING_LEVEL="WARNING", PYTHONPATH=str(checkout))
    done = subprocess.run([sys.executable, "-c", CHILD, algo, str(iterations)], cwd=checkout, env=env,
                          capture_output=True, text=True, timeout=3600)
    line = next((x for x in done.stdout.splitlines() if x.startswith("AB ")), None)
    if done.returncode != 0 or line is None:
        raise RuntimeError(f"the iteration in {checkout} failed:\n{done.stderr[-3000:]}")
    return json.loads(line[3:])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", type=Path, help="the first checkout (e.g. a worktree of the commit before)")
    parser.add_argument("b", type=Path, help="the second checkout")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=2, help="timed iterations per trainer")
    parser.add_argument("--algo", default="gchgg")
    args = parser.parse_args(argv)
    from gchgg.analysis import stats

    ratios = []
    for r in range(args.rounds):
        order = (args.a, args.b) if r % 2 == 0 else (args.b, args.a)
        medians = {c: statistics.median(one(c.resolve(), args.algo, args.iterations)) for c in order}
        ratios.append(medians[args.b] / medians[args.a])
        print(f"round {r}: A {medians[args.a]:.2f} s, B {medians[args.b]:.2f} s per iteration, B / A {ratios[-1]:.3f}",
              flush=True)
    estimate = stats.median_interval(ratios)
    print(f"B / A = {estimate.format(3)} (median of {len(ratios)} rounds' ratios, 95 % bootstrap interval; "
          f"A: {args.a}, B: {args.b}, algo={args.algo})")


if __name__ == "__main__":
    main()
