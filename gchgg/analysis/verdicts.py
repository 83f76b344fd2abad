"""The verdict rules: each kind of claim judged on its runs, by its interval and, for a comparison, its exact test.

A claim's ``kind`` sets what is measured and the verdict's rule (every kind: *undecided* while a
group it reads has fewer than ``min_runs`` runs, ``0 runs`` for a group without any yet):

- ``reaches_by`` (``by`` N): first ≥ 0.9 of the group. Holds if the IQM's CI upper bound ≤ N · (1 +
  ``slack``), contradicted if its lower bound is above that, else undecided.
- ``fails`` (``within`` W): first ≥ 0.9. Holds if every run is censored and every run ran W iterations
  (none reached 0.9 in W); undecided if a run ended sooner ("tested to N"); contradicted if the IQM's CI
  upper bound < W, else undecided.
- ``final`` (``level`` m, ``spread`` s): the success rate at the last iteration of the task's budget.
  Undecided while a run ended before it (:class:`Ends`: stopped early by the stop rule, or at its own
  cap): no value is carried past a run's last row. Otherwise holds if the IQM's CI lies inside
  [m − s, m + s], contradicted if it lies wholly outside, else undecided.
- ``faster`` (``than`` B): P(a run of the group reaches 0.9 in fewer iterations than a run of B), ties
  and pairs whose order censoring leaves open counted half (:func:`gchgg.analysis.stats.probability_of_improvement`).
  Holds if its CI lies above 0.5 and the exact Mann–Whitney test (:func:`gchgg.analysis.exact.mann_whitney`,
  two-sided, at the interval's level) rejects ½; contradicted if the CI lies below 0.5 and the test
  rejects; else undecided.
- ``faster_paired`` (``than`` B, ``pairs`` F): paired forks (:mod:`gchgg.run.fork`) in ``<results>/<task>/F/``,
  the group's and B's runs paired by seed: the mean paired difference group − B of first ≥ 0.9
  (:func:`gchgg.analysis.stats.paired_difference_interval`; a censored run counted one past its censoring
  iteration) beside the exact Wilcoxon signed-rank and sign tests. Holds if its CI lies below 0 (the
  group reaches 0.9 earlier) and both tests give p < 0.05, contradicted if above 0 with both, else
  undecided; undecided below ``min_pairs`` pairs (default 8).
- ``score: auc`` (``faster``, ``faster_pooled``, ``faster_paired``, ``alike``): the same rules on the area under the
  evaluation-success curve (the mean success over iterations 0 … R − 1, R the two groups' common
  range, :func:`gchgg.analysis.plot.auc_range`; higher is better) instead of first ≥ 0.9: the threshold's first
  crossing is noisy where a curve hovers near 0.9, the area weighs the whole curve. Default
  ``score: first``.
- ``faster_pooled`` (``than`` B, ``tasks`` {T: n, ...}): P(a run of the group beats a run of B) as for
  ``faster``, on each task T, averaged over the tasks (rliable's average probability of improvement,
  :func:`gchgg.analysis.stats.average_poi_interval`: each task's runs resampled apart). Read once, when each task
  has n runs of each group (the last look of its sequential design): holds if the CI lies above 0.5,
  contradicted if below 0.5, each with the stratified Mann–Whitney test (:func:`gchgg.analysis.exact.
  mann_whitney_tasks`) at p < 0.05; undecided before that, where the CI contains 0.5, or the test does not
  reject.
- ``alike`` (``than`` B, ``margin`` m): P(a run of the group reaches 0.9 in fewer iterations than a run
  of B), as for ``faster``. Holds if its CI lies inside [0.5 − m, 0.5 + m] (neither beats the other in
  more than 0.5 + m of the pairs; no exact test of equality exists to add), contradicted if it lies outside
  that band and excludes 0.5 and the Mann–Whitney test rejects ½, else undecided (a few runs give a wide
  CI: "alike" needs many).

``looks`` (``reaches_by``, ``final``, ``faster``, ``alike``): the runs per group at each planned look of a
sequential design (runs added until the interval decides, e.g. ``[3, 4, 5, 6, 7, 8, 9, 10]``): the
interval is then drawn at Pocock's level for all those looks (:func:`gchgg.analysis.stats.sequential_alpha`), not
at 95 %, since reading it after every added run and stopping once it decides would otherwise decide too
often; the row is undecided while the groups' run counts differ or are not one of the looks.

The intervals are percentile-bootstrap intervals (:mod:`gchgg.analysis.stats`); the tests are
exact or permutation tests (:mod:`gchgg.analysis.exact`). :mod:`gchgg.analysis.claims` reads the claims and
the runs and writes the table.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gchgg.analysis import exact, plot, stats

__all__ = ["COMPARISONS", "KINDS", "LOOKS_KINDS", "SCORES", "SEED_FILE", "STOP_PATIENCE", "VERDICTS", "Claim", "Ends",
           "Row", "ended_by_stop_rule", "judge", "judge_paired", "judge_pooled", "measure_groups", "seed_files"]

KINDS = {"reaches_by": ("by",), "fails": ("within",), "final": ("level", "spread"), "faster": ("than",),
         "faster_pooled": ("than", "tasks"), "faster_paired": ("than", "pairs"), "alike": ("than", "margin")}
"""Each kind of claim and the fields it needs besides id, task, groups, claim and paper."""

LOOKS_KINDS = ("reaches_by", "final", "faster", "alike")
"""The kinds whose interval may be drawn at Pocock's level for a sequential design's ``looks``."""

VERDICTS = ("holds", "contradicted", "undecided")
COMPARISONS = ("faster", "faster_pooled", "faster_paired", "alike")
"""The kinds that compare two groups, on either score."""
SCORES = ("first", "auc")
"""What a comparison reads: first ≥ 0.9 (fewer iterations is better) or the AUC (higher is better)."""


@dataclass
class Claim:
    """One claim about one group (and, for a comparison, the group it is compared with) on one task (for
    ``faster_pooled``: on each of ``tasks``, ``task`` naming them together)."""

    id: str
    task: str
    kind: str
    group: str
    claim: str
    paper: str
    by: float = math.nan
    within: float = math.nan
    level: float = math.nan
    spread: float = math.nan
    than: str = ""
    margin: float = math.nan
    pairs: str = ""  # faster_paired: the task's subfolder of paired forks
    score: str = "first"  # COMPARISONS: "first" (first >= 0.9) or "auc"
    runs: tuple[tuple[str, str], ...] = ()  # (group, glob under results) instead of <task>/<group>-seed<N>.csv
    looks: tuple[int, ...] = ()  # LOOKS_KINDS: runs per group at each planned look of a sequential design
    tasks: tuple[tuple[str, int], ...] = ()  # faster_pooled: (task, runs per group when it is read), in order


@dataclass
class Row:
    """A claim's line of the table: what was measured, the verdict and its reason."""

    claim: Claim
    measured: str
    verdict: str
    reason: str
    short_of_runs: bool = False


