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
interval (:mod:`gchgg.analysis.stats`, rliable's definitions), are in the table too:

- **first ≥ 0.9**, censored: :func:`first_at` 0.9 if it is below the run's budget B. A run that did
  not get there is *censored* at ``C = min(L, B)``, L its last iteration + 1 (the number of
  iterations it ran; iterations count from 0), and counted at ``C + 1``: at B + 1, the issue's
  "budget + 1", if it ran its budget, and at its own length + 1 if it ended before (a pick_obstacle
  run abandoned at 0.00 after 200 of 400 iterations is censored at 200 and counted at 201, not as
  failing at 400). Every count of a censored run is above every first iteration a run of the same
  budget can show (at most B − 1). A run that stopped early by ``train.stop_success`` had reached
  0.9 and is not censored.
- **AUC**: the mean evaluation success rate over iterations 0 … R − 1, a fraction in [0, 1], each
  run shorter than R held at its last value as the curves hold it. R is common to the groups
  compared on a task (all of the task's groups in the table, the two in ``--compare``): the smallest
  budget among their runs, or the length of their shortest censored run if that is shorter (so no
  run that never reached 0.9 is extended past its end); ``--auc-range R`` sets it. The table and
  ``--compare`` print it.

A run's budget B is ``--budget`` if given, else ``train.iterations`` of its saved config, else that
of the task's Fig. 5 experiment (``conf/experiment/fig5_<task>.yaml``: reach 15, push_new 200,
pick_no_obstacle 200, pick_obstacle 400), else the task's longest run's length.

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
import csv
import functools
import itertools
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gchgg.analysis import stats

__all__ = ["Run", "Scores", "auc", "auc_range", "average_poi", "budget_of", "compare", "find_runs", "first_score",
           "format_looks", "group_runs", "iqr", "paired", "plot", "scores", "seed_of", "table"]

_IGNORED = ("seed", "resume", "threads", "matmul", "logging.", "graph.cache_dir", "hydra.")  # never a group's setting
_SEED_SUFFIX = re.compile(r"-seed\d+$")
_EXPERIMENTS = Path(__file__).resolve().parents[2] / "conf" / "experiment"  # fig5_<task>.yaml: the tasks' budgets
THRESHOLD = 0.9
"""The success rate whose first iteration is the scores' "first ≥ 0.9"."""


@dataclass
class Run:
    """One training run: where it is, its settings (flattened config) and its ``metrics.csv`` rows."""

    path: Path
    task: str
    settings: dict[str, str] = field(default_factory=dict)
    rows: list[dict[str, float]] = field(default_factory=list)
    label: str = ""

    def column(self, name: str) -> np.ndarray:
        """The column's values per iteration (NaN where a row lacks it)."""
        return np.array([row.get(name, math.nan) for row in self.rows], dtype=float)

    @property
    def hours(self) -> float:
        """Wall-clock hours of the logged iterations: the sum of the ``seconds_*`` columns."""
        return sum(self.iteration_seconds()) / 3600.0

    def iteration_seconds(self) -> list[float]:
        """Each logged iteration's wall-clock seconds: the sum of its ``seconds_*`` columns."""
        return [sum(v for k, v in row.items() if k.startswith("seconds_")) for row in self.rows]


def _flatten(tree: dict, prefix: str = "") -> dict[str, str]:
    out = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_flatten(value, f"{name}."))
        else:
            out[name] = str(value)
    return out


FRACTIONS = ("success_rate", "train_success_rate", "object_off_table", "object_moved", "object_rose_2cm",
             "object_rose_10cm")
"""Columns that are fractions of episodes, read rounded to 6 decimals: runs before December 2026
wrote them as float32 means, 90 of 100 as 0.8999999762, which must count as reaching 0.9."""


def _read_rows(path: Path) -> list[dict[str, float]]:
    def value(key: str, text: str) -> float:
        return round(float(text), 6) if key in FRACTIONS else float(text)

    with open(path, newline="") as f:
        rows = [{k: value(k, v) for k, v in row.items() if v not in ("", None)} for row in csv.DictReader(f)]
    if not rows or "success_rate" not in rows[0]:
        raise ValueError(f"{path} is not a metrics.csv of a training run (no rows, or no success_rate column)")
    return rows


