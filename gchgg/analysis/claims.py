"""The claims table: each of the paper's claims (a hand-written YAML list) against the committed runs, with a verdict.

    python -m gchgg.analysis.claims docs/results --out docs/results/claims.md [--claims docs/results/claims.yaml]
    python -m gchgg.analysis.claims docs/results --readme README.md   # the README's results block (readme_results)

Reads the runs of each claim's task from the files ``<results>/<task>/<group>-seed<N>.csv`` (every seed
there; not ``unfinished/`` nor ``invalid/``), or, for a claim with ``runs`` (a mapping of each of its
groups to a glob under ``<results>``, e.g. Fig. 6's ablations against the default runs: ``{"500":
fig6/eta/500-seed*.csv, gchgg: pick_no_obstacle/gchgg-seed[012].csv}``), from those files, every run
taken as one of the claim's task (its budget); and scores them as :mod:`gchgg.analysis.plot` does (first ≥ 0.9: a run
that never got there is censored at its budget or its end, whichever comes first, and counted one
past it; the success rate held past a run's end) and writes a Markdown table: per
claim the claim, the paper's figure, the measured one (IQM [95 % CI] or a probability of improvement
[95 % CI], :mod:`gchgg.analysis.stats`; the runs it rests on) and a verdict, *holds*, *contradicted* or
*undecided*, with its reason. Below the table, one line per verdict lists its claims: the lines the
README quotes.

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

An entry with a list of ``groups`` (or of ``than``) is one claim per member; ``{name}`` and
``{than}`` in its ``claim`` are replaced by the display names of ``names``.
"""

from __future__ import annotations

import argparse
import functools
import itertools
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gchgg.analysis import exact, plot, stats

__all__ = ["Claim", "Row", "judge", "judge_paired", "judge_pooled", "load_claims", "main", "measure",
           "measure_globs", "readme_results", "render", "replace_block", "seed_files", "summary", "verdicts"]

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


def _as_list(value) -> list:
    return list(value) if isinstance(value, (list, tuple)) else [value]


