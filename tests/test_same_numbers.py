"""A fixed-seed tiny run of every algorithm on push_new reproduces its recorded metrics.csv exactly.

In so tiny a push_new run the cube hardly moves, so HGG's pool stays empty; the algorithms with a
goal generator are also recorded on reach, where every trajectory enters the pool and the
intermediate goals, D_G and λ come into play.

Refactors must not change a single number: ``tests/data/same_numbers/<task>-<algo>.csv`` holds the metrics
(timing columns aside) of the run below as the code produced them when recorded. A change that
is meant to alter learning re-records them with ``python tests/test_same_numbers.py`` and says why.

The float32 products of the updates are torch's BLAS (MKL), which computes them with other kernels,
and so other roundings, on Intel CPUs than on AMD ones: the losses of an Intel machine's tiny run
differ from an AMD machine's from the 7th digit on (and on reach, where the policy moves the arm,
so do the distances and the diversity that follow). So each vendor has
its recording: ``same_numbers/`` for AMD (AVX2 and AVX-512 alike), ``same_numbers/intel/`` for Intel
(recorded on a Xeon with AVX-512 and AMX). Re-recording writes the running machine's.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from test_train import config, tiny  # noqa: E402

from gchgg import train  # noqa: E402
from gchgg.linear import cpu_vendor  # noqa: E402

RECORDED = Path(__file__).parent / "data" / "same_numbers" / ("intel" if cpu_vendor() == "GenuineIntel" else "")
CASES = [("push_new", algo) for algo in ("her", "hgg", "ghgg", "cher", "gchgg", "gchgg_code")] + [
    ("reach", algo) for algo in ("hgg", "gchgg", "gchgg_code")
]


def run(task: str, algo: str, folder: Path) -> list[dict[str, str]]:
    """Metrics rows (timing columns dropped) of a 3-iteration tiny run with 4 episodes in 2 chunks."""
    overrides = [f"env={task}", f"algo={algo}", *tiny(folder, iterations=3), "train.episodes=4", "train.chunks=2",
                 "train.updates=8", "train.warmup_steps=200", "seed=3"]
    train.run(config(overrides), folder / "run")
    with open(folder / "run" / "metrics.csv", newline="") as f:
        return [{k: v for k, v in row.items() if not k.startswith("seconds_")} for row in csv.DictReader(f)]


@pytest.mark.parametrize("task, algo", CASES)
def test_tiny_run_reproduces_the_recorded_metrics(task, algo, tmp_path):
    with open(RECORDED / f"{task}-{algo}.csv", newline="") as f:
        recorded = list(csv.DictReader(f))
    assert run(task, algo, tmp_path) == recorded


if __name__ == "__main__":  # re-record
    import os
    import tempfile

    os.environ.setdefault("MUJOCO_GL", "disable")
    RECORDED.mkdir(parents=True, exist_ok=True)
    for task, algo in CASES:
        with tempfile.TemporaryDirectory() as tmp:
            rows = run(task, algo, Path(tmp))
        path = RECORDED / f"{task}-{algo}.csv"
        with open(path, "w", newline="") as f:
            writer = csv.DictWriter(f, list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        print(f"recorded {path} ({len(rows)} rows)")