def load_run(path: str | Path) -> Run:
    """A run from its folder (``metrics.csv`` + ``config.yaml``) or from a metrics CSV file."""
    path = Path(path)
    csv_path = path / "metrics.csv" if path.is_dir() else path
    if not csv_path.is_file():
        raise FileNotFoundError(f"no metrics.csv at {csv_path}: pass a run folder, a sweep folder or a CSV file")
    config = csv_path.parent / "config.yaml" if path.is_dir() else csv_path.with_suffix(".yaml")
    settings, task = {}, ""
    if config.is_file():
        import yaml

        settings = _flatten(yaml.safe_load(config.read_text()) or {})
        task = settings.get("env.name", "")
    label = "" if settings else _SEED_SUFFIX.sub("", csv_path.stem)
    task = task or csv_path.parent.name  # docs/results/push_new/gchgg-seed0.csv: task push_new
    return Run(csv_path.parent if path.is_dir() else csv_path, task, settings, _read_rows(csv_path), label)


def find_runs(paths: Iterable[str | Path]) -> list[Run]:
    """Every run under ``paths`` (run folders, sweep folders searched recursively, or CSV files)."""
    runs = []
    for path in map(Path, paths):
        if path.is_dir() and not (path / "metrics.csv").is_file():
            found = sorted(p.parent for p in path.rglob("metrics.csv"))
            if not found:
                found = sorted(path.glob("*.csv"))  # a folder of metrics CSVs: docs/results/push_new
            if not found:
                raise FileNotFoundError(f"no metrics.csv under {path}, nor a CSV file in it")
            runs.extend(load_run(p) for p in found)
        else:
            runs.append(load_run(path))
    return runs


def group_runs(runs: Sequence[Run]) -> dict[tuple[str, str], list[Run]]:
    """Runs by (task, label): the label names the settings that differ between runs of the same task
    (``algo.name=gchgg, curriculum.scale=standardized``), or is the file name for runs without a config."""
    groups: dict[tuple[str, str], list[Run]] = {}
    by_task: dict[str, list[Run]] = {}
    for run in runs:
        by_task.setdefault(run.task, []).append(run)
    for task, members in by_task.items():
        configured = [r for r in members if r.settings]
        keys = sorted({k for r in configured for k in r.settings if not k.startswith(_IGNORED)})
        differing = [k for k in keys if len({r.settings.get(k) for r in configured}) > 1]
        if "algo.name" in differing:  # settings an algo choice implies (its sampler, metric, ...) add nothing
            by_algo: dict[str, list[Run]] = {}
            for r in configured:
                by_algo.setdefault(r.settings.get("algo.name"), []).append(r)
            implied = {
                k for k in differing
                if k != "algo.name" and all(len({r.settings.get(k) for r in rs}) == 1 for rs in by_algo.values())
            }  # fmt: skip
            differing = [k for k in differing if k not in implied]
        for run in members:
            if run.settings:
                label = (", ".join(f"{k}={run.settings.get(k)}" for k in differing)
                         or run.settings.get("algo.name", "run"))
                label = label.replace("algo.name=", "")
            else:
                label = run.label
            groups.setdefault((task, label), []).append(run)
    return groups


def iqr(values: Sequence[float]) -> tuple[float, float, float]:
    """``(median, first quartile, third quartile)`` (linear interpolation; ``inf`` allowed; NaN values,
    runs that did not log a column, are left out).

    >>> iqr([1.0, 2.0, 3.0, 4.0, float("nan")])
    (2.5, 1.75, 3.25)
    """
    values = np.asarray(values, dtype=float)
    values = np.sort(values[~np.isnan(values)])
    if len(values) == 0:
        return (math.nan,) * 3
    q = []
    for p in (0.5, 0.25, 0.75):  # numpy's percentile turns inf - inf into NaN; interpolate by hand
        pos = p * (len(values) - 1)
        lo, hi = int(math.floor(pos)), int(math.ceil(pos))
        frac = pos - lo
        q.append(values[lo] if frac == 0 or values[lo] == values[hi] else values[lo] + frac * (values[hi] - values[lo]))
    return float(q[0]), float(q[1]), float(q[2])