def load_claims(path: str | Path) -> tuple[list[Claim], dict]:
    """The claims of a YAML file (one per group of each entry) and its settings (``min_runs``, ``slack``)."""
    import yaml

    data = yaml.safe_load(Path(path).read_text()) or {}
    names = data.get("names") or {}
    settings = {"min_runs": int(data.get("min_runs", 3)), "slack": float(data.get("slack", 0.1)),
                "min_pairs": int(data.get("min_pairs", 8))}
    if settings["min_runs"] < 1 or settings["slack"] < 0:
        raise ValueError(f"{path}: min_runs {settings['min_runs']}, slack {settings['slack']}; allowed: "
                         "min_runs 1 or more, slack 0 or more")
    claims = []
    for number, entry in enumerate(data.get("claims") or []):
        if not isinstance(entry, dict):
            raise ValueError(f"{path}: claim #{number + 1} is {entry!r}; allowed: a mapping (id, task, kind, ...)")
        where = f"{path}: claim {entry.get('id', f'#{number + 1}')}"
        missing = [k for k in ("id", "task", "kind", "groups", "claim", "paper") if k not in entry]
        if missing:
            raise ValueError(f"{where}: no {', '.join(missing)}; "
                             "every claim needs id, task, kind, groups, claim, paper")
        kind = entry["kind"]
        if kind not in KINDS:
            raise ValueError(f"{where}: kind {kind!r}; allowed: {', '.join(KINDS)}")
        missing = [k for k in KINDS[kind] if k not in entry]
        if missing:
            raise ValueError(f"{where}: kind {kind} needs {', '.join(KINDS[kind])}; {', '.join(missing)} missing")
        score = entry.get("score", "first")
        if score not in SCORES or (score != "first" and kind not in COMPARISONS):
            raise ValueError(f"{where}: score {score!r} with kind {kind}; allowed: {', '.join(SCORES)} with "
                             f"{', '.join(COMPARISONS)}; first with the other kinds")
        looks = entry.get("looks") or []
        if looks and (kind not in LOOKS_KINDS or not isinstance(looks, list)
                      or any(not isinstance(n, int) or n < 1 for n in looks)
                      or any(b <= a for a, b in itertools.pairwise(looks))):
            raise ValueError(f"{where}: looks {looks!r} with kind {kind}; allowed with {', '.join(LOOKS_KINDS)}: "
                             "an increasing list of run counts per group, each 1 or more")
        tasks = entry.get("tasks") or {}
        if kind == "faster_pooled" and (not isinstance(tasks, dict) or len(tasks) < 2 or any(
                not isinstance(n, int) or isinstance(n, bool) or n < 1 for n in tasks.values())):
            raise ValueError(f"{where}: tasks {tasks!r} with kind {kind}; allowed: a mapping of two or more tasks "
                             "to the runs per group at which the claim is read, each 1 or more")
        groups, others = _as_list(entry["groups"]), _as_list(entry.get("than", ""))
        runs = entry.get("runs") or {}
        if not isinstance(runs, dict) or any(not isinstance(v, str) for v in runs.values()):
            raise ValueError(f"{where}: runs {runs!r}; allowed: a mapping of each group to a glob of CSVs "
                             "under the results folder")
        runs = {str(k): v for k, v in runs.items()}
        unnamed = [g for g in [*groups, *others] if g and runs and g not in runs]
        if unnamed:
            raise ValueError(f"{where}: runs names no glob for {', '.join(unnamed)}; a claim with runs names "
                             "one for each of its groups and than")
        for group in groups:
            for than in others:
                suffix = (f"-{group}" if len(groups) > 1 else "") + (f"-{than}" if len(others) > 1 else "")
                fields = {k: float(entry[k]) for k in ("by", "within", "level", "spread", "margin") if k in entry}
                claims.append(Claim(
                    id=f"{entry['id']}{suffix}", task=entry["task"], kind=kind, group=group, than=than,
                    claim=entry["claim"].format(name=names.get(group, group), than=names.get(than, than)),
                    paper=entry["paper"], pairs=str(entry.get("pairs", "")), score=score,
                    runs=tuple((g, runs[g]) for g in (group, than) if g in runs), looks=tuple(looks),
                    tasks=tuple((str(t), n) for t, n in tasks.items()) if kind == "faster_pooled" else (),
                    **fields))
    if not claims:
        raise ValueError(f"{path}: no claims (a YAML mapping with a `claims` list)")
    return claims, settings


SEED_FILE = re.compile(r"^(?P<group>.+)-seed\d+\.csv$")
"""A run's CSV in a task's folder: ``<group>-seed<N>.csv`` (``gchgg-seed0.csv``)."""


def seed_files(folder: str | Path) -> list[Path]:
    """The runs' CSVs directly in ``folder`` named ``<group>-seed<N>.csv`` (not those in its subfolders,
    ``unfinished/`` or ``invalid/``, nor other CSVs), sorted by name."""
    folder = Path(folder)
    return sorted(p for p in folder.glob("*.csv") if p.is_file() and SEED_FILE.match(p.name))


def measure(results: str | Path, task: str) -> tuple[dict[str, plot.Scores], dict[str, tuple[np.ndarray, int, int]]]:
    """The runs of ``<results>/<task>/<group>-seed<N>.csv`` by group: their :class:`gchgg.analysis.plot.Scores` (the
    AUC's range common to all the task's groups), and each run's success rate at the last iteration of
    its budget (held past its end) with how many runs stopped early by the stop rule (reached 0.9 and
    ended before their budget) and the budget's last iteration. Empty if there are no such files."""
    groups = _task_runs(results, task)
    return _measure(groups) if groups else ({}, {})


def measure_globs(results: str | Path, task: str, runs: Sequence[tuple[str, str]]) -> tuple[dict, dict]:
    """As :func:`measure`, for the runs of each ``(group, glob)`` of ``runs``: the CSVs under ``results``
    that match the glob, each taken as a run of ``task`` (its budget) labelled ``group``."""
    groups = _glob_runs(results, task, runs)
    return _measure(groups) if groups else ({}, {})


