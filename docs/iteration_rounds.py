"""Pool the rounds of ``benchmarks/iteration.py`` runs: ``everything on / fp32 floor`` with a 95 % bootstrap interval.

    python docs/iteration_rounds.py [docs/benchmark_logs/d4117cc.txt ...]

Reads the line ``everything on / fp32 floor = X (...; the median of N rounds' ratios: a, b, ...)`` from each
given output of ``benchmarks/iteration.py`` (default: the runs of the library code of d4117cc in
``docs/benchmark_logs/``) and prints each run's median and the rounds' pooled median with a 95 % percentile
bootstrap interval over the rounds (:func:`gchgg.analysis.stats.median_interval`, 10,000 resamples, seed 0). The
rounds of one run are not independent draws (they share a trainer and the minutes they ran in), so the
interval is a lower bound on the uncertainty, not a test.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np

from gchgg.analysis.stats import median_interval

LOGS = Path(__file__).resolve().parent / "benchmark_logs"
SAME_CODE = ("d4117cc.txt", "f88d517-replication.txt", "4221258.txt")  # the library code of d4117cc
REPS = 10_000  # bootstrap resamples (generator seeded 0: gchgg.analysis.stats' default)
LINE = re.compile(r"everything on / fp32 floor = ([0-9.]+) .*rounds' ratios: ([0-9., ]+)\)")


def rounds_of(path: Path) -> list[float]:
    """The rounds' ratios of ``everything on / fp32 floor`` printed in one run's output."""
    for line in path.read_text().splitlines():
        match = LINE.search(line)
        if match:
            return [float(x) for x in match.group(2).split(",")]
    raise ValueError(f"{path}: no 'everything on / fp32 floor' line (is it benchmarks/iteration.py's output?)")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("logs", nargs="*", type=Path, default=[LOGS / name for name in SAME_CODE],
                        help="outputs of benchmarks/iteration.py (default: the runs of d4117cc's library code)")
    args = parser.parse_args(argv)
    pooled = []
    for path in args.logs:
        rounds = rounds_of(path)
        pooled += rounds
        listed = ", ".join(f"{r:.2f}" for r in rounds)
        print(f"{path.name}: median {np.median(rounds):.2f} of {len(rounds)} rounds ({listed})")
    pooled_median = median_interval(pooled, reps=REPS)
    print(f"pooled: everything on / fp32 floor = {pooled_median.format()} (median of {len(pooled)} rounds "
          f"of {len(args.logs)} runs, 95 % bootstrap interval over the rounds; target <= 1.0)")


if __name__ == "__main__":
    main(sys.argv[1:])