def curves(runs: Sequence[Run], column: str) -> np.ndarray:
    """``[runs, iterations]`` values of ``column``, each run held at its last value to the longest run's end."""
    length = max(len(r.rows) for r in runs)
    out = np.full((len(runs), length), math.nan)
    for i, run in enumerate(runs):
        values = run.column(column)
        out[i, : len(values)] = values
        if len(values):
            out[i, len(values) :] = values[-1]
    return out


def first_at(run: Run, threshold: float, column: str = "success_rate") -> float:
    """The first iteration whose ``column`` is ≥ ``threshold`` (``inf`` if none)."""
    for row in run.rows:
        if row.get(column, -math.inf) >= threshold:
            return row["iteration"]
    return math.inf


@functools.cache
def _fig5_budget(task: str) -> int | None:
    """``train.iterations`` of ``conf/experiment/fig5_<task>.yaml`` (None if there is no such file)."""
    path = _EXPERIMENTS / f"fig5_{task}.yaml"
    if not path.is_file():
        return None
    import yaml

    return int(((yaml.safe_load(path.read_text()) or {}).get("train") or {})["iterations"])


def budget_of(run: Run, override: int | None = None) -> int | None:
    """The iterations ``run`` was given: ``override`` if set, else its config's ``train.iterations``, else
    the task's Fig. 5 budget (``conf/experiment/fig5_<task>.yaml``), else None (not known)."""
    if override is not None:
        if override < 1:
            raise ValueError(f"--budget {override}: a budget is a number of iterations, allowed: 1 or more")
        return int(override)
    if "train.iterations" in run.settings:
        return int(run.settings["train.iterations"])
    return _fig5_budget(run.task)


def first_score(run: Run, budget: int, threshold: float = THRESHOLD) -> tuple[int, bool]:
    """``(iteration, censored)``: the first iteration at ``success_rate`` ≥ ``threshold`` if below ``budget``
    (:func:`first_at`), else ``min(last iteration + 1, budget) + 1`` marked censored: one past the
    iteration the run is censored at (see the module's docstring).

    >>> run = Run(Path("r.csv"), "t", rows=[{"iteration": i, "success_rate": s} for i, s in enumerate([0, 0.5, 0.9])])
    >>> first_score(run, 200), first_score(run, 2), first_score(run, 200, threshold=0.95)
    ((2, False), (3, True), (4, True))
    """
    first = first_at(run, threshold)
    if first < budget:
        return int(first), False
    return min(int(run.rows[-1]["iteration"]) + 1, budget) + 1, True


def auc(run: Run, iterations: int, column: str = "success_rate") -> float:
    """The mean of ``column`` over iterations 0 … ``iterations`` − 1, the run held at its last value past its end."""
    if iterations < 1:
        raise ValueError(f"AUC range {iterations}: the mean over iterations 0 … R − 1 needs R ≥ 1")
    values = run.column(column)
    held = np.concatenate([values, np.full(max(iterations - len(values), 0), values[-1])])[:iterations]
    if np.isnan(held).any():
        raise ValueError(f"{run.path}: {column} is missing at an iteration below {iterations}; the AUC needs every one")
    return float(held.mean())


@dataclass
class Scores:
    """One group's per-run scores: first ≥ 0.9 (censored or not) under each run's budget, and the AUC
    over the common range ``auc_range`` of the groups it was compared with."""

    first: np.ndarray
    censored: np.ndarray
    auc: np.ndarray
    budgets: list[int]
    auc_range: int

    @property
    def runs(self) -> int:
        return len(self.first)

    @property
    def censored_at(self) -> list[int]:
        """The iteration each censored run is censored at (its count in ``first`` less 1)."""
        return [int(f) - 1 for f, c in zip(self.first, self.censored, strict=True) if c]

    @property
    def first_bound(self) -> np.ndarray:
        """first ≥ 0.9 as the probability of improvement reads it: the iteration where observed, and where
        censored the iteration it was censored at, a bound (its true first iteration is that or later)."""
        return self.first - self.censored

    def first_interval(self, rng: np.random.Generator | None = None) -> stats.Estimate:
        """IQM [95 % CI] of first ≥ 0.9 (censored runs counted one past their censoring iteration)."""
        return stats.iqm_interval(self.first, rng=rng)

    def auc_interval(self, rng: np.random.Generator | None = None) -> stats.Estimate:
        """IQM [95 % CI] of the AUC."""
        return stats.iqm_interval(self.auc, rng=rng)


