"""The claims table (gchgg.analysis.claims): each verdict rule on synthetic runs, and the committed table up to date."""

from __future__ import annotations

from pathlib import Path

import pytest

from gchgg.analysis import claims

REPO = Path(__file__).resolve().parents[1]


def write_csv(path, success):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("iteration,success_rate\n" + "".join(f"{i},{s}\n" for i, s in enumerate(success)))


def reaching(at, length=20, level=1.0):
    """Success 0 before iteration ``at``, ``level`` from it on."""
    return [0.0] * at + [level] * (length - at)


CLAIMS = """
min_runs: 3
slack: 0.1
names: {fast: Fast, slow: Slow}
claims:
  - {id: by-fast, task: toy, kind: reaches_by, groups: [fast], by: 5, claim: "{name} by 5", paper: "5"}
  - {id: by-slow, task: toy, kind: reaches_by, groups: [slow], by: 5, claim: "{name} by 5", paper: "5"}
  - {id: by-mixed, task: toy, kind: reaches_by, groups: [mixed], by: 10, claim: "{name} by 10", paper: "10"}
  - {id: fails, task: toy, kind: fails, groups: [never, flat, fast, few, absent], within: 20, claim: "{name} fails",
     paper: "-"}
  - {id: faster, task: toy, kind: faster, groups: [fast], than: [slow, fast], claim: "{name} beats {than}", paper: "x"}
  - {id: slower, task: toy, kind: faster, groups: [slow], than: fast, claim: "{name} beats {than}", paper: "x"}
  - {id: sooner, task: toy, kind: faster, groups: [quick], than: late, claim: "{name} < {than}", paper: "x"}
  - {id: later, task: toy, kind: faster, groups: [late], than: quick, claim: "{name} < {than}", paper: "x"}
  - {id: final-fast, task: toy, kind: final, groups: [fast], level: 1.0, spread: 0.0, claim: "1.0", paper: "1.0"}
  - {id: final-low, task: toy, kind: final, groups: [fast], level: 0.5, spread: 0.1, claim: "0.5", paper: "0.5"}
  - {id: final-never, task: toy, kind: final, groups: [never], level: 0.9, spread: 0.05, claim: "0.9", paper: "0.9"}
  - {id: final-stopped, task: toy, kind: final, groups: [stopped], level: 0.99, spread: 0.01, claim: "0.99",
     paper: "0.99"}
  - {id: elsewhere, task: missing_task, kind: fails, groups: [fast], within: 20, claim: "-", paper: "-"}
"""


@pytest.fixture
def results(tmp_path):
    toy = tmp_path / "toy"  # no Fig. 5 experiment: the budget is the longest run, 20 iterations
    for seed, at in enumerate([3, 4, 5]):
        write_csv(toy / f"fast-seed{seed}.csv", reaching(at))
    for seed, at in enumerate([15, 16, 17]):
        write_csv(toy / f"slow-seed{seed}.csv", reaching(at))
    for seed, at in enumerate([3, 10, 17]):
        write_csv(toy / f"mixed-seed{seed}.csv", reaching(at))
    for seed in range(3):
        write_csv(toy / f"never-seed{seed}.csv", [0.0] * (20 - 5 * seed))  # censored at 20, 15, 10
        write_csv(toy / f"stopped-seed{seed}.csv", reaching(2, length=8, level=0.9))  # the stop rule ended it at 8
    for seed in range(4):
        write_csv(toy / f"quick-seed{seed}.csv", reaching(3 + seed))
        write_csv(toy / f"late-seed{seed}.csv", reaching(14 + seed))
        write_csv(toy / f"flat-seed{seed}.csv", [0.0] * 20)  # never reached 0.9, every run to the budget
    write_csv(toy / "few-seed0.csv", [0.0] * 20)
    (tmp_path / "claims.yaml").write_text(CLAIMS)
    return tmp_path