SEED_FILE = re.compile(r"^(?P<group>.+)-seed\d+\.csv$")
"""A run's CSV in a task's folder: ``<group>-seed<N>.csv`` (``gchgg-seed0.csv``)."""


def seed_files(folder: str | Path) -> list[Path]:
    """The runs' CSVs directly in ``folder`` named ``<group>-seed<N>.csv`` (not those in its subfolders,
    ``unfinished/`` or ``invalid/``, nor other CSVs), sorted by name."""
    folder = Path(folder)
    return sorted(p for p in folder.glob("*.csv") if p.is_file() and SEED_FILE.match(p.name))



STOP_PATIENCE = 5
"""The stop rule's patience (``train.stop_patience``): a run it ended holds ≥ 0.9 over its last 5 rows."""


@dataclass
class Ends:
    """Where a group's runs ended: each run's last success rate, how many iterations it ran, whether the
    stop rule ended it (its last :data:`STOP_PATIENCE` rows ≥ 0.9, before the budget) and the budget's
    last iteration. A run that ran out its own cap before the budget is short, not stopped early."""

    last: np.ndarray
    ran: np.ndarray
    by_stop_rule: np.ndarray
    budget_last: int

    @property
    def short(self) -> np.ndarray:
        """The runs that ended before the budget's last iteration (no success rate measured there)."""
        return self.ran <= self.budget_last


