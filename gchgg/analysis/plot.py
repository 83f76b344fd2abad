"""Curves and tables over seeds: median and interquartile range of a metric per group of runs.

    python -m gchgg.analysis.plot RUN_OR_SWEEP_OR_CSV... [--out FIG.png] [--table TABLE.md] [--y COLUMN...]
    python -m gchgg.analysis.plot docs/results/push_new --compare gchgg ghgg [--budget N] [--auc-range R]
    python -m gchgg.analysis.plot docs/results/push_new/forks --pairs gchgg ghgg

Each argument is a run folder (``metrics.csv`` and the ``config.yaml`` the trainer saves), a folder
holding such runs at any depth (a sweep), a ``metrics.csv``-style file, or a folder of such files
(its ``*.csv``, not its subfolders': ``docs/results/push_new``). Runs are grouped by task
and by the settings that differ between them, read from their saved configs (seed, paths and
logging aside); a CSV without a config beside it is grouped by its name without its ``-seed<N>``
suffix and its task is its folder's name (``docs/results/push_new/gchgg-seed0.csv`` → task
``push_new``, group ``gchgg``). A run that stopped early
(``train.stop_success``) holds its last value to the longest run's end.

The figure has one panel per task and per ``--y`` column (rows: columns; default: the success rate;
the tasks in Fig. 5's order) and a median line with an interquartile band per group, each group in
one colour throughout (Fig. 5 of the paper). ``--y d_g
train_success_rate object_rose_10cm`` draws a run's diagnostics beside its success. The table
(Markdown) gives per group: runs, iterations to the first success rate ≥ 0.5 and ≥ 0.9 (median
[IQR] over runs; a run that never got there counts as never, and the table says how many did), each
``--y`` column at chosen iterations and at the end, a run's last iteration,
the iteration HGG's stop condition switched it to target goals (``stopped``), the iterations from
that stop to the first success ≥ 0.9 (after the stop the curriculum samples plainly, so every HGG
variant trains the same way from there), the mean
``diversity_decided`` fraction while the curriculum was active (before that stop), wall-clock
hours, and seconds per iteration (a run's median: what an iteration of the method costs).

Two scores per run, summarised per group by their interquartile mean with a 95 % stratified-bootstrap
interval, are in the table too: **first ≥ 0.9**, censored at the run's budget B, and the **AUC**, the
mean success over iterations 0 … R − 1, R common to the groups compared on a task (the table and
``--compare`` print it). :mod:`gchgg.analysis.scoring` defines both, B (``--budget``, else the run's
config, else the task's Fig. 5 experiment) and R (``--auc-range``).

``--compare A B`` prints, per task holding both groups, the probability that a run of A beats a
run of B on each score (fewer iterations to 0.9; a larger AUC), with its 95 % interval, instead of
the table (``--table`` and ``--out`` still write theirs). ``--looks N1 N2 …`` names the looks of a
sequential design, planned before its first: the comparison is read at N1, N2, … runs per group (runs
added until an interval decides, at most the last look's); the intervals are then drawn at Pocock's
level for all those looks (:func:`gchgg.analysis.stats.sequential_alpha`), and the groups' present run count
must be one of them. Without ``--looks``, runs of several tasks (``docs/results/push_new
docs/results/pick_obstacle``) add a line averaging each score's probability over the tasks (rliable's
average probability of improvement, each task's runs resampled apart), as the claims table's
``faster_pooled`` claims read it.

``--task NAME`` takes every run as one of task ``NAME`` (one panel, that task's budget), for runs of a
task kept in several folders, e.g. a Fig. 6 ablation's CSVs (``docs/results/fig6/eta/500-seed0.csv``,
group ``500``) beside the default setting's runs (``docs/results/pick_no_obstacle/gchgg-seed0.csv``)::

    python -m gchgg.analysis.plot docs/results/fig6/eta/*.csv docs/results/pick_no_obstacle/gchgg-seed[012].csv \
        --task pick_no_obstacle --y success_rate lambda diversity_decided --out eta.png --table eta.md

``--pairs A B`` pairs the runs of A and B by seed (paired forks: two forks of one checkpoint with the
same new seed, :mod:`gchgg.run.fork`) and prints, per pair, both runs' HGG stop iteration and first
iteration at ≥ 0.9 (censored as above, marked ``>``), their differences A − B, and per score the mean
paired difference with its 95 % bootstrap interval over pairs (:func:`gchgg.analysis.stats.paired_difference_interval`)
and how many pairs A was ahead, level and behind in.
"""

