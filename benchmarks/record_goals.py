"""Achieved goals of a recorded run, for the samplers' benchmark: ``benchmarks/data/<task>_achieved_goals.npy``.

Reads the replay files (:mod:`gchgg.run.replay_log`) a training run wrote for its first iterations and
saves ``--size`` achieved goals drawn uniformly (without replacement) from their rows, float32
``[size, 3]``. ``benchmarks/samplers.py`` samples a plain buffer's goals and targets from it: goals
as a learning agent's buffer holds them early on, clumped where an object rests.

Run: ``python benchmarks/record_goals.py ~/gchgg-runs/push_new/hgg-seed1`` (``--iterations 12
--size 20000 --seed 0`` by default; ``--out`` to write elsewhere). Prints what it read and wrote.
The recording docs/benchmarks.md's Xeon section read came from ``python -m gchgg.train
env=push_new algo=hgg seed=1 train.iterations=12 precision=float32 matmul=default`` at 1c92d3a
(``hydra.run.dir`` as the run folder above; the file is not kept in git, so a new machine records it anew).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from gchgg.run import replay_log

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a run folder holding replay/iteration-*.pt")
    parser.add_argument("--iterations", type=int, default=12, help="the first iterations to read (default 12)")
    parser.add_argument("--size", type=int, default=20_000, help="goals to keep (default 20,000)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "data" / "push_new_achieved_goals.npy")
    args = parser.parse_args()
    files = [args.run / "replay" / f"iteration-{k:06d}.pt" for k in range(args.iterations)]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise SystemExit(f"--iterations {args.iterations}: replay files missing (pruned, or not written yet): "
                         f"{', '.join(missing[:3])}{' …' if len(missing) > 3 else ''}")
    goals = torch.cat([replay_log.read(f)["rows"]["achieved_goal"].reshape(-1, 3) for f in files])
    if args.size > len(goals):
        raise SystemExit(f"--size {args.size} is more than the {len(goals):,} rows of the first {args.iterations} "
                         "iterations")
    keep = torch.randperm(len(goals), generator=torch.Generator().manual_seed(args.seed))[: args.size]
    chosen = goals[keep].to(torch.float32)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.save(args.out, chosen.numpy())
    distinct = len(torch.unique(chosen, dim=0))
    print(f"read {len(goals):,} achieved goals from {args.run} iterations 0-{args.iterations - 1}; wrote {args.size:,} "
          f"({distinct:,} distinct) to {args.out}")


if __name__ == "__main__":
    main()
