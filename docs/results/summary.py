"""Summarises the learning curves in docs/results/ (the numbers the README quotes) and plots them.

Each ``<env>-<algo>.csv`` is a run's ``metrics.csv``. Prints, per run: iterations, env steps, the
success rate at a few iterations, the first iteration at or above 0.5 and 0.9, the best and last
success rate, the hours spent in the timed phases (goals, rollout, store, update, eval,
checkpoint) and, for HGG-style runs, the iteration at which intermediate goals stopped. With
``--plot FILE.png`` draws success rate against iteration for every run of each task.

Run: ``python docs/results/summary.py --plot docs/results/curves.png``
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parent
MARKS = (0, 10, 25, 50, 70, 100, 150)


def load(path: Path) -> dict[str, list[float]]:
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path} holds no rows")
    return {key: [float(row[key]) if row[key] not in ("", None) else float("nan") for row in rows] for key in rows[0]}


def first_at(values: list[float], iterations: list[float], level: float) -> str:
    for it, value in zip(iterations, values):
        if value >= level:
            return str(int(it))
    return "never"


def summarise(name: str, run: dict[str, list[float]]) -> None:
    iterations, success = run["iteration"], run["success_rate"]
    marks = ", ".join(f"{m}: {success[m]:.2f}" for m in MARKS if m < len(success))
    line = (f"{name}: {len(iterations)} iterations, {int(run['env_steps'][-1]):,} env steps; success at {marks}; "
            f"first >= 0.5 at {first_at(success, iterations, 0.5)}, >= 0.9 at {first_at(success, iterations, 0.9)}; "
            f"best {max(success):.2f}, last {success[-1]:.2f}")
    phases = [key for key in run if key.startswith("seconds_")]
    if phases:
        hours = sum(v for key in phases for v in run[key] if v == v) / 3600  # v == v: skip blanks (NaN)
        line += f"; {hours:.1f} h in the timed phases"
    stopped = run.get("stopped")
    if stopped is not None and any(stopped) and run.get("d_g") and any(run["d_g"]):
        line += f"; stop condition met at iteration {int(iterations[stopped.index(1.0)])} (target goals from then on)"
    print(line)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plot", type=Path, help="write the success curves to this PNG")
    args = parser.parse_args()
    runs = {path.stem: load(path) for path in sorted(HERE.glob("*.csv"))}
    if not runs:
        raise SystemExit(f"no CSV files in {HERE}")
    for name, run in runs.items():
        summarise(name, run)
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        tasks: dict[str, list[str]] = defaultdict(list)
        for name in runs:
            tasks[name.split("-")[0]].append(name)
        fig, axes = plt.subplots(1, len(tasks), figsize=(5 * len(tasks), 3.6), squeeze=False)
        for ax, (task, names) in zip(axes[0], tasks.items()):
            for name in names:
                ax.plot(runs[name]["iteration"], runs[name]["success_rate"], label=name.split("-", 1)[1])
            ax.set(title=task, xlabel="iteration (50 episodes each)", ylabel="success rate (100 target goals)",
                   ylim=(-0.02, 1.02))
            ax.grid(alpha=0.3)
            ax.legend()
        fig.tight_layout()
        fig.savefig(args.plot, dpi=110)
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
