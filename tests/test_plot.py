"""Curves and tables over seeds (gchgg.analysis.plot) on hand-made run folders: grouping, medians, quartiles."""

from __future__ import annotations

import csv
import math

import pytest

from gchgg.analysis import plot


def make_run(folder, algo, seed, success, scale="raw", extra=None):
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(
        f"seed: {seed}\nenv:\n  name: push_new\nalgo:\n  name: {algo}\ncurriculum:\n  scale: {scale}\n"
        f"logging:\n  progress: false\n"
    )
    with open(folder / "metrics.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["iteration", "success_rate", "seconds_update", *(extra or {})])
        for i, s in enumerate(success):
            writer.writerow([i, s, 360.0, *(v[i] for v in (extra or {}).values())])


@pytest.fixture
def sweep(tmp_path):
    make_run(tmp_path / "a0", "ghgg", 0, [0.0, 0.5, 0.9, 0.95])
    make_run(tmp_path / "a1", "ghgg", 1, [0.0, 0.2, 0.6, 0.7])
    make_run(tmp_path / "a2", "ghgg", 2, [0.0, 0.0, 0.1])  # shorter: held at 0.1
    make_run(tmp_path / "b0", "gchgg", 0, [0.1, 0.9, 1.0],
             extra={"diversity_decided": [0.2, 0.4, 0.6], "stopped": [0, 0, 1], "d_g": [0.5, 0.4, 0.0]})
    make_run(tmp_path / "b1", "gchgg", 1, [0.0, 0.0, 0.5], scale="standardized")
    return tmp_path


def test_runs_are_grouped_by_the_settings_that_differ(sweep):
    groups = plot.group_runs(plot.find_runs([sweep]))
    assert sorted(label for _, label in groups) == [
        "gchgg, curriculum.scale=raw", "gchgg, curriculum.scale=standardized", "ghgg, curriculum.scale=raw"]
    assert [r.settings["seed"] for r in groups["push_new", "ghgg, curriculum.scale=raw"]] == ["0", "1", "2"]


def test_medians_quartiles_and_first_iterations(sweep):
    groups = plot.group_runs(plot.find_runs([sweep]))
    runs = groups["push_new", "ghgg, curriculum.scale=raw"]
    values = plot.curves(runs, "success_rate")
    assert values[2].tolist() == [0.0, 0.0, 0.1, 0.1]  # held at its last value
    assert plot.iqr(values[:, 3]) == pytest.approx((0.7, 0.4, 0.825))
    assert [plot.first_at(r, 0.5) for r in runs] == [1, 2, math.inf]
    assert plot.iqr([1, 2, math.inf]) == (2.0, 1.5, math.inf)
    text = plot.table(groups, at=(1, 3))
    row = next(line for line in text.splitlines() if "| ghgg" in line)
    assert "| 3 | 2 [1.5, never] (2/3) | never [never, never] (1/3) | 0.20 [0.10, 0.35] | 0.70 [0.40, 0.82] |" in row
    # no HGG stop logged; hours: 4, 4, 3 rows of 360 s; each iteration 360 s
    assert row.endswith("| — | — | — | 0.40 [0.35, 0.40] | 360.0 [360.0, 360.0] |")
    # past every run's end (iterations 0-3) each run counts with its last value: the final column's figures
    past = next(line for line in plot.table(groups, at=(9,)).splitlines() if "| ghgg" in line)
    assert "| 0.70 [0.40, 0.82] | 0.70 [0.40, 0.82] |" in past
    gchgg = next(line for line in text.splitlines() if "gchgg, curriculum.scale=raw" in line)
    # HGG stop at iteration 2, 0.9 first reached at 1 (before it); diversity_decided averaged before the stop
    assert "| 2 [2, 2] | -1 [-1, -1] | 0.30 |" in gchgg


def test_csv_files_group_by_name_and_the_cli_writes_figure_and_table(tmp_path, capsys):
    for seed, rates in enumerate([[0.0, 1.0], [0.0, 0.5]]):
        with open(tmp_path / f"her-seed{seed}.csv", "w") as f:
            f.write("iteration,success_rate\n" + "".join(f"{i},{r}\n" for i, r in enumerate(rates)))
    plot.main([str(tmp_path / "her-seed0.csv"), str(tmp_path / "her-seed1.csv"), "--out", str(tmp_path / "f.png"),
               "--table", str(tmp_path / "t.md"), "--at", "1"])
    assert (tmp_path / "f.png").stat().st_size > 1000
    text = (tmp_path / "t.md").read_text()
    assert f"| {tmp_path.name} | her | 2 | 1 [1, 1] (2/2) | never [never, never] (1/2) | 0.75 [0.62, 0.88] |" in text
    assert "her" in capsys.readouterr().out


def test_a_folder_without_runs_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no metrics.csv under"):
        plot.find_runs([tmp_path])


def test_a_success_rate_of_exactly_90_of_100_reaches_0_9(tmp_path):
    """Runs before December 2026 wrote success rates as float32 means: 90 of 100 as 0.8999999762."""
    import torch

    as_float32 = torch.ones(100, dtype=torch.bool)
    as_float32[:10] = False
    written = as_float32.float().mean().item()
    assert written < 0.9  # the old value, below the threshold it stands for
    make_run(tmp_path / "old", "ghgg", 0, [0.5, written, 0.95])
    (run,) = plot.find_runs([tmp_path])
    assert plot.first_at(run, 0.9) == 1


def test_diagnostic_columns_are_tabulated_and_drawn_beside_success(sweep, capsys):
    """``--y d_g``: the d_g column at the chosen iterations; the thresholds stay on the success rate."""
    out = sweep / "diagnostics.png"
    plot.main([str(sweep / "b0"), "--y", "success_rate", "d_g", "--at", "1", "--out", str(out)])
    text = capsys.readouterr().out
    head, _, row = text.splitlines()[:3]
    cells = dict(zip((c.strip() for c in head.split("|")), (c.strip() for c in row.split("|")), strict=True))
    assert cells["first ≥ 0.5"] == "1 [1, 1] (1/1)"  # success 0.9 at 1, although d_g is 0.4 there
    assert cells["success_rate at 1"] == "0.90 [0.90, 0.90]" and cells["final success_rate"] == "1.00 [1.00, 1.00]"
    assert cells["d_g at 1"] == "0.40 [0.40, 0.40]" and cells["final d_g"] == "0.00 [0.00, 0.00]"
    assert cells["first ≥ 0.9 − HGG stop"] == "-1 [-1, -1]"
    import matplotlib.image

    assert matplotlib.image.imread(out).shape[0] > 1.8 * 4 * 110  # two rows of panels, 4 inches each at 110 dpi


def test_runs_without_a_column_are_left_out_of_its_statistics_and_an_unknown_column_is_an_error(sweep, capsys):
    groups = plot.group_runs(plot.find_runs([sweep / "b0", sweep / "a0"]))
    both = {"all": [run for runs in groups.values() for run in runs]}
    assert plot.iqr(plot.curves(both["all"], "d_g")[:, 1]) == (0.4, 0.4, 0.4)  # a0 has no d_g: not a NaN median
    with pytest.raises(SystemExit):
        plot.main([str(sweep), "--y", "d_gg"])
    assert ("--y d_gg: no run logged this column; the runs' columns are d_g, diversity_decided"
            in capsys.readouterr().err)


def write_csv(path, success):
    """A bare metrics CSV (no config beside it): iterations 0, 1, ... with these success rates."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("iteration,success_rate\n" + "".join(f"{i},{s}\n" for i, s in enumerate(success)))


def test_a_folder_of_csvs_is_its_runs_without_its_subfolders(tmp_path):
    write_csv(tmp_path / "push_new" / "gchgg-seed0.csv", [0.0, 1.0])
    write_csv(tmp_path / "push_new" / "gchgg-seed1.csv", [0.0, 0.5])
    write_csv(tmp_path / "push_new" / "unfinished" / "gchgg-seed2.csv", [0.0])  # not one of the folder's runs
    runs = plot.find_runs([tmp_path / "push_new"])
    assert [r.path.name for r in runs] == ["gchgg-seed0.csv", "gchgg-seed1.csv"]
    assert list(plot.group_runs(runs)) == [("push_new", "gchgg")]


def test_budgets_come_from_the_config_else_the_tasks_fig5_experiment_else_the_override(sweep, tmp_path):
    write_csv(tmp_path / "push_new" / "her-seed0.csv", [0.0])
    write_csv(tmp_path / "pick_obstacle" / "her-seed0.csv", [0.0])
    write_csv(tmp_path / "reach" / "her-seed0.csv", [0.0])
    write_csv(tmp_path / "elsewhere" / "her-seed0.csv", [0.0])
    push, pick, reach, other = (plot.load_run(tmp_path / t / "her-seed0.csv")
                                for t in ("push_new", "pick_obstacle", "reach", "elsewhere"))
    # conf/experiment/fig5_*.yaml
    assert [plot.budget_of(r) for r in (push, pick, reach, other)] == [200, 400, 15, None]
    assert plot.budget_of(pick, override=250) == 250
    configured = plot.load_run(sweep / "a0")
    configured.settings["train.iterations"] = "150"
    assert plot.budget_of(configured) == 150
    with pytest.raises(ValueError, match="--budget 0: .* allowed: 1 or more"):
        plot.budget_of(push, override=0)


def test_first_at_0_9_is_censored_at_the_budget_or_at_the_runs_own_end_and_counted_one_past_it(tmp_path):
    def run(success):
        write_csv(tmp_path / "r.csv", success)
        return plot.load_run(tmp_path / "r.csv")

    # reached at iteration 2 (0-based, as plot.first_at counts): observed
    assert plot.first_score(run([0.0, 0.5, 0.9, 1.0]), budget=10) == (2, False)
    # ran its whole budget of 4 iterations (0-3) without 0.9: censored at 4, counted at budget + 1 = 5
    assert plot.first_score(run([0.0, 0.5, 0.8, 0.8]), budget=4) == (5, True)
    # stayed at 0.00 and ended after 3 of its 10 iterations: censored at its own end, 3, counted at 4, not at 11
    assert plot.first_score(run([0.0, 0.0, 0.0]), budget=10) == (4, True)
    # reached 0.9 only at its budget's end or after it: censored at the budget, counted one past it
    assert plot.first_score(run([0.0, 0.0, 0.9]), budget=2) == (3, True)
    # stopped early by the stop rule after holding 0.9: observed, not censored
    assert plot.first_score(run([0.0, 0.95, 0.95]), budget=10) == (1, False)


def test_auc_is_the_mean_success_over_the_common_range_each_run_held_at_its_last_value(tmp_path):
    write_csv(tmp_path / "r.csv", [0.0, 0.5, 1.0])
    run = plot.load_run(tmp_path / "r.csv")
    assert plot.auc(run, 3) == pytest.approx(0.5)
    assert plot.auc(run, 5) == pytest.approx((0 + 0.5 + 1 + 1 + 1) / 5)  # held at 1.0 to iteration 4
    assert plot.auc(run, 2) == pytest.approx(0.25)  # only iterations 0 and 1


def test_the_table_gives_iqm_intervals_of_both_scores_and_the_censored_count(tmp_path, capsys):
    for seed, rates in enumerate([[0.0, 0.9, 1.0, 1.0], [0.0, 0.0, 0.9, 1.0], [0.0, 0.0, 0.0, 0.5]]):
        write_csv(tmp_path / "toy" / f"a-seed{seed}.csv", rates)
    plot.main([str(tmp_path / "toy"), "--at", "1"])
    head, _, row = capsys.readouterr().out.splitlines()[:3]
    cells = dict(zip((c.strip() for c in head.split("|")), (c.strip() for c in row.split("|")), strict=True))
    # task toy has no Fig. 5 experiment: the budget is its longest run, 4 iterations; the third run is
    # censored at 4 and counted at 5
    first = (1 + 2 + 5) / 3  # 3 runs: the IQM is their mean
    assert cells["first ≥ 0.9 IQM [95 % CI]"].startswith(f"{first:.1f} [")
    assert cells["censored"] == "1"
    auc = ((0 + 0.9 + 1 + 1) + (0 + 0 + 0.9 + 1) + (0 + 0 + 0 + 0.5)) / 12
    assert cells["AUC IQM [95 % CI]"].startswith(f"{auc:.3f} [") and cells["AUC IQM [95 % CI]"].endswith(" over 0-3")
    plot.main([str(tmp_path / "toy"), "--at", "1", "--budget", "2"])  # first >= 0.9 must come before iteration 2
    head, _, row = capsys.readouterr().out.splitlines()[:3]
    cells = dict(zip((c.strip() for c in head.split("|")), (c.strip() for c in row.split("|")), strict=True))
    # the second run's 0.9 at iteration 2 is past the budget: both it and the third are censored at 2, counted at 3
    assert cells["first ≥ 0.9 IQM [95 % CI]"] == f"{(1 + 3 + 3) / 3:.1f} [1.0, 3.0]" and cells["censored"] == "2"
    assert cells["AUC IQM [95 % CI]"].endswith(" over 0-1")  # R: the budget, 2


def test_compare_prints_the_probability_that_a_run_of_one_group_beats_one_of_the_other(tmp_path, capsys):
    for seed, (fast, slow) in enumerate([(1, 3), (2, 3), (1, None)]):
        write_csv(tmp_path / "toy" / f"fast-seed{seed}.csv", [0.0] * fast + [0.9] * (5 - fast))
        write_csv(tmp_path / "toy" / f"slow-seed{seed}.csv",
                  [0.0] * 5 if slow is None else [0.0] * slow + [0.95] * (5 - slow))
    write_csv(tmp_path / "other" / "fast-seed0.csv", [0.0, 1.0])
    plot.main([str(tmp_path / "toy"), str(tmp_path / "other"), "--compare", "fast", "slow"])
    out = capsys.readouterr().out.splitlines()
    # fast: 1, 2, 1 against slow: 3, 3, 5: every pair won; the AUCs: fast's are all larger
    assert out == ["other: no runs of slow",
                   "toy: P(fast beats slow) first >= 0.9: 1.00 [1.00, 1.00] (3 vs 3 runs); "
                   "AUC over iterations 0-4: 1.00 [1.00, 1.00]"]
    plot.main([str(tmp_path / "toy"), "--compare", "slow", "fast"])
    assert capsys.readouterr().out.startswith("toy: P(slow beats fast) first >= 0.9: 0.00 [0.00, 0.00] (3 vs 3 runs)")
    with pytest.raises(SystemExit):
        plot.main([str(tmp_path / "toy"), "--compare", "fast", "her"])
    assert "--compare fast her: no group 'her'; the groups are fast, slow" in capsys.readouterr().err


def test_compare_over_several_tasks_adds_their_average_and_looks_leave_it_out(tmp_path, capsys):
    # ahead: a first at 1, 2 against b at 3, 4, 3 (a wins every pair); behind: a at 4, 3 against b at 1, 2
    for task, a, b in [("ahead", [1, 2], [3, 4, 3]), ("behind", [4, 3], [1, 2])]:
        for seed, at in enumerate(a):
            write_csv(tmp_path / task / f"a-seed{seed}.csv", [0.0] * at + [1.0] * (6 - at))
        for seed, at in enumerate(b):
            write_csv(tmp_path / task / f"b-seed{seed}.csv", [0.0] * at + [1.0] * (6 - at))
    plot.main([str(tmp_path / "ahead"), str(tmp_path / "behind"), "--compare", "a", "b"])
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 3  # 1 and 0 in every resample: the average is 0.5 in each
    assert out[2] == "averaged over ahead, behind: P(a beats b) first >= 0.9: 0.50 [0.50, 0.50]; AUC: 0.50 [0.50, 0.50]"
    write_csv(tmp_path / "ahead" / "a-seed2.csv", [0.0] * 2 + [1.0] * 4)
    write_csv(tmp_path / "behind" / "a-seed2.csv", [0.0] * 3 + [1.0] * 3)
    write_csv(tmp_path / "behind" / "b-seed2.csv", [0.0] * 1 + [1.0] * 5)
    plot.main([str(tmp_path / "ahead"), str(tmp_path / "behind"), "--compare", "a", "b", "--looks", "2", "3"])
    assert not any(line.startswith("averaged") for line in capsys.readouterr().out.splitlines())


def test_compare_counts_ties_half_and_leaves_the_order_of_censored_runs_open(tmp_path, capsys):
    # a: 0.9 at 1, and one run never (censored at 4); b: 0.9 at 1, and at 2
    for name, rates in {"a-seed0": [0, 1, 1, 1], "a-seed1": [0, 0, 0, 0],
                        "b-seed0": [0, 1, 1, 1], "b-seed1": [0, 0, 1, 1]}.items():
        write_csv(tmp_path / "toy" / f"{name}.csv", rates)
    plot.main([str(tmp_path / "toy"), "--compare", "a", "b"])
    line = capsys.readouterr().out.strip()
    # pairs (1, 1) tie, (1, 2) won, (5 censored, 1) lost, (5 censored, 2) lost: (0.5 + 1) / 4
    assert line.startswith("toy: P(a beats b) first >= 0.9: 0.38 [")
    # AUCs over 0-3: a 0.75, 0.00; b 0.75, 0.50: (0.75, 0.75) tie, (0.75, 0.5) won, 0.00 lost twice: 1.5 / 4
    assert "; AUC over iterations 0-3: 0.38 [" in line


def test_the_readme_quotes_what_compare_prints_on_the_committed_push_new_runs(capsys):
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    plot.main([str(repo / "docs/results/push_new"), "--compare", "gchgg", "ghgg"])
    (line,) = capsys.readouterr().out.splitlines()
    assert f"    {line}\n" in (repo / "README.md").read_text()


def reference_auc(success, iterations):
    """Mean success over iterations 0 .. iterations - 1, the list extended with its last value."""
    held = list(success) + [success[-1]] * max(0, iterations - len(success))
    return sum(held[:iterations]) / iterations


def test_the_auc_range_is_the_smallest_budget_or_the_shortest_censored_run_and_can_be_set(tmp_path, capsys):
    toy = tmp_path / "toy"  # no Fig. 5 experiment: every run's budget is the longest run's length, 8
    a = [[0.0, 0.5, 0.9, 1.0, 1.0, 1.0, 1.0, 1.0], [0.0, 0.0, 0.95, 0.95]]  # the second stopped early: held at 0.95
    b = [[0.0, 0.2, 0.4, 0.6, 0.8, 0.8, 0.8, 0.8], [0.0, 0.1, 0.9, 0.9, 0.9, 0.9, 0.9, 0.9]]
    short = [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0]]  # never reached 0.9, abandoned after 6 of 8 iterations: censored at 6
    for name, runs in {"a": a, "b": b, "short": short}.items():
        for seed, rates in enumerate(runs):
            write_csv(toy / f"{name}-seed{seed}.csv", rates)
    groups = plot.group_runs(plot.find_runs([toy]))
    every = plot.scores(groups)
    assert {s.auc_range for s in every.values()} == {6}  # capped by the censored run's length, 6 < 8
    assert every["toy", "a"].auc.tolist() == pytest.approx([reference_auc(r, 6) for r in a])
    assert every["toy", "short"].first.tolist() == [7] and every["toy", "short"].censored_at == [6]
    pair = plot.scores({k: v for k, v in groups.items() if k[1] in ("a", "b")})
    assert pair["toy", "b"].auc_range == 8  # no censored run among a and b: the budget
    assert pair["toy", "b"].auc.tolist() == pytest.approx([reference_auc(r, 8) for r in b])
    three = plot.scores(groups, auc_iterations=3)["toy", "a"]
    assert three.auc.tolist() == pytest.approx([reference_auc(r, 3) for r in a])
    plot.main([str(toy), "--compare", "a", "b"])  # --compare: the range of the two groups compared
    assert capsys.readouterr().out.strip().endswith("AUC over iterations 0-7: 1.00 [1.00, 1.00]")
    plot.main([str(toy), "--compare", "a", "short"])
    assert "AUC over iterations 0-5: " in capsys.readouterr().out
    plot.main([str(toy), "--compare", "a", "b", "--auc-range", "2"])
    line = capsys.readouterr().out.strip()
    # AUC over 0-1: a 0.25, 0.00; b 0.10, 0.05: (0.25 > 0.10, 0.25 > 0.05, 0 < 0.10, 0 < 0.05): 2 / 4
    assert line.endswith("AUC over iterations 0-1: 0.50 [0.00, 1.00]")
    with pytest.raises(SystemExit):
        plot.main([str(toy), "--compare", "a", "b", "--auc-range", "0"])
    assert "--auc-range 0: the AUC is the mean over iterations 0 ... R-1; allowed: R >= 1" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--auc-range 0"):
        plot.scores(groups, auc_iterations=0)


def test_a_run_reaching_0_9_where_a_shorter_one_was_censored_does_not_beat_it(tmp_path, capsys):
    """Censored at 3 (it ran iterations 0-2), its true first >= 0.9 is 3 or later: 0.9 at 3 may tie it,
    at 2 beats it."""
    write_csv(tmp_path / "toy" / "late-seed0.csv", [0.0, 0.0, 0.0, 0.9, 0.9])  # observed at 3
    write_csv(tmp_path / "toy" / "early-seed0.csv", [0.0, 0.0, 0.9, 0.9, 0.9])  # observed at 2
    write_csv(tmp_path / "toy" / "short-seed0.csv", [0.0, 0.0, 0.0])  # censored at 3, counted at 4
    groups = plot.group_runs(plot.find_runs([tmp_path / "toy"]))
    short = plot.scores(groups)["toy", "short"]
    assert short.first.tolist() == [4] and short.first_bound.tolist() == [3]
    def poi(a, b):
        return plot.compare(groups, a, b)[0].split("; AUC")[0]

    assert poi("late", "short") == "toy: P(late beats short) first >= 0.9: 0.50 [0.50, 0.50] (1 vs 1 runs)"
    assert poi("early", "short") == "toy: P(early beats short) first >= 0.9: 1.00 [1.00, 1.00] (1 vs 1 runs)"
    assert poi("short", "late") == "toy: P(short beats late) first >= 0.9: 0.50 [0.50, 0.50] (1 vs 1 runs)"


def write_rows(path, success, stopped):
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["iteration", "success_rate", "stopped"])
        writer.writerows([i, s, t] for i, (s, t) in enumerate(zip(success, stopped, strict=True)))


def test_pairs_match_runs_by_seed_and_give_paired_differences(tmp_path, capsys):
    """Forks of one checkpoint: A (gchgg) and B (ghgg) share a seed per pair; the differences are A − B."""
    folder = tmp_path / "forks"
    folder.mkdir()
    stop = {  # seed -> (A's HGG stop, A's first >= 0.9, B's HGG stop, B's first >= 0.9)
        100: (4, 6, 5, 8), 101: (3, 9, 3, 7), 102: (5, 7, 6, 7),
    }
    for seed, (a_stop, a_first, b_stop, b_first) in stop.items():
        for algo, s, f in (("gchgg", a_stop, a_first), ("ghgg", b_stop, b_first)):
            write_rows(folder / f"{algo}-seed{seed}.csv", [0.0] * f + [0.9] * (12 - f), [0] * s + [1] * (12 - s))
    write_rows(folder / "ghgg-seed103.csv", [0.0] * 12, [0] * 12)  # no partner
    plot.main([str(folder), "--pairs", "gchgg", "ghgg", "--budget", "12"])
    out = capsys.readouterr().out
    assert "forks: 3 pairs of gchgg (A) and ghgg (B) by seed; without a partner: seed 103" in out
    assert "seed 101: HGG stop A 3, B 3 (A - B 0); first >= 0.9 A 9, B 7 (A - B 2)" in out
    # first >= 0.9: -2, +2, 0 -> mean 0; HGG stop: -1, 0, -1 -> mean -0.67
    assert "first >= 0.9, A - B over 3 pairs: mean 0.0 [" in out and "A ahead in 1, level in 1, behind in 1" in out
    assert "HGG stop, A - B over 3 pairs: mean -0.7 [-1.0, 0.0]; A ahead in 2, level in 1, behind in 0" in out
    # A's first >= 0.9: 6, 9, 7 and B's 8, 7, 7, centred -4/3, 5/3, -1/3 and 2/3, -1/3, -1/3:
    # r = (-4/3) / sqrt(14/3 * 2/3) = -0.756
    assert "    the same runs unpaired: 0.0 [" in out
    assert "partners' correlation r = -0.76; paired t-test p = 1.000" in out  # mean difference 0
    # HGG stop: -1, 0, -1: t = -2 with 2 degrees of freedom, two-sided p = 1 - 2 / sqrt(6)
    # Wilcoxon drops the 0: [-1, -1], both negative, exact p = 2 / 2**2
    assert f"paired t-test p = {1 - 2 / 6 ** 0.5:.3f}, Wilcoxon signed-rank p = 0.500" in out
    # AUC over iterations 0-11 (the budget): 0.9 from first >= 0.9 on, A 0.9 * (6, 3, 5) / 12, B 0.9 * (4, 5, 5) / 12;
    # A - B = 0.15, -0.15, 0: a resample of all -0.15 (or all 0.15) has probability 1/27 > 2.5 %: the CI is the extremes
    assert ("AUC over iterations 0-11, A - B over 3 pairs: mean 0.000 [-0.150, 0.150]; A ahead in 1, level in 1, "
            "behind in 1") in out
    with pytest.raises(SystemExit):
        plot.main([str(folder), "--pairs", "gchgg", "cher"])


def test_task_puts_runs_of_several_folders_in_one_panel(tmp_path, capsys):
    """A Fig. 6 ablation's CSVs beside the default setting's runs, kept in the task's own folder."""
    write_csv(tmp_path / "fig6" / "eta" / "500-seed0.csv", [0.0] * 5 + [0.95] * 5)
    write_csv(tmp_path / "pick_no_obstacle" / "gchgg-seed0.csv", [0.0] * 3 + [0.95] * 7)
    plot.main([str(tmp_path / "fig6" / "eta" / "500-seed0.csv"), str(tmp_path / "pick_no_obstacle" / "gchgg-seed0.csv"),
               "--task", "pick_no_obstacle", "--at", "5"])
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| pick_no_obstacle")]
    assert [row.split(" | ")[1] for row in rows] == ["500", "gchgg"]


def test_looks_draw_the_compare_intervals_at_pococks_level_for_a_sequential_design(tmp_path, capsys):
    from gchgg.analysis import stats

    for seed, (a, b) in enumerate(zip([2, 3, 2, 4, 1, 3, 2, 5], [3, 2, 4, 3, 4, 5, 3, 4], strict=True)):
        write_csv(tmp_path / "toy" / f"a-seed{seed}.csv", [0.0] * a + [0.95] * (6 - a))
        write_csv(tmp_path / "toy" / f"b-seed{seed}.csv", [0.0] * b + [0.95] * (6 - b))
    plot.main([str(tmp_path / "toy"), "--compare", "a", "b"])
    plain = capsys.readouterr().out.strip()
    plot.main([str(tmp_path / "toy"), "--compare", "a", "b", "--looks", "4", "6", "8", "10"])
    looked = capsys.readouterr().out.strip()
    level = 100 * (1 - stats.sequential_alpha([4, 6, 8, 10]))
    assert looked.endswith(f"; {level:.1f} % intervals, Pocock's for looks at 4, 6, 8, 10 runs") and 96 < level < 99

    def first(line):  # point, low, high of P on first >= 0.9
        point, interval = line.split("first >= 0.9: ")[1].split(" (")[0].split(" [")
        return float(point), *map(float, interval.rstrip("]").split(", "))

    (p, low, high), (p_looked, low_looked, high_looked) = first(plain), first(looked)
    assert p == p_looked and low_looked <= low and high_looked >= high and (low_looked, high_looked) != (low, high)
    for args, message in [(["--looks", "4", "6", "9"], "--looks 4 6 9: toy has 8 runs of a and 8 of b; a look reads "
                                                       "the same number of runs of each, one of the planned looks"),
                          (["--looks", "4", "3"], "--looks 4 3: allowed an increasing list of run counts")]:
        with pytest.raises(SystemExit):
            plot.main([str(tmp_path / "toy"), "--compare", "a", "b", *args])
        assert message in capsys.readouterr().err
    with pytest.raises(SystemExit):
        plot.main([str(tmp_path / "toy"), "--looks", "4"])
    assert "--looks: the looks of a comparison; allowed only with --compare A B" in capsys.readouterr().err


def test_panels_follow_fig5s_task_order_and_a_group_keeps_its_colour_across_panels():
    assert plot.panel_tasks(["pick_obstacle", "fig6", "reach", "push_new", "pick_no_obstacle", "abc"]) == [
        "reach", "push_new", "pick_no_obstacle", "pick_obstacle", "abc", "fig6"]
    # her is missing from one task: cher keeps C0, gchgg C1 and her C2 in every panel
    assert plot.label_colours(["gchgg", "cher", "her", "gchgg"]) == {"cher": "C0", "gchgg": "C1", "her": "C2"}


def test_names_of_the_modules_split_from_plot_stay_importable_from_it():
    from gchgg.analysis import runs, scoring

    for name in plot.__all__:
        assert hasattr(plot, name), name
    for module in (runs, scoring):
        for name in module.__all__:
            assert getattr(plot, name) is getattr(module, name), name