def ended_by_stop_rule(run: plot.Run, budget: int, patience: int = STOP_PATIENCE) -> bool:
    """Whether the stop rule ended ``run``: it ended before ``budget`` with its last ``patience`` success rates
    ≥ 0.9 (a run that hit its own cap below 0.9, or at the budget, was not ended by it)."""
    success = run.column("success_rate")
    return len(success) < budget and len(success) >= patience and bool((success[-patience:] >= plot.THRESHOLD).all())


def measure_groups(groups: dict[tuple[str, str], list[plot.Run]]) -> tuple[dict, dict]:
    """Scores and where the runs ended (:class:`Ends`), of runs grouped by (task, label), keyed by label."""
    group_scores = plot.scores(groups)
    scores, ends = {}, {}
    for key, runs in groups.items():
        s = scores[key[1]] = group_scores[key]
        ends[key[1]] = Ends(
            last=np.array([r.column("success_rate")[:b][-1] for r, b in zip(runs, s.budgets, strict=True)]),
            ran=np.array([min(len(r.rows), b) for r, b in zip(runs, s.budgets, strict=True)]),
            by_stop_rule=np.array([ended_by_stop_rule(r, b) for r, b in zip(runs, s.budgets, strict=True)]),
            budget_last=max(s.budgets) - 1)
    return scores, ends


def _few(claim: Claim, runs: dict[str, int], min_runs: int) -> str:
    """The reason a claim is undecided for want of runs ("" if every group it reads has enough)."""
    short = [g for g in (claim.group, claim.than) if g and runs.get(g, 0) < min_runs]
    if not short:
        return ""
    parts = [f"{g}: {runs.get(g, 0)} run{'s' * (runs.get(g, 0) != 1)}" for g in short]
    return "; ".join(parts) + (f" ({min_runs} needed)" if any(runs.get(g, 0) for g in short) else "")


def _number(value: float) -> str:
    return f"{value:g}"


def _off_look(claim: Claim, *runs: int) -> str:
    """Why the claim is undecided for a sequential design whose looks these run counts (one per group it
    reads) miss: they differ, or are not one of ``claim.looks`` ("" without looks, or at a look)."""
    if not claim.looks or (len(set(runs)) == 1 and runs[0] in claim.looks):
        return ""
    each = " each" if len(runs) > 1 else ""
    return (f"{' and '.join(map(str, runs))} runs: not a look of the design "
            f"({plot.format_looks(claim.looks)}{each})")


@functools.cache
def _pocock_alpha(looks: tuple[int, ...]) -> float:
    """:func:`gchgg.analysis.stats.sequential_alpha` of the looks, simulated once per design (claims share designs)."""
    return stats.sequential_alpha(looks)


def _p(value: float) -> str:
    """A p-value or level in the table: two decimals from 0.1 on, two significant digits below."""
    return f"{value:.2g}" if value < 0.1 else f"{value:.2f}"


def _span(values) -> str:
    low, high = int(min(values)), int(max(values))
    return f"{low}" if low == high else f"{low}–{high}"


def _faster_verdict(claim: Claim, text: str, poi: stats.Estimate, p_value: float, alpha: float, test: str) -> Row:
    """A faster claim's verdict on its probability of improvement and its exact test's two-sided ``p_value``:
    holds with the CI above 0.5 and p < ``alpha``, contradicted with the CI below 0.5 and p < ``alpha``."""
    side = "above" if poi.low > 0.5 else "below" if poi.high < 0.5 else ""
    if not side:
        return Row(claim, text, "undecided", "CI contains 0.5")
    if p_value >= alpha:
        return Row(claim, text, "undecided", f"CI {side} 0.5, but {test} p = {_p(p_value)} ≥ {_p(alpha)}")
    return Row(claim, text, "holds" if side == "above" else "contradicted", f"CI {side} 0.5; p < {_p(alpha)}")