def test_each_rule_gives_its_verdict(results):
    loaded, settings = claims.load_claims(results / "claims.yaml")
    rows = {r.claim.id: r for r in claims.verdicts(results, loaded, **settings)}
    verdicts = {key: (r.verdict, r.reason) for key, r in rows.items()}
    assert verdicts["by-fast"] == ("holds", "CI ≤ 5.5 (5 + 10 %)")  # IQM of 3, 4, 5 and its CI within [3, 5]
    assert verdicts["by-slow"] == ("contradicted", "CI > 5.5 (5 + 10 %)")
    assert verdicts["by-mixed"] == ("undecided", "CI straddles 11 (10 + 10 %)")
    assert verdicts["fails-never"] == ("undecided", "no run reached 0.9, but 2 of 3 were tested to 10–20 "
                                                    "iterations, not 20")  # "fails within 20" needs 20 iterations
    assert verdicts["fails-flat"] == ("holds", "no run reached 0.9 in 20 iterations")
    assert verdicts["fails-fast"] == ("contradicted", "CI < 20")
    assert verdicts["fails-few"] == ("undecided", "few: 1 run (3 needed)")
    assert verdicts["fails-absent"] == ("undecided", "absent: 0 runs")
    assert rows["fails-absent"].measured == "—; 0 runs"
    # 3 runs against 3: the CI excludes 0.5, but the exact test cannot go below 0.10
    assert verdicts["faster-slow"] == ("undecided", "CI above 0.5, but Mann–Whitney p = 0.10 ≥ 0.05")
    assert verdicts["faster-fast"] == ("undecided", "CI contains 0.5")
    assert verdicts["slower"] == ("undecided", "CI below 0.5, but Mann–Whitney p = 0.10 ≥ 0.05")
    assert verdicts["sooner"] == ("holds", "CI above 0.5; p < 0.05")  # 4 against 4: p = 2/70
    assert verdicts["later"] == ("contradicted", "CI below 0.5; p < 0.05")
    assert verdicts["final-fast"] == ("holds", "CI inside [1.00, 1.00]")
    assert verdicts["final-low"] == ("contradicted", "CI above [0.40, 0.60]")
    assert verdicts["final-never"] == ("undecided", "2 of 3 runs ended before iteration 19 (2 ran out their own "
                                                    "cap): no success measured there")
    assert verdicts["final-stopped"] == ("undecided", "3 of 3 runs ended before iteration 19 (3 stopped early by "
                                                      "the stop rule): no success measured there")
    assert verdicts["elsewhere"] == ("undecided", "fast: 0 runs")
    assert rows["by-fast"].measured == "first ≥ 0.9 IQM 4.0 [3.0, 5.0]; 3 runs, 0 censored"
    assert rows["faster-slow"].measured == ("P(fast beats slow) on first ≥ 0.9: 1.00 [1.00, 1.00]; 3 vs 3 runs; "
                                            "Mann–Whitney p = 0.10")
    assert rows["final-stopped"].measured == ("last success IQM 0.90 [0.90, 0.90] (runs ended after 8 iterations, "
                                              "not at 19); 3 runs, 3 stopped early by the stop rule")
    assert rows["final-fast"].measured == "success at 19 IQM 1.00 [1.00, 1.00]; 3 runs"
    assert rows["faster-slow"].claim.claim == "Fast beats Slow"


def test_the_command_writes_the_table_and_its_verdict_lines(results, capsys):
    out = results / "claims.md"
    claims.main([str(results), "--out", str(out)])
    text = out.read_text()
    assert text == capsys.readouterr().out
    assert ("| by-fast | Fast by 5 | 5 | first ≥ 0.9 IQM 4.0 [3.0, 5.0]; 3 runs, 0 censored "
            "| **holds**: CI ≤ 5.5 (5 + 10 %) |") in text
    assert "- **contradicted** (4 of 18): toy: Slow by 5; Fast fails; late < quick; 0.5\n" in text