def _task_runs(results: str | Path, task: str) -> dict[tuple[str, str], list[plot.Run]]:
    files = seed_files(Path(results) / task)
    return plot.group_runs([plot.load_run(p) for p in files]) if files else {}


def _glob_runs(results: str | Path, task: str, runs: Sequence[tuple[str, str]]) -> dict[tuple[str, str], list]:
    groups: dict[tuple[str, str], list[plot.Run]] = {}
    for group, pattern in runs:
        for path in sorted(Path(results).glob(pattern)):
            run = plot.load_run(path)
            run.task, run.label = task, group
            groups.setdefault((task, group), []).append(run)
    return groups


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


def _measure(groups: dict[tuple[str, str], list[plot.Run]]) -> tuple[dict, dict]:
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


def verdicts(results: str | Path, claims: Sequence[Claim], min_runs: int = 3, slack: float = 0.1,
             min_pairs: int = 8) -> list[Row]:
    """Every claim judged on the runs under ``results`` (``<results>/<task>/``; paired forks in its subfolder)."""
    loaded: dict = {}
    measured: dict = {}
    rows = []

    def task_groups(task: str) -> dict:
        if task not in loaded:
            loaded[task] = _task_runs(results, task)
        return loaded[task]

    for c in claims:
        if c.kind == "faster_paired":
            rows.append(judge_paired(c, results, min_pairs))
            continue
        if c.kind == "faster_pooled":
            rows.append(judge_pooled(c, task_groups, min_runs))
            continue
        key = (c.task, c.runs) if c.runs else c.task
        if key not in measured:
            loaded[key] = _glob_runs(results, c.task, c.runs) if c.runs else task_groups(c.task)
            measured[key] = _measure(loaded[key]) if loaded[key] else ({}, {})
        scores, finals = measured[key]
        if c.score == "auc":  # the AUC over the two groups' own common range, as gchgg.analysis.plot --compare reads it
            pair = {k: runs for k, runs in loaded[key].items() if k[1] in (c.group, c.than)}
            scores = {label: s for (_, label), s in plot.scores(pair).items()} if pair else {}
        rows.append(judge(c, scores, finals, min_runs, slack))
    return rows


def summary(rows: Sequence[Row]) -> list[str]:
    """One line per verdict: how many claims got it (for undecided: how many for want of runs) and
    which, by task (``task: claim; claim — task: claim``)."""
    lines = []
    for verdict in VERDICTS:
        chosen = [r for r in rows if r.verdict == verdict]
        by_task: dict[str, list[str]] = {}
        for r in chosen:
            by_task.setdefault(r.claim.task, []).append(r.claim.claim)
        listed = " — ".join(f"{task}: {'; '.join(texts)}" for task, texts in by_task.items()) or "none"
        few = sum(r.short_of_runs for r in chosen)
        count = f"{len(chosen)} of {len(rows)}" + (f", {few} for want of runs" if few else "")
        lines.append(f"- **{verdict}** ({count}): {listed}")
    return lines