def judge(claim: Claim, scores: dict[str, plot.Scores], finals: dict[str, tuple[np.ndarray, int, int]],
          min_runs: int = 3, slack: float = 0.1) -> Row:
    """The claim's row: its measured figure and its verdict by the rule of its kind (module docstring)."""
    runs = {label: s.runs for label, s in scores.items()}
    few = _few(claim, runs, min_runs)
    mine = scores.get(claim.group)
    if mine is None:
        return Row(claim, "—; 0 runs", "undecided", few, True)
    alpha, level = stats.ALPHA, ""
    if claim.looks:
        alpha = _pocock_alpha(claim.looks)
        level = f" ({100 * (1 - alpha):.1f} % CI, Pocock's for looks at {plot.format_looks(claim.looks)})"
    first = stats.iqm_interval(mine.first, alpha=alpha)
    first_text = (f"first ≥ {plot.THRESHOLD} IQM {first.format(1)}{level}; "
                  f"{mine.runs} run{'s' * (mine.runs != 1)}, {int(mine.censored.sum())} censored")
    if claim.kind == "reaches_by":
        bound = claim.by * (1 + slack)
        target = f"{_number(bound)} ({_number(claim.by)} + {_number(100 * slack)} %)"
        if few:
            return Row(claim, first_text, "undecided", few, True)
        if off := _off_look(claim, mine.runs):
            return Row(claim, first_text, "undecided", off)
        if first.high <= bound:
            return Row(claim, first_text, "holds", f"CI ≤ {target}")
        if first.low > bound:
            return Row(claim, first_text, "contradicted", f"CI > {target}")
        return Row(claim, first_text, "undecided", f"CI straddles {target}")
    if claim.kind == "fails":
        if few:
            return Row(claim, first_text, "undecided", few, True)
        censored = int(mine.censored.sum())
        if censored == mine.runs:
            ran = sorted(set(int(n) for n in finals[claim.group].ran))
            tested = f"{ran[0]}" if len(ran) == 1 else f"{ran[0]}–{ran[-1]}"
            if ran[0] < claim.within:
                short = int((finals[claim.group].ran < claim.within).sum())
                return Row(claim, first_text, "undecided", f"no run reached 0.9, but {short} of {mine.runs} "
                                                           f"were tested to {tested} iterations, not "
                                                           f"{_number(claim.within)}")
            return Row(claim, first_text, "holds", f"no run reached 0.9 in {tested} iterations")
        if first.high < claim.within:
            return Row(claim, first_text, "contradicted", f"CI < {_number(claim.within)}")
        return Row(claim, first_text, "undecided", f"{mine.runs - censored} of {mine.runs} runs reached 0.9; "
                                                   f"CI reaches {_number(claim.within)}")
    if claim.kind == "final":
        ends = finals[claim.group]
        end = stats.iqm_interval(ends.last, alpha=alpha)
        stopped, short = int(ends.by_stop_rule.sum()), int(ends.short.sum())
        if short:
            text = (f"last success IQM {end.format(2)}{level} (runs ended after {_span(ends.ran)} iterations, "
                    f"not at {ends.budget_last}); {mine.runs} run{'s' * (mine.runs != 1)}, {stopped} stopped early "
                    "by the stop rule")
        else:
            text = f"success at {ends.budget_last} IQM {end.format(2)}{level}; {mine.runs} run{'s' * (mine.runs != 1)}"
        low, high = claim.level - claim.spread, claim.level + claim.spread
        band = f"[{low:.2f}, {high:.2f}]"
        eps = 1e-9  # 0.99 + 0.01 is 1.0 up to float rounding
        if few:
            return Row(claim, text, "undecided", few, True)
        if off := _off_look(claim, mine.runs):
            return Row(claim, text, "undecided", off)
        if short:
            why = (f"{stopped} stopped early by the stop rule, " if stopped else "") + (
                f"{short - stopped} ran out their own cap" if short > stopped else "")
            return Row(claim, text, "undecided", f"{short} of {mine.runs} runs ended before iteration "
                                                 f"{ends.budget_last} ({why.rstrip(', ')}): no success measured there")
        if end.low >= low - eps and end.high <= high + eps:
            return Row(claim, text, "holds", f"CI inside {band}")
        if end.low > high + eps:
            return Row(claim, text, "contradicted", f"CI above {band}")
        if end.high < low - eps:
            return Row(claim, text, "contradicted", f"CI below {band}")
        return Row(claim, text, "undecided", f"CI overlaps {band}")
    # faster, alike
    other = scores.get(claim.than)
    if other is None:
        return Row(claim, f"{first_text}; {claim.than}: 0 runs", "undecided", few, True)
    if claim.score == "auc":
        poi = stats.poi_interval(mine.auc, other.auc, alpha=alpha)
        p_value = exact.mann_whitney(mine.auc, other.auc)
        on = f"AUC over iterations 0–{mine.auc_range - 1}"
    else:
        poi = stats.poi_interval(mine.first_bound, other.first_bound, lower_is_better=True,
                                 x_censored=mine.censored, y_censored=other.censored, alpha=alpha)
        p_value = exact.mann_whitney(mine.first_bound, other.first_bound, lower_is_better=True,
                                     x_censored=mine.censored, y_censored=other.censored)
        on = f"first ≥ {plot.THRESHOLD}"
    text = (f"P({claim.group} beats {claim.than}) on {on}: {poi.format(2)}{level}; {mine.runs} vs {other.runs} runs; "
            f"Mann–Whitney p = {_p(p_value)}")
    if few:
        return Row(claim, text, "undecided", few, True)
    if off := _off_look(claim, mine.runs, other.runs):
        return Row(claim, text, "undecided", off)
    if claim.kind == "alike":
        low, high = 0.5 - claim.margin, 0.5 + claim.margin
        band = f"[{low:.2f}, {high:.2f}]"
        if poi.low >= low and poi.high <= high:
            return Row(claim, text, "holds", f"CI inside {band}")
        if poi.low > 0.5 or poi.high < 0.5:
            if p_value >= alpha:
                return Row(claim, text, "undecided", f"CI outside {band}, excluding 0.5, but Mann–Whitney "
                                                     f"p = {_p(p_value)} ≥ {_p(alpha)}")
            return Row(claim, text, "contradicted", f"CI outside {band}, excluding 0.5; p < {_p(alpha)}")
        return Row(claim, text, "undecided", f"CI contains 0.5, reaches outside {band}")
    return _faster_verdict(claim, text, poi, p_value, alpha, "Mann–Whitney")