def test_only_the_task_folders_seed_files_are_read_every_seed_of_them(results):
    toy = results / "toy"
    write_csv(toy / "fast-seed3.csv", reaching(6))  # a fourth seed: read
    write_csv(toy / "unfinished" / "fast-seed4.csv", reaching(19))  # unfinished/: not read
    write_csv(toy / "invalid" / "fast-seed5.csv", [0.0] * 20)  # invalid/: not read
    write_csv(toy / "fast-diagnostic.csv", [0.0] * 20)  # not <group>-seed<N>.csv: not read
    assert [p.name for p in claims.seed_files(toy) if p.name.startswith("fast")] == [
        "fast-seed0.csv", "fast-seed1.csv", "fast-seed2.csv", "fast-seed3.csv"]
    scores, _ = claims.measure(results, "toy")
    assert scores["fast"].first.tolist() == [3, 4, 5, 6] and "fast-diagnostic" not in scores
    assert claims.measure(results, "missing_task") == ({}, {})


def test_a_claim_of_an_unknown_kind_or_without_its_figure_is_an_error(tmp_path):
    path = tmp_path / "claims.yaml"
    path.write_text("claims:\n  - {id: x, task: t, kind: sooner, groups: [a], claim: c, paper: p}\n")
    with pytest.raises(ValueError, match="claim x: kind 'sooner'; allowed: reaches_by, fails, final, faster"):
        claims.load_claims(path)
    path.write_text("claims:\n  - {id: x, task: t, kind: reaches_by, groups: [a], claim: c, paper: p}\n")
    with pytest.raises(ValueError, match="kind reaches_by needs by; by missing"):
        claims.load_claims(path)


def test_the_committed_claims_table_is_the_commands_output_and_the_readme_quotes_its_verdicts():
    """After adding runs, regenerate it: python -m gchgg.analysis.claims docs/results --out docs/results/claims.md"""
    loaded, settings = claims.load_claims(REPO / "docs/results/claims.yaml")
    rows = claims.verdicts(REPO / "docs/results", loaded, **settings)
    text = claims.render(rows, "python -m gchgg.analysis.claims docs/results --out docs/results/claims.md", **settings)
    committed = (REPO / "docs/results/claims.md").read_text()
    assert text == committed, "docs/results/claims.md is stale: regenerate it with the command above"
    readme = (REPO / "README.md").read_text()
    lines = [line for line in committed.splitlines() if line.startswith("- **")]  # the verdict lines
    assert len(lines) == 3
    for line in lines:
        assert line in readme, f"README.md does not quote claims.md's verdict line {line[:40]!r}"


def test_paired_forks_are_judged_by_the_mean_paired_difference(tmp_path):
    """faster_paired: forks paired by seed in <task>/<pairs>/; holds when the CI of A − B lies below 0,
    undecided below min_pairs pairs or when the CI contains 0."""
    forks = tmp_path / "toy" / "forks"
    for seed in range(8):  # A reaches 0.9 two iterations before B in every pair, from seed-dependent starts
        write_csv(forks / f"a-seed{seed}.csv", reaching(5 + seed % 3))
        write_csv(forks / f"b-seed{seed}.csv", reaching(7 + seed % 3))
        write_csv(forks / f"c-seed{seed}.csv", reaching(5 + seed % 3 + (1 if seed % 2 else -1)))  # a: ahead, behind
    write_csv(forks / "b-seed9.csv", reaching(3))  # no partner: left out
    (tmp_path / "claims.yaml").write_text("""
min_pairs: 8
claims:
  - {id: p, task: toy, kind: faster_paired, groups: [a], than: [b, c], pairs: forks, claim: "{name} < {than}",
     paper: "x"}
""")
    loaded, settings = claims.load_claims(tmp_path / "claims.yaml")
    rows = {r.claim.id: r for r in claims.verdicts(tmp_path, loaded, **settings)}
    assert rows["p-b"].verdict == "holds" and "mean -2.0 [-2.0, -2.0]; 8 pairs" in rows["p-b"].measured
    assert rows["p-c"].verdict == "undecided" and rows["p-c"].reason == "CI contains 0"
    settings["min_pairs"] = 9
    rows = {r.claim.id: r for r in claims.verdicts(tmp_path, loaded, **settings)}
    assert rows["p-b"].verdict == "undecided" and rows["p-b"].reason == "8 pairs (9 needed)"


