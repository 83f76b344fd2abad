"""Curves and tables over seeds (gchgg.plot) on hand-made run folders: grouping, medians, quartiles."""

from __future__ import annotations

import csv
import math

import pytest

from gchgg import plot


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
    make_run(tmp_path / "b0", "gchgg", 0, [0.1, 0.9, 1.0], extra={"diversity_decided": [0.2, 0.4, 0.6], "stopped": [0, 0, 1], "d_g": [0.5, 0.4, 0.0]})
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
    assert row.endswith("| — | — | — | 0.40 [0.35, 0.40] |")  # no HGG stop logged; hours: 4, 4, 3 rows of 360 s
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
    cells = dict(zip((c.strip() for c in head.split("|")), (c.strip() for c in row.split("|"))))
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
    assert "--y d_gg: no run logged this column; the runs' columns are d_g, diversity_decided" in capsys.readouterr().err