def judge_pooled(claim: Claim, task_groups: Callable[[str], dict[tuple[str, str], list[plot.Run]]],
                 min_runs: int = 3) -> Row:
    """A ``faster_pooled`` claim's row: the probability of improvement averaged over ``claim.tasks``, whose runs
    ``task_groups(task)`` gives (grouped as :func:`gchgg.analysis.plot.group_runs`), each task scored on its own."""
    scored, counts, few = [], [], []
    for task, _ in claim.tasks:
        pair = {key: runs for key, runs in task_groups(task).items() if key[1] in (claim.group, claim.than)}
        by_label = {label: s for (_, label), s in plot.scores(pair).items()} if pair else {}
        mine, other = by_label.get(claim.group), by_label.get(claim.than)
        counts.append((task, mine.runs if mine else 0, other.runs if other else 0))
        if short := _few(claim, {label: s.runs for label, s in by_label.items()}, min_runs):
            few.append(f"{task}: {short}")
        if mine and other:
            scored.append((task, mine, other))
    runs_text = ", ".join(f"{task} {a} vs {b}" for task, a, b in counts) + " runs"
    if len(scored) < len(claim.tasks):
        return Row(claim, f"—; {runs_text}", "undecided", "; ".join(few), True)
    scored.sort(key=lambda item: item[0])  # the tasks' resampling order as plot --compare's: the same digits
    poi = plot.average_poi([(a, b) for _, a, b in scored], claim.score)
    if claim.score == "auc":
        p_value = exact.mann_whitney_tasks([a.auc for _, a, _ in scored], [b.auc for _, _, b in scored])
        on = "AUC (each task over its two groups' common range)"
    else:
        p_value = exact.mann_whitney_tasks(
            [a.first_bound for _, a, _ in scored], [b.first_bound for _, _, b in scored], lower_is_better=True,
            x_censored=[a.censored for _, a, _ in scored], y_censored=[b.censored for _, _, b in scored])
        on = f"first ≥ {plot.THRESHOLD}"
    text = (f"P({claim.group} beats {claim.than}) on {on}, averaged over {len(scored)} tasks: {poi.format(2)}; "
            f"{runs_text}; stratified Mann–Whitney p = {_p(p_value)}")
    if few:
        return Row(claim, text, "undecided", "; ".join(few), True)
    planned = dict(claim.tasks)
    early = [f"{task} {a} and {b}" for task, a, b in counts if not a == b == planned[task]]
    if early:
        plan = ", ".join(f"{task} {n}" for task, n in claim.tasks)
        return Row(claim, text, "undecided", f"read once, at {plan} runs of each; now {', '.join(early)}")
    return _faster_verdict(claim, text, poi, p_value, stats.ALPHA, "stratified Mann–Whitney")