def test_a_claim_reads_its_groups_from_the_globs_it_names_under_its_tasks_budget(tmp_path):
    """runs: each group's CSVs from a glob (Fig. 6's ablations against the default runs elsewhere), every
    run scored as one of the claim's task; alike: holds when P(A beats B)'s CI lies in 0.5 ± margin."""
    for seed, at in enumerate([3, 4, 5, 6]):
        write_csv(tmp_path / "toy" / f"base-seed{seed}.csv", reaching(at))
        write_csv(tmp_path / "ablation" / "slow" / f"x-seed{seed}.csv", reaching(at + 10))
        write_csv(tmp_path / "ablation" / "same" / f"x-seed{seed}.csv", reaching(at))
    write_csv(tmp_path / "toy" / "base-seed4.csv", reaching(19))  # left out by the glob below
    (tmp_path / "claims.yaml").write_text("""
names: {base: Base, "slow": Slow}
claims:
  - {id: f, task: toy, kind: faster, groups: [base], than: [slow, same], claim: "{name} < {than}", paper: "x",
     runs: {base: "toy/base-seed[0-3].csv", slow: "ablation/slow/*.csv", same: "ablation/same/*.csv"}}
  - {id: a, task: toy, kind: alike, groups: [base], than: [slow, same], margin: 0.25, claim: "{name} ~ {than}",
     paper: "x", runs: {base: "toy/base-seed[0-3].csv", slow: "ablation/slow/*.csv", same: "ablation/same/*.csv"}}
""")
    loaded, settings = claims.load_claims(tmp_path / "claims.yaml")
    rows = {r.claim.id: r for r in claims.verdicts(tmp_path, loaded, **settings)}
    assert rows["f-slow"].verdict == "holds" and rows["f-slow"].claim.claim == "Base < Slow"
    assert rows["f-slow"].measured == ("P(base beats slow) on first ≥ 0.9: 1.00 [1.00, 1.00]; 4 vs 4 runs; "
                                       "Mann–Whitney p = 0.029")  # 2 of 70 splits as extreme
    assert rows["f-same"].verdict == "undecided"
    assert (rows["a-slow"].verdict, rows["a-slow"].reason) == (
        "contradicted", "CI outside [0.25, 0.75], excluding 0.5; p < 0.05")
    assert rows["a-same"].verdict == "undecided" and rows["a-same"].reason.startswith("CI contains 0.5")
    scores, _ = claims.measure_globs(tmp_path, "toy", [("slow", "ablation/slow/*.csv")])
    assert scores["slow"].first.tolist() == [13, 14, 15, 16]