from __future__ import annotations

import argparse
import itertools
import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from gchgg.analysis.runs import FRACTIONS, Run, curves, find_runs, first_at, group_runs, iqr, load_run, seed_of
from gchgg.analysis.scoring import (
    THRESHOLD,
    Scores,
    auc,
    auc_range,
    average_poi,
    budget_of,
    compare,
    first_score,
    format_looks,
    paired,
    scores,
)

# Its own names, and those of gchgg.analysis.runs and .scoring that claims, docs, benchmarks and tests read from here
__all__ = ["FIG5_TASKS", "FRACTIONS", "THRESHOLD", "Run", "Scores", "auc", "auc_range", "average_poi", "budget_of",
           "compare", "curves", "find_runs", "first_at", "first_score", "format_looks", "group_runs", "iqr",
           "label_colours", "load_run", "main", "paired", "panel_tasks", "plot", "scores", "seed_of", "table"]


def _fmt(quartiles: tuple[float, float, float], digits: int | None = None) -> str:
    def one(v: float) -> str:
        if v == math.inf:
            return "never"
        return "—" if math.isnan(v) else (f"{v:g}" if digits is None else f"{v:.{digits}f}")

    median, low, high = quartiles
    return "—" if math.isnan(median) else f"{one(median)} [{one(low)}, {one(high)}]"  # —: no run logged it


def _as_list(column: str | Sequence[str]) -> list[str]:
    """One column name or several, as a list."""
    return [column] if isinstance(column, str) else list(column)