def render(rows: Sequence[Row], command: str, min_runs: int = 3, slack: float = 0.1, min_pairs: int = 8) -> str:
    """The Markdown page: how it was made, the table, and the verdict lines."""
    def cell(text: str) -> str:
        return text.replace("|", "\\|")

    lines = [
        "# The paper's claims against the committed runs",
        "",
        f"Generated by `{command}` from the runs in each task's folder (its CSVs) and the claims in",
        "[claims.yaml](claims.yaml) (what each claim measures, and the verdict rules); do not edit by hand.",
        "first ≥ 0.9: a run's first iteration at an evaluation success rate ≥ 0.9; a run that never got there",
        "is censored at the number of iterations it ran or its budget, whichever is smaller, and counted",
        "one past it (the Fig. 5 budgets: `conf/experiment/fig5_<task>.yaml`; the runs: `<task>/<group>-seed<N>.csv`).",
        "IQM [95 % CI]: interquartile mean over runs with a",
        "stratified-bootstrap interval; P(A beats B): probability of improvement, ties counted half",
        f"(`gchgg/analysis/stats.py`, rliable's definitions). Undecided below {min_runs} runs per group;",
        "The intervals are percentile intervals (rliable's): BCa's corrections need the jackknife of a statistic",
        "over the runs, which at 3 to 12 runs is itself too noisy to trust, and both cover less than 95 % at such",
        "sizes. So a comparison is decided only where its exact test agrees at the same level: Mann–Whitney for",
        "independent runs (`gchgg/analysis/exact.py`: the permutation distribution of P(A beats B), censoring",
        "included; averaged over tasks with each task's runs relabelled apart for a pooled claim), Wilcoxon",
        "signed-rank and the sign test, both, for paired forks. 3 runs against 3 cannot give p below 0.10, so",
        "such a comparison stays undecided. An \"equal\" (alike) claim holds on its interval alone. \"fails",
        "within W\" holds only on runs that ran W iterations (a shorter run reads \"tested to N\"); \"stopped early\"",
        "means ended by the stop rule (its last 5 evaluations ≥ 0.9 before the budget), not a run that hit its",
        "own cap; a success rate is never carried past a run's last row, so a claim on the rate at the budget's",
        "end is undecided while a run ended before it.",
        f"\"by N\" claims hold up to N + {100 * slack:g} %. Paired forks (`<task>/<subfolder>/`, runs paired by seed):",
        f"the mean paired difference with a bootstrap interval over pairs, undecided below {min_pairs} pairs.",
        "A claim whose runs lie elsewhere (Fig. 6: `fig6/<ablation>/<value>-seed<N>.csv` against the default runs)",
        "names their files in claims.yaml (`runs:`); each is scored under its claim's task's budget. A pooled claim",
        "averages P(A beats B) over its tasks (rliable's average probability of improvement, each task's runs",
        "resampled apart) and is read once, when each task has the runs claims.yaml plans for it.",
        "",
        "| id | claim | paper | measured | verdict |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        verdict = f"**{r.verdict}**" + (f": {r.reason}" if r.reason else "")
        lines.append(f"| {r.claim.id} | {cell(r.claim.claim)} | {cell(r.claim.paper)} | {cell(r.measured)} "
                     f"| {cell(verdict)} |")
    lines += ["", "Verdicts:", "", *summary(rows), ""]
    return "\n".join(lines)


# --- The README's results block -------------------------------------------------------------------------------
# Self-contained: it reads the claims' verdicts (verdicts, summary) and the runs' scores (measure) as they are,
# whatever the verdict rules; the README's test checks the committed block against readme_results.

README_BEGIN, README_END = "<!-- results:begin -->", "<!-- results:end -->"
README_METHODS = ("her", "hgg", "cher", "ghgg", "gchgg")
"""The README table's columns: Fig. 5's methods, in the paper's order."""
README_COMMAND = "python -m gchgg.analysis.claims docs/results --readme README.md"


def _readme_cell(scores: plot.Scores | None) -> str:
    """One method's first ≥ 0.9 on one task: IQM [95 % CI] and n, or that no run reached 0.9."""
    if scores is None:
        return "—"
    never = int(scores.censored.sum())
    if never == scores.runs:
        return f"none of {scores.runs} by {max(scores.censored_at)}"
    estimate = stats.iqm_interval(scores.first, alpha=stats.ALPHA)
    tail = f", {never} never" if never else ""
    return f"{estimate.format(1)}, n = {scores.runs}{tail}"


def readme_results(results: str | Path, claims_path: str | Path | None = None,
                   readme_dir: str | Path = ".") -> str:
    """The README's results block, markers included: per task, each Fig. 5 method's first ≥ 0.9 (IQM [95 %
    CI], n runs; :mod:`gchgg.analysis.stats`) and the count of the task's claims by verdict, then the verdict
    lines of :func:`summary`. Links are written relative to ``readme_dir`` (the README's folder)."""
    import os

    import yaml

    results = Path(results)
    claims_path = Path(claims_path) if claims_path else results / "claims.yaml"
    loaded, settings = load_claims(claims_path)
    names = (yaml.safe_load(claims_path.read_text()) or {}).get("names") or {}
    rows = verdicts(results, loaded, **settings)
    tasks = list(dict.fromkeys(r.claim.task for r in rows))
    link = Path(os.path.relpath(results, readme_dir)).as_posix()
    header = ["task (budget)", *(names.get(m, m) for m in README_METHODS), "claims: " + " / ".join(VERDICTS)]
    lines = [
        README_BEGIN,
        f"<!-- written by `{README_COMMAND}`; do not edit by hand -->",
        "",
        f"Each method's first ≥ {plot.THRESHOLD}, the first iteration at an evaluation success rate ≥ "
        f"{plot.THRESHOLD}: interquartile mean",
        "[95 % bootstrap CI] over its n seeds (`<task>/<method>-seed<N>.csv`). A seed that never got there "
        "counts one past",
        "its budget or its end; \"none of n by N\": no seed did within N iterations. Last column: the claims "
        "about the task",
        f"by verdict (each with its measured figure and reason: [claims.md]({link}/claims.md)).",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "---|" * len(header),
    ]
    for task in tasks:
        scores, _ = measure(results, task)
        budget = max((max(s.budgets) for s in scores.values()), default=None)
        label = f"{task} ({budget})" if budget else f"{task} (claims over several tasks)"
        counts = [sum(r.verdict == v and r.claim.task == task for r in rows) for v in VERDICTS]
        cells = [_readme_cell(scores.get(m)) if scores else "" for m in README_METHODS]
        lines.append("| " + " | ".join([label, *cells, " / ".join(map(str, counts))]) + " |")
    lines += ["", f"<details><summary>The {len(rows)} claims by verdict</summary>", "", *summary(rows), "",
              "</details>", README_END]
    return "\n".join(lines)


def replace_block(text: str, block: str) -> str:
    """``text`` with the block between the README markers (markers included) replaced by ``block``."""
    begin, end = text.find(README_BEGIN), text.find(README_END)
    if begin < 0 or end < begin:
        raise ValueError(f"no {README_BEGIN} ... {README_END} block; add the two markers where the results go")
    return text[:begin] + block + text[end + len(README_END):]


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", help="the folder holding a folder of runs per task (docs/results)")
    parser.add_argument("--claims", help="the claims' YAML file; default: <results>/claims.yaml")
    parser.add_argument("--out", help="the Markdown file to write (printed either way)")
    parser.add_argument("--readme", help="rewrite this README's results block (between the markers "
                        f"{README_BEGIN} and {README_END}) and print the block instead of the table")
    args = parser.parse_args(argv)
    results = Path(args.results)
    if not results.is_dir():
        parser.error(f"results {args.results}: not a folder; pass the folder holding <task>/ folders of runs")
    claims_path = Path(args.claims) if args.claims else results / "claims.yaml"
    if not claims_path.is_file():
        parser.error(f"--claims {claims_path}: no such file; pass the claims' YAML file")
    claims, settings = load_claims(claims_path)
    rows = verdicts(results, claims, **settings)
    command = f"python -m gchgg.analysis.claims {args.results}" + (
        f" --claims {args.claims}" if args.claims else "") + (
        f" --out {args.out}" if args.out else "")
    text = render(rows, command, **settings)
    if args.out:
        Path(args.out).write_text(text)
    if args.readme:
        readme = Path(args.readme)
        if not readme.is_file():
            parser.error(f"--readme {args.readme}: no such file")
        block = readme_results(results, claims_path, readme.resolve().parent)
        try:
            readme.write_text(replace_block(readme.read_text(), block))
        except ValueError as error:
            parser.error(f"--readme {args.readme}: {error}")
        print(block)
        return
    print(text, end="")


if __name__ == "__main__":
    main()