def test_score_auc_compares_the_areas_under_the_curves(tmp_path):
    """score: auc reads the mean success over the groups' common range (higher is better): a group that
    crosses 0.9 later but holds a higher level before it wins on the area and loses on first >= 0.9."""
    toy, forks = tmp_path / "toy", tmp_path / "toy" / "forks"
    for seed in range(8):
        early = [0.0] * (4 + seed % 2) + [0.9] * 15  # first >= 0.9 at 4 or 5, then 0.9
        high = [0.85] * (6 + seed % 2) + [0.95] * 13  # 0.85 from the start, first >= 0.9 at 6 or 7
        for folder in (toy, forks):
            write_csv(folder / f"early-seed{seed}.csv", early)
            write_csv(folder / f"high-seed{seed}.csv", high)
    (tmp_path / "claims.yaml").write_text("""
min_pairs: 8
claims:
  - {id: f, task: toy, kind: faster, groups: [high], than: early, claim: "c", paper: "x"}
  - {id: a, task: toy, kind: faster, groups: [high], than: early, score: auc, claim: "c", paper: "x"}
  - {id: pf, task: toy, kind: faster_paired, groups: [high], than: early, pairs: forks, claim: "c", paper: "x"}
  - {id: pa, task: toy, kind: faster_paired, groups: [high], than: early, pairs: forks, score: auc, claim: "c",
     paper: "x"}
""")
    loaded, settings = claims.load_claims(tmp_path / "claims.yaml")
    rows = {r.claim.id: r for r in claims.verdicts(tmp_path, loaded, **settings)}
    assert (rows["f"].verdict, rows["a"].verdict) == ("contradicted", "holds")
    assert rows["a"].measured == ("P(high beats early) on AUC over iterations 0–19: 1.00 [1.00, 1.00]; 8 vs 8 runs; "
                                  "Mann–Whitney p = 0.00016")  # 2 of 12,870 splits
    assert (rows["pf"].verdict, rows["pa"].verdict) == ("contradicted", "holds")
    assert rows["pa"].reason == "CI above 0; both p < 0.05"
    assert rows["pa"].measured.endswith("8 pairs; Wilcoxon p = 0.0078, sign test p = 0.0078")  # 2 of 256 flips
    assert "on AUC over iterations 0–19, paired forks: mean " in rows["pa"].measured


@pytest.mark.parametrize("entry, message", [
    ("{id: x, task: t, kind: faster, groups: [a], than: b, claim: c, paper: p, runs: {a: 'f/*.csv'}}",
     "claim x: runs names no glob for b"),
    ("{id: x, task: t, kind: reaches_by, by: 5, score: auc, groups: [a], claim: c, paper: p}",
     "claim x: score 'auc' with kind reaches_by; allowed: first, auc with faster"),
])
def test_a_claim_with_runs_missing_a_group_or_a_score_its_kind_cannot_read_is_an_error(tmp_path, entry, message):
    path = tmp_path / "claims.yaml"
    path.write_text(f"claims:\n  - {entry}\n")
    with pytest.raises(ValueError, match=message):
        claims.load_claims(path)


def assert_wider(row, than):
    """The interval in ``row``'s measured figure contains ``than``'s and differs from it."""
    def interval(r):
        low, high = r.measured.split(" [")[1].split("]")[0].split(", ")
        return float(low), float(high)

    (low, high), (wide_low, wide_high) = interval(than), interval(row)
    assert wide_low <= low and wide_high >= high and (wide_low, wide_high) != (low, high)


def test_looks_give_a_faster_claim_pococks_interval_and_runs_off_the_looks_leave_it_undecided(tmp_path):
    from gchgg.analysis import stats

    toy = tmp_path / "toy"
    for seed, (a, b) in enumerate(zip([2, 3, 2, 4, 1, 3, 2, 5], [3, 2, 4, 3, 4, 5, 3, 4], strict=True)):
        write_csv(toy / f"a-seed{seed}.csv", reaching(a, length=8))
        write_csv(toy / f"b-seed{seed}.csv", reaching(b, length=8))
    (tmp_path / "claims.yaml").write_text("""
claims:
  - {id: plain, task: toy, kind: faster, groups: [a], than: b, claim: "c", paper: "x"}
  - {id: looked, task: toy, kind: faster, groups: [a], than: b, looks: [6, 7, 8, 9, 10], claim: "c", paper: "x"}
  - {id: unplanned, task: toy, kind: faster, groups: [a], than: b, looks: [4, 6], claim: "c", paper: "x"}
""")
    loaded, settings = claims.load_claims(tmp_path / "claims.yaml")
    rows = {r.claim.id: r for r in claims.verdicts(tmp_path, loaded, **settings)}
    level = 100 * (1 - stats.sequential_alpha([6, 7, 8, 9, 10]))
    assert f" ({level:.1f} % CI, Pocock's for looks at 6-10 runs); 8 vs 8 runs" in rows["looked"].measured
    assert_wider(rows["looked"], than=rows["plain"])
    assert rows["unplanned"].verdict == "undecided"
    assert rows["unplanned"].reason == "8 and 8 runs: not a look of the design (4, 6 runs each)"
    for looks, kind in [("[4, 3]", "faster"), ("[3]", "fails")]:
        (tmp_path / "bad.yaml").write_text(f"claims:\n  - {{id: x, task: t, kind: {kind}, groups: [a], than: b, "
                                           f"within: 5, looks: {looks}, claim: c, paper: p}}\n")
        with pytest.raises(ValueError, match=f"claim x: looks .* with kind {kind}; allowed with reaches_by, "
                                             "final, faster, alike"):
            claims.load_claims(tmp_path / "bad.yaml")


