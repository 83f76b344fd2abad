"""Each run's scores (first ≥ 0.9, censored at its budget, and the AUC) and the comparisons of groups on them.

Two scores per run, summarised per group by their interquartile mean with a 95 % stratified-bootstrap
interval (:mod:`gchgg.analysis.stats`, rliable's definitions), in the table of :mod:`gchgg.analysis.plot`:

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

:func:`compare` reads the probability that a run of one group beats a run of another on each score,
:func:`paired` the differences of runs paired by seed; ``python -m gchgg.analysis.plot`` prints both
(``--compare``, ``--pairs``), and :mod:`gchgg.analysis.claims` checks the paper's claims with them.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gchgg.analysis import stats
from gchgg.analysis.runs import Run, first_at, seed_of

__all__ = ["THRESHOLD", "Scores", "auc", "auc_range", "average_poi", "budget_of", "compare", "first_score",
           "format_looks", "paired", "scores"]

_EXPERIMENTS = Path(__file__).resolve().parents[2] / "conf" / "experiment"  # fig5_<task>.yaml: the tasks' budgets
THRESHOLD = 0.9
"""The success rate whose first iteration is the scores' "first ≥ 0.9"."""


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