def auc_range(runs: Sequence[Run], budgets: Sequence[int], censored: Sequence[bool]) -> int:
    """The AUC's common range R for ``runs`` (those of the groups compared on one task): the smallest of
    their ``budgets``, or the length (last iteration + 1) of their shortest ``censored`` run if shorter."""
    ends = [int(r.rows[-1]["iteration"]) + 1 for r, c in zip(runs, censored, strict=True) if c]
    return min([*budgets, *ends])


def scores(groups: dict[tuple[str, str], list[Run]], budget: int | None = None,
           auc_iterations: int | None = None) -> dict[tuple[str, str], Scores]:
    """Each group's :class:`Scores`; ``budget`` overrides every run's (see :func:`budget_of`), and
    ``auc_iterations`` the AUC's range R, else :func:`auc_range` over the task's runs in ``groups``
    (pass only the groups to compare). A run whose budget is not known gets its task's longest run's length."""
    if auc_iterations is not None and auc_iterations < 1:
        raise ValueError(f"--auc-range {auc_iterations}: the AUC is the mean over iterations 0 … R − 1; "
                         "allowed: R ≥ 1")
    longest: dict[str, int] = {}
    for (task, _), runs in groups.items():
        longest[task] = max([longest.get(task, 0), *(int(r.rows[-1]["iteration"]) + 1 for r in runs)])
    budgets = {id(r): budget_of(r, budget) or longest[task] for (task, _), runs in groups.items() for r in runs}
    firsts = {id(r): first_score(r, budgets[id(r)]) for runs in groups.values() for r in runs}
    ranges: dict[str, int] = {}
    for task in longest:
        members = [r for (t, _), runs in groups.items() if t == task for r in runs]
        ranges[task] = auc_iterations or auc_range(members, [budgets[id(r)] for r in members],
                                                   [firsts[id(r)][1] for r in members])
    out = {}
    for (task, label), runs in groups.items():
        out[task, label] = Scores(
            first=np.array([firsts[id(r)][0] for r in runs], dtype=float),
            censored=np.array([firsts[id(r)][1] for r in runs], dtype=bool),
            auc=np.array([auc(r, ranges[task]) for r in runs]),
            budgets=[budgets[id(r)] for r in runs],
            auc_range=ranges[task],
        )
    return out