@pytest.mark.parametrize("kind, fields", [("reaches_by", "by: 4"), ("final", "level: 0.99, spread: 0.01")])
def test_looks_give_a_one_group_claim_pococks_interval_and_runs_off_the_looks_leave_it_undecided(
        tmp_path, kind, fields):
    from gchgg.analysis import stats

    toy = tmp_path / "toy"
    for seed, (first, end) in enumerate(zip([2, 3, 2, 4, 1, 3, 2, 5], [0.9, 1.0, 0.95, 0.9, 1.0, 0.92, 0.97, 0.9],
                                            strict=True)):
        rows = reaching(first, length=8)
        rows[-1] = end
        write_csv(toy / f"a-seed{seed}.csv", rows)
    (tmp_path / "claims.yaml").write_text(f"""
claims:
  - {{id: plain, task: toy, kind: {kind}, {fields}, groups: [a], claim: "c", paper: "x"}}
  - {{id: looked, task: toy, kind: {kind}, {fields}, groups: [a], looks: [6, 7, 8, 9, 10], claim: "c", paper: "x"}}
  - {{id: unplanned, task: toy, kind: {kind}, {fields}, groups: [a], looks: [4, 6], claim: "c", paper: "x"}}
""")
    loaded, settings = claims.load_claims(tmp_path / "claims.yaml")
    rows = {r.claim.id: r for r in claims.verdicts(tmp_path, loaded, **settings)}
    level = 100 * (1 - stats.sequential_alpha([6, 7, 8, 9, 10]))
    assert f"] ({level:.1f} % CI, Pocock's for looks at 6-10 runs); 8 runs" in rows["looked"].measured
    assert "Pocock" not in rows["plain"].measured
    assert_wider(rows["looked"], than=rows["plain"])
    assert rows["unplanned"].verdict == "undecided"
    assert rows["unplanned"].reason == "8 runs: not a look of the design (4, 6 runs)"


