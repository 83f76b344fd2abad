"""The claims table: each of the paper's claims (a hand-written YAML list) against the committed runs, with a verdict.

    python -m gchgg.analysis.claims docs/results --out docs/results/claims.md [--claims docs/results/claims.yaml]
    python -m gchgg.analysis.claims docs/results --readme README.md   # the README's results block (readme_results)

Reads the runs of each claim's task from the files ``<results>/<task>/<group>-seed<N>.csv`` (every seed
there; not ``unfinished/`` nor ``invalid/``), or, for a claim with ``runs`` (a mapping of each of its
groups to a glob under ``<results>``, e.g. Fig. 6's ablations against the default runs: ``{"500":
fig6/eta/500-seed*.csv, gchgg: pick_no_obstacle/gchgg-seed[012].csv}``), from those files, every run
taken as one of the claim's task (its budget); and scores them as :mod:`gchgg.analysis.plot` does (first ≥ 0.9: a run
that never got there is censored at its budget or its end, whichever comes first, and counted one
past it; no success rate carried past a run's last row) and writes a Markdown table: per
claim the claim, the paper's figure, the measured one (IQM [95 % CI] or a probability of improvement
[95 % CI], :mod:`gchgg.analysis.stats`; the runs it rests on) and a verdict, *holds*, *contradicted* or
*undecided*, with its reason. Below the table, one line per verdict lists its claims: the lines the
README quotes.

A claim's ``kind`` sets what is measured and the verdict's rule: :mod:`gchgg.analysis.verdicts`.

An entry with a list of ``groups`` (or of ``than``) is one claim per member; ``{name}`` and
``{than}`` in its ``claim`` are replaced by the display names of ``names``.
"""

from __future__ import annotations

import argparse
import itertools
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gchgg.analysis import plot, stats
from gchgg.analysis.verdicts import (
    COMPARISONS,
    KINDS,
    LOOKS_KINDS,
    SCORES,
    VERDICTS,
    Claim,
    Row,
    ended_by_stop_rule,
    judge,
    judge_paired,
    judge_pooled,
    measure_groups,
    seed_files,
)

__all__ = ["Claim", "Row", "ended_by_stop_rule", "judge", "judge_paired", "judge_pooled", "load_claims", "main",
           "measure", "measure_globs", "readme_results", "render", "replace_block", "seed_files", "summary", "verdicts"]


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



def measure(results: str | Path, task: str) -> tuple[dict[str, plot.Scores], dict[str, tuple[np.ndarray, int, int]]]:
    """The runs of ``<results>/<task>/<group>-seed<N>.csv`` by group: their :class:`gchgg.analysis.plot.Scores` (the
    AUC's range common to all the task's groups), and each run's success rate at the last iteration of
    its budget (held past its end) with how many runs stopped early by the stop rule (reached 0.9 and
    ended before their budget) and the budget's last iteration. Empty if there are no such files."""
    groups = _task_runs(results, task)
    return measure_groups(groups) if groups else ({}, {})


def measure_globs(results: str | Path, task: str, runs: Sequence[tuple[str, str]]) -> tuple[dict, dict]:
    """As :func:`measure`, for the runs of each ``(group, glob)`` of ``runs``: the CSVs under ``results``
    that match the glob, each taken as a run of ``task`` (its budget) labelled ``group``."""
    groups = _glob_runs(results, task, runs)
    return measure_groups(groups) if groups else ({}, {})


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
            measured[key] = measure_groups(loaded[key]) if loaded[key] else ({}, {})
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