def judge_paired(claim: Claim, results: str | Path, min_pairs: int = 8) -> Row:
    """A ``faster_paired`` claim's row: the forks in ``<results>/<task>/<pairs>/`` paired by seed."""
    files = seed_files(Path(results) / claim.task / claim.pairs)
    groups = plot.group_runs([plot.load_run(p) for p in files]) if files else {}
    task_groups = {label: runs for (_, label), runs in groups.items()}
    if claim.group not in task_groups or claim.than not in task_groups:
        return Row(claim, "—; 0 pairs", "undecided", f"0 pairs ({min_pairs} needed)", True)
    group_scores = plot.scores({key: runs for key, runs in groups.items() if key[1] in (claim.group, claim.than)})
    auc = claim.score == "auc"
    value = {}
    for (_, label), score in group_scores.items():
        runs = task_groups[label]
        value[label] = {plot.seed_of(r): (score.auc if auc else score.first)[i] for i, r in enumerate(runs)}
    seeds = sorted(set(value[claim.group]) & set(value[claim.than]) - {None})
    if not seeds:
        return Row(claim, "—; 0 pairs", "undecided", f"0 pairs ({min_pairs} needed)", True)
    mine, theirs = [value[claim.group][k] for k in seeds], [value[claim.than][k] for k in seeds]
    difference = stats.paired_difference_interval(mine, theirs)
    on = (f"AUC over iterations 0–{next(iter(group_scores.values())).auc_range - 1}" if auc
          else f"first ≥ {plot.THRESHOLD}")
    signed_rank, sign = exact.wilcoxon(mine, theirs), exact.sign_test(mine, theirs)
    text = (f"{claim.group} − {claim.than} on {on}, paired forks: mean {difference.format(3 if auc else 1)}; "
            f"{difference.runs} pair{'s' * (difference.runs != 1)}; Wilcoxon p = {_p(signed_rank)}, "
            f"sign test p = {_p(sign)}")
    if difference.runs < min_pairs:
        return Row(claim, text, "undecided", f"{difference.runs} pairs ({min_pairs} needed)", True)
    sooner, later = (difference.low > 0, difference.high < 0) if auc else (difference.high < 0, difference.low > 0)
    if not (sooner or later):
        return Row(claim, text, "undecided", "CI contains 0")
    side = ("above" if sooner == auc else "below")
    if max(signed_rank, sign) >= stats.ALPHA:
        return Row(claim, text, "undecided", f"CI {side} 0, but Wilcoxon p = {_p(signed_rank)}, sign test "
                                             f"p = {_p(sign)}: not both < {_p(stats.ALPHA)}")
    return Row(claim, text, "holds" if sooner else "contradicted", f"CI {side} 0; both p < {_p(stats.ALPHA)}")