def compare(groups: dict[tuple[str, str], list[Run]], first: str, second: str, budget: int | None = None,
            rng: np.random.Generator | None = None, auc_iterations: int | None = None,
            looks: Sequence[int] | None = None) -> list[str]:
    """Per task holding both groups, one line: P(a run of ``first`` beats a run of ``second``) on first ≥ 0.9
    (strictly fewer iterations; a censored run read as its censoring iteration, a bound, and its pairs as
    in :func:`gchgg.analysis.stats.probability_of_improvement`: :attr:`Scores.first_bound`) and
    on the AUC (larger; over the range :func:`auc_range` gives the two groups' runs, or ``auc_iterations``),
    each with its 95 % interval and the runs it rests on; with ``looks`` (the runs per group at each planned
    look of a sequential design, the present count among them), at Pocock's level for those looks instead.
    Without ``looks``, where two or more tasks hold both groups, a last line averages both figures over those
    tasks (:func:`gchgg.analysis.stats.average_poi_interval`)."""
    labels = {label for _, label in groups}
    for name in (first, second):
        if name not in labels:
            raise ValueError(f"--compare {first} {second}: no group {name!r}; "
                             f"the groups are {', '.join(sorted(labels))}")
    alpha, level = stats.ALPHA, ""
    if looks:
        alpha = stats.sequential_alpha(looks)
        level = f"; {100 * (1 - alpha):.1f} % intervals, Pocock's for looks at {format_looks(looks)}"
    lines, both = [], []
    for task in sorted({task for task, _ in groups}):
        if (task, first) not in groups or (task, second) not in groups:
            missing = first if (task, first) not in groups else second
            lines.append(f"{task}: no runs of {missing}")
            continue
        pair = {key: groups[key] for key in ((task, first), (task, second))}
        pair_scores = scores(pair, budget, auc_iterations)
        a, b = pair_scores[task, first], pair_scores[task, second]
        if looks and (a.runs != b.runs or a.runs not in looks):
            raise ValueError(f"--looks {' '.join(map(str, looks))}: {task} has {a.runs} runs of {first} and {b.runs} "
                             f"of {second}; a look reads the same number of runs of each, one of the planned looks")
        poi_first = stats.poi_interval(a.first_bound, b.first_bound, lower_is_better=True, x_censored=a.censored,
                                       y_censored=b.censored, alpha=alpha, rng=rng)
        poi_auc = stats.poi_interval(a.auc, b.auc, alpha=alpha, rng=rng)
        lines.append(f"{task}: P({first} beats {second}) first >= {THRESHOLD}: {poi_first.format()}"
                     f" ({a.runs} vs {b.runs} runs); AUC over iterations 0-{a.auc_range - 1}: {poi_auc.format()}"
                     f"{level}")
        both.append((task, a, b))
    if len(both) > 1 and not looks:  # rliable's average probability of improvement over the tasks
        pairs = [(a, b) for _, a, b in both]
        average_first, average_auc = (average_poi(pairs, score, rng) for score in ("first", "auc"))
        lines.append(f"averaged over {', '.join(task for task, _, _ in both)}: P({first} beats {second}) first >= "
                     f"{THRESHOLD}: {average_first.format()}; AUC: {average_auc.format()}")
    return lines


def average_poi(pairs: Sequence[tuple[Scores, Scores]], score: str = "first",
                rng: np.random.Generator | None = None) -> stats.Estimate:
    """P(a run of the first group beats one of the second) averaged over tasks, one ``(first, second)`` pair of
    :class:`Scores` per task (:func:`gchgg.analysis.stats.average_poi_interval`), on ``score``: ``"first"`` (fewer
    iterations to 0.9, censored runs as in :func:`compare`) or ``"auc"`` (a larger area)."""
    if score == "auc":
        return stats.average_poi_interval([a.auc for a, _ in pairs], [b.auc for _, b in pairs], rng=rng)
    return stats.average_poi_interval([a.first_bound for a, _ in pairs], [b.first_bound for _, b in pairs],
                                      lower_is_better=True, x_censored=[a.censored for a, _ in pairs],
                                      y_censored=[b.censored for _, b in pairs], rng=rng)


def format_looks(looks: Sequence[int]) -> str:
    """``3, 4, 5 runs``, or ``3-10 runs`` for a run of consecutive counts."""
    looks = list(looks)
    if len(looks) > 2 and looks == list(range(looks[0], looks[-1] + 1)):
        return f"{looks[0]}-{looks[-1]} runs"
    return f"{', '.join(map(str, looks))} runs"


def seed_of(run: Run) -> int | None:
    """The run's seed: its config's ``seed``, else the ``-seed<N>`` of its CSV's name (``None`` without either)."""
    if "seed" in run.settings:
        return int(run.settings["seed"])
    match = re.search(r"-seed(\d+)$", Path(run.path).stem)
    return int(match.group(1)) if match else None