def table(groups: dict[tuple[str, str], list[Run]], at: Sequence[int] = (70, 100, 150),
          column: str | Sequence[str] = "success_rate", budget: int | None = None,
          auc_iterations: int | None = None) -> str:
    """A Markdown table per group: runs, iterations to success ≥ 0.5 / ≥ 0.9, each of ``column`` at ``at``
    and at the end, the IQM [95 % CI] of first ≥ 0.9 (censored runs counted one past their censoring
    iteration, and how many were), the IQM [95 % CI] of the AUC and its range (``0-R−1``, R common to
    a task's groups: :func:`auc_range`, or ``auc_iterations``), ... (the thresholds and scores are on
    ``success_rate`` whatever ``column`` is; ``budget`` overrides the runs' budgets, :func:`budget_of`).

    A run shorter than an ``at`` iteration (one stopped early, or ``at 300`` for a run of iterations
    0–299) counts with its last value, as the curves hold it."""
    columns = _as_list(column)
    group_scores = scores(groups, budget, auc_iterations)
    head = ["task", "group", "runs", "first ≥ 0.5", "first ≥ 0.9"]
    for name in columns:
        head += [*(f"{name} at {i}" for i in at), f"final {name}"]
    head += [f"first ≥ {THRESHOLD} IQM [95 % CI]", "censored", "AUC IQM [95 % CI]"]
    head += ["last iteration", "HGG stop", "first ≥ 0.9 − HGG stop", "diversity decided (before the stop)", "hours",
             "s/iteration"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (task, label), runs in sorted(groups.items()):
        reached = {t: [first_at(r, t) for r in runs] for t in (0.5, 0.9)}
        cells = [task, label, str(len(runs))]
        for t in (0.5, 0.9):
            n = sum(math.isfinite(v) for v in reached[t])
            cells.append(f"{_fmt(iqr(reached[t]))} ({n}/{len(runs)})")
        for name in columns:
            values = curves(runs, name)
            for i in at:  # past the longest run's end: every run's last value, as the curves hold it
                cells.append(_fmt(iqr(values[:, min(i, values.shape[1] - 1)]), 2))
            cells.append(_fmt(iqr([r.column(name)[-1] for r in runs]), 2))
        score = group_scores[task, label]
        cells += [score.first_interval().format(1), str(int(score.censored.sum())),
                  f"{score.auc_interval().format(3)} over 0-{score.auc_range - 1}"]
        cells.append(_fmt(iqr([r.rows[-1]["iteration"] for r in runs])))
        generated = [r for r in runs if "d_g" in r.rows[-1]]  # runs with a goal generator
        stops = [first_at(r, 1.0, "stopped") for r in generated]
        cells.append(f"{_fmt(iqr(stops))}" if stops else "—")
        # after the stop every HGG variant trains on target goals with plain sampling: how long that took
        after = [first_at(r, 0.9) - stop for r, stop in zip(generated, stops, strict=True) if math.isfinite(stop)]
        cells.append(f"{_fmt(iqr(after))}" if after else "—")
        decided = [_while_curriculum(r, "diversity_decided") for r in runs if "diversity_decided" in r.rows[-1]]
        cells.append(f"{np.mean(decided):.2f}" if decided else "—")
        cells.append(_fmt(iqr([r.hours for r in runs]), 2))
        cells.append(_fmt(iqr([float(np.median(r.iteration_seconds())) for r in runs]), 1))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _while_curriculum(run: Run, column: str) -> float:
    """Mean of ``column`` over the iterations before HGG's stop (``stopped`` 0; all rows without it):
    afterwards the curriculum samples one candidate and the column is 0 by construction."""
    values = run.column(column)
    if "stopped" in run.rows[-1]:
        values = values[run.column("stopped") == 0]
    return float(np.nanmean(values)) if len(values) else math.nan


FIG5_TASKS = ("reach", "push_new", "pick_no_obstacle", "pick_obstacle")
"""The paper's Fig. 5 panels a–d, in its order: the figure's panels follow it."""


def panel_tasks(tasks: Iterable[str]) -> list[str]:
    """The figure's panel order: the tasks of Fig. 5 in the paper's order, then any others alphabetically."""
    tasks = set(tasks)
    return [t for t in FIG5_TASKS if t in tasks] + sorted(tasks - set(FIG5_TASKS))


def label_colours(labels: Iterable[str]) -> dict[str, str]:
    """One colour per group label, the same in every panel (matplotlib's cycle ``C0``, ``C1``, … over the
    sorted labels), so that a method keeps its colour where another task lacks a group."""
    return {label: f"C{i % 10}" for i, label in enumerate(sorted(set(labels)))}


def plot(
    groups: dict[tuple[str, str], list[Run]], out: str | Path, column: str | Sequence[str] = "success_rate"
) -> None:
    """One panel per task and column: median and interquartile band of the column per group against iteration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = _as_list(column)
    tasks = panel_tasks(task for task, _ in groups)
    colours = label_colours(label for _, label in groups)
    fig, axes = plt.subplots(len(columns), len(tasks), figsize=(5.5 * len(tasks), 4 * len(columns)), squeeze=False)
    for row, name in zip(axes, columns, strict=True):
        for ax, task in zip(row, tasks, strict=True):
            for (t, label), runs in sorted(groups.items()):
                if t != task:
                    continue
                values = curves(runs, name)
                x = np.arange(values.shape[1])
                stats = np.array([iqr(values[:, i]) for i in x])
                ax.plot(x, stats[:, 0], color=colours[label], label=f"{label} (n={len(runs)})")
                ax.fill_between(x, stats[:, 1], stats[:, 2], color=colours[label], alpha=0.2)
            ax.set_title(task or "runs")
            ax.set_xlabel("iteration")
            ax.set_ylabel(name)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", help="run folders, sweep folders or metrics CSV files")
    parser.add_argument("--out", help="figure file (PNG, PDF, SVG)")
    parser.add_argument("--table", help="Markdown table file (printed either way)")
    parser.add_argument("--y", nargs="+", default=["success_rate"], metavar="COLUMN",
                        help="metrics columns to plot (one row of panels each) and tabulate; default: success_rate")
    parser.add_argument("--at", type=int, nargs="*", default=[70, 100, 150], help="iterations the table reports")
    parser.add_argument("--budget", type=int, metavar="N",
                        help="every run's budget in iterations (censoring of first >= 0.9, the AUC's range); "
                             "default: its config's train.iterations, else conf/experiment/fig5_<task>.yaml's")
    parser.add_argument("--auc-range", type=int, metavar="R",
                        help="the AUC is the mean success over iterations 0 ... R-1; default: the smallest budget of "
                             "the compared runs, or their shortest censored run's length if shorter")
    parser.add_argument("--compare", nargs=2, metavar=("A", "B"),
                        help="print P(a run of group A beats one of group B) per task, on both scores, "
                             "instead of the table")
    parser.add_argument("--looks", type=int, nargs="+", metavar="N",
                        help="with --compare: the runs per group at each planned look of a sequential design "
                             "(runs added until an interval decides); the intervals are then Pocock's for those "
                             "looks, and the present run count must be one of them")
    parser.add_argument("--task", help="treat every run as one of this task (its budget, one panel): runs of one "
                                       "task kept in several folders, e.g. a Fig. 6 ablation beside its default runs")
    parser.add_argument("--pairs", nargs=2, metavar=("A", "B"),
                        help="pair the runs of groups A and B by seed (paired forks) and print the paired "
                             "differences A - B of HGG stop and first >= 0.9, instead of the table")
    args = parser.parse_args(argv)
    if args.budget is not None and args.budget < 1:
        parser.error(f"--budget {args.budget}: a budget is a number of iterations, allowed: 1 or more")
    if args.auc_range is not None and args.auc_range < 1:
        parser.error(f"--auc-range {args.auc_range}: the AUC is the mean over iterations 0 ... R-1; allowed: R >= 1")
    runs = find_runs(args.paths)
    if args.task:  # one task for all: runs from several folders in one panel (a Fig. 6 ablation and its default)
        for run in runs:
            run.task = args.task
    logged = {key for run in runs for row in run.rows for key in row}
    unknown = [name for name in args.y if name not in logged]
    if unknown:
        parser.error(f"--y {' '.join(unknown)}: no run logged {'these columns' if len(unknown) > 1 else 'this column'};"
                     f" the runs' columns are {', '.join(sorted(logged))}")
    if args.looks and not args.compare:
        parser.error("--looks: the looks of a comparison; allowed only with --compare A B")
    if args.looks and (min(args.looks) < 1 or any(b <= a for a, b in itertools.pairwise(args.looks))):
        parser.error(f"--looks {' '.join(map(str, args.looks))}: allowed an increasing list of run counts, each 1 "
                     "or more")
    groups = group_runs(runs)
    if args.compare:
        try:
            print("\n".join(compare(groups, *args.compare, budget=args.budget, auc_iterations=args.auc_range,
                                     looks=args.looks)))
        except ValueError as error:
            parser.error(str(error))
    if args.pairs:
        try:
            print("\n".join(paired(groups, *args.pairs, budget=args.budget)))
        except ValueError as error:
            parser.error(str(error))
    quiet = args.compare or args.pairs
    text = table(groups, args.at, args.y, args.budget, args.auc_range) if args.table or not quiet else ""
    if not quiet:
        print(text, end="")
    if args.table:
        Path(args.table).write_text(text)
    if args.out:
        plot(groups, args.out, args.y)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