def test_a_pooled_claim_averages_the_tasks_and_is_read_only_at_its_planned_runs(tmp_path):
    # t1: a first at 2, 3, 2 against b at 5, 6, 7 (a wins every pair); t2: a at 6, 7, 5 against b at 2, 3, 2
    # (b wins every pair); t3: four runs of each, a at 2, 3, 2, 3 against b at 5, 6, 6, 4 (a wins every pair)
    for task, a, b in [("t1", [2, 3, 2], [5, 6, 7]), ("t2", [6, 7, 5], [2, 3, 2]), ("t3", [2, 3, 2, 3], [5, 6, 6, 4])]:
        for seed, at in enumerate(a):
            write_csv(tmp_path / task / f"a-seed{seed}.csv", reaching(at, length=8))
        for seed, at in enumerate(b):
            write_csv(tmp_path / task / f"b-seed{seed}.csv", reaching(at, length=8))
    write_csv(tmp_path / "t4" / "a-seed0.csv", reaching(2, length=8))  # no runs of b
    (tmp_path / "claims.yaml").write_text("""
claims:
  - {id: even, task: both, kind: faster_pooled, tasks: {t1: 3, t2: 3}, groups: [a], than: b, claim: c, paper: p}
  - {id: ahead, task: both, kind: faster_pooled, tasks: {t1: 3, t3: 4}, groups: [a], than: b, claim: c, paper: p}
  - {id: early, task: both, kind: faster_pooled, tasks: {t1: 3, t3: 3}, groups: [a], than: b, claim: c, paper: p}
  - {id: area, task: both, kind: faster_pooled, score: auc, tasks: {t1: 3, t2: 3}, groups: [a], than: b,
     claim: c, paper: p}
  - {id: missing, task: both, kind: faster_pooled, tasks: {t1: 3, t4: 3}, groups: [a], than: b, claim: c, paper: p}
""")
    loaded, settings = claims.load_claims(tmp_path / "claims.yaml")
    rows = {r.claim.id: r for r in claims.verdicts(tmp_path, loaded, **settings)}
    assert rows["even"].measured == ("P(a beats b) on first ≥ 0.9, averaged over 2 tasks: 0.50 [0.50, 0.50]; "
                                     "t1 3 vs 3, t2 3 vs 3 runs; stratified Mann–Whitney p = 1.00")
    assert (rows["even"].verdict, rows["even"].reason) == ("undecided", "CI contains 0.5")
    assert rows["area"].measured.startswith("P(a beats b) on AUC (each task over its two groups' common range), "
                                            "averaged over 2 tasks: 0.50 [0.50, 0.50]")
    assert rows["ahead"].measured.startswith("P(a beats b) on first ≥ 0.9, averaged over 2 tasks: 1.00 [1.00, 1.00]")
    assert (rows["ahead"].verdict, rows["ahead"].reason) == ("holds", "CI above 0.5; p < 0.05")
    assert rows["ahead"].measured.endswith("stratified Mann–Whitney p = 0.0014")  # 2 of 20 · 70 relabellings
    assert (rows["early"].verdict, rows["early"].reason) == (
        "undecided", "read once, at t1 3, t3 3 runs of each; now t3 4 and 4")
    assert rows["missing"].measured == "—; t1 3 vs 3, t4 1 vs 0 runs"
    assert (rows["missing"].verdict, rows["missing"].reason) == ("undecided", "t4: a: 1 run; b: 0 runs (3 needed)")
    for tasks in ("{t1: 3}", "{t1: 0, t2: 3}", "[t1, t2]"):
        (tmp_path / "bad.yaml").write_text(f"claims:\n  - {{id: x, task: t, kind: faster_pooled, tasks: {tasks}, "
                                           "groups: [a], than: b, claim: c, paper: p}\n")
        with pytest.raises(ValueError, match="claim x: tasks .* with kind faster_pooled; allowed: a mapping of two "
                                             "or more tasks"):
            claims.load_claims(tmp_path / "bad.yaml")


def test_stopped_early_means_the_stop_rule_ended_the_run_not_its_cap(tmp_path):
    """pick_obstacle's gchgg-seed2 ran its whole 300-iteration cap of a 400 budget at 0.88: not stopped early."""
    def run(success):
        write_csv(tmp_path / "r-seed0.csv", success)
        from gchgg.analysis import plot
        return plot.load_run(tmp_path / "r-seed0.csv")

    assert claims.ended_by_stop_rule(run(reaching(5, length=12, level=0.9)), budget=20)  # 7 rows >= 0.9, then ended
    assert not claims.ended_by_stop_rule(run([0.0] * 8 + [0.9, 0.92, 0.95, 0.88]), budget=20)  # its cap, at 0.88
    assert not claims.ended_by_stop_rule(run([0.0] * 8 + [0.9] * 4), budget=20)  # 4 rows >= 0.9: not the rule's 5
    assert not claims.ended_by_stop_rule(run(reaching(5, length=20)), budget=20)  # ran to the budget