def paired(groups: dict[tuple[str, str], list[Run]], first: str, second: str, budget: int | None = None,
           rng: np.random.Generator | None = None) -> list[str]:
    """Per task holding both groups: the runs of ``first`` (A) and ``second`` (B) paired by seed, a line
    per pair (HGG stop and first ≥ 0.9 of each, censored ones marked ``>``, and A − B), then per score
    (the HGG stop, first ≥ 0.9, and the AUC over the pairs' common range, :func:`auc_range`)
    the mean paired difference A − B with its 95 % interval and how many pairs A was ahead (fewer
    iterations), level and behind in, and below it the same runs' difference taken unpaired (the two
    groups resampled apart) with the partners' Pearson correlation (pairing narrows the interval only
    where partners correlate) and the small-sample tests of :func:`gchgg.analysis.stats.paired_tests`. Runs
    without a partner are named and left out."""
    labels = {label for _, label in groups}
    for name in (first, second):
        if name not in labels:
            raise ValueError(f"--pairs {first} {second}: no group {name!r}; the groups are {', '.join(sorted(labels))}")
    lines = []
    for task in sorted({task for task, _ in groups}):
        if (task, first) not in groups or (task, second) not in groups:
            continue
        pair_scores = scores({key: groups[key] for key in ((task, first), (task, second))}, budget)
        by_seed = []
        for label in (first, second):
            runs, score = groups[task, label], pair_scores[task, label]
            by_seed.append({seed_of(r): (r, score.first[i], score.censored[i], score.auc[i])
                            for i, r in enumerate(runs)})
        seeds = sorted(set(by_seed[0]) & set(by_seed[1]) - {None})
        alone = sorted(str(s) for s in set(by_seed[0]) ^ set(by_seed[1]))
        lines.append(f"{task}: {len(seeds)} pair{'s' * (len(seeds) != 1)} of {first} (A) and {second} (B) by seed"
                     + (f"; without a partner: seed {', '.join(alone)}" if alone else ""))
        if not seeds:
            continue
        auc_name = f"AUC over iterations 0-{pair_scores[task, first].auc_range - 1}"
        columns = {"HGG stop": [], f"first >= {THRESHOLD}": [], auc_name: []}
        for seed in seeds:
            (a, a_first, a_cens, a_auc), (b, b_first, b_cens, b_auc) = by_seed[0][seed], by_seed[1][seed]
            stops = [first_at(r, 1.0, "stopped") for r in (a, b)]
            columns["HGG stop"].append(stops)
            columns[f"first >= {THRESHOLD}"].append([a_first, b_first])
            columns[auc_name].append([a_auc, b_auc])
            first_text = [f"{'>' if c else ''}{v:g}" for v, c in ((a_first, a_cens), (b_first, b_cens))]
            lines.append(f"  seed {seed}: HGG stop A {stops[0]:g}, B {stops[1]:g} (A - B {stops[0] - stops[1]:g}); "
                         f"first >= {THRESHOLD} A {first_text[0]}, B {first_text[1]} (A - B {a_first - b_first:g})")
        for name, values in columns.items():
            values = np.asarray(values, dtype=float)
            finite = np.isfinite(values).all(1)
            if not finite.any():
                lines.append(f"  {name}: no pair where both runs have one")
                continue
            a_values, b_values = values[finite, 0], values[finite, 1]
            digits = 3 if name == auc_name else 1
            estimate = stats.paired_difference_interval(a_values, b_values, rng=rng)
            better = a_values > b_values if name == auc_name else a_values < b_values  # the AUC: higher is ahead
            worse = a_values < b_values if name == auc_name else a_values > b_values
            ahead, behind = int(better.sum()), int(worse.sum())
            pairs = f"{estimate.runs} pair{'s' * (estimate.runs != 1)}"
            lines.append(f"  {name}, A - B over {pairs}: mean {estimate.format(digits)}; A ahead in {ahead}, "
                         f"level in {estimate.runs - ahead - behind}, behind in {behind}")
            if estimate.runs > 1:  # did pairing remove noise? the partners' correlation, and the runs unpaired
                apart = stats.unpaired_difference_interval(a_values, b_values, rng=rng)
                spread = a_values.std() * b_values.std()
                r = f"{np.mean((a_values - a_values.mean()) * (b_values - b_values.mean())) / spread:.2f}" if spread \
                    else "undefined (a constant score)"
                t, w = stats.paired_tests(a_values, b_values)
                lines.append(f"    the same runs unpaired: {apart.format(digits)}; partners' correlation r = {r}; "
                             f"paired t-test p = {t:.3f}, Wilcoxon signed-rank p = {w:.3f}")
    return lines


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
