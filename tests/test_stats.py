"""Interval estimates (gchgg.analysis.stats) against plainly written references: IQM, bootstrap CIs, probability of
improvement."""

from __future__ import annotations

import itertools
from fractions import Fraction

import numpy as np
import pytest
import scipy.stats

from gchgg.analysis import stats


def reference_iqm(values) -> float:
    """Sort, cut floor(N / 4) from each end, average what is left (rliable's trimmed mean)."""
    values = sorted(float(v) for v in np.ravel(values))
    cut = len(values) // 4
    kept = values[cut : len(values) - cut]
    return sum(kept) / len(kept)


def reference_poi(x, y, lower_is_better=False, x_censored=None, y_censored=None) -> Fraction:
    """Count every pair: a win where x is observed and strictly better, a loss where y is, else half."""
    x_censored = x_censored or [False] * len(x)
    y_censored = y_censored or [False] * len(y)
    total = Fraction(0)
    for (a, ca), (b, cb) in itertools.product(zip(x, x_censored, strict=True), zip(y, y_censored, strict=True)):
        a_better = a < b if lower_is_better else a > b
        b_better = b < a if lower_is_better else b > a
        if a_better and not ca:
            total += 1
        elif b_better and not cb:
            total += 0
        else:
            total += Fraction(1, 2)
    return total / (len(x) * len(y))


@pytest.mark.parametrize("values, expected", [
    ([1, 2, 3, 4], 2.5),  # 1 cut from each end
    ([5, 1, 3], 3.0),  # nothing cut from 3
    ([7], 7.0),
    ([1, 2, 3, 4, 100, 5, 6, 7], 4.5),  # 2 cut from each end: 3, 4, 5, 6
    ([10, 0, 0, 0, 10], 10 / 3),  # 1 cut from each end of 5: 0, 0, 10
])
def test_iqm_of_known_arrays(values, expected):
    assert stats.iqm(values) == pytest.approx(expected)
    assert stats.iqm(values) == pytest.approx(reference_iqm(values))


def test_iqm_equals_scipys_trimmed_mean_and_pools_tasks():
    rng = np.random.default_rng(3)
    for n in range(1, 13):
        values = rng.normal(size=n)
        assert stats.iqm(values) == pytest.approx(scipy.stats.trim_mean(values, 0.25))
    matrix = rng.normal(size=(5, 3))  # [runs, tasks]: rliable pools every score
    assert stats.iqm(matrix) == pytest.approx(scipy.stats.trim_mean(matrix, 0.25, axis=None))
    assert stats.iqm(matrix) == pytest.approx(reference_iqm(matrix))


def test_an_empty_group_or_a_nan_score_is_an_error_not_a_nan():
    with pytest.raises(ValueError, match="no runs"):
        stats.iqm([])
    with pytest.raises(ValueError, match="no runs"):
        stats.iqm_interval([])
    with pytest.raises(ValueError, match="NaN"):
        stats.iqm([1.0, float("nan")])
    with pytest.raises(ValueError, match="the same tasks"):
        stats.probability_of_improvement(np.zeros((2, 2)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="reps=0"):
        stats.iqm_interval([1.0], reps=0)


def test_the_bootstrap_interval_is_the_percentiles_of_a_resampling_loop():
    """Vectorised resampling = a loop over resamples (scipy's trimmed mean, numpy's percentile) on the same draws."""
    scores = np.array([[74.0, 0.62], [84.0, 0.55], [75.0, 0.71], [90.0, 0.40]])  # 4 runs, 2 tasks
    estimate = stats.iqm_interval(scores, reps=300, rng=np.random.default_rng(7))
    draws = np.random.default_rng(7).integers(0, 4, size=(300, 4, 2))  # per resample, per task: 4 runs drawn
    means = []
    for r in range(300):
        resampled = np.stack([scores[draws[r, :, t], t] for t in range(2)], axis=1)  # runs stay within their task
        means.append(scipy.stats.trim_mean(resampled, 0.25, axis=None))
    assert (estimate.low, estimate.high) == pytest.approx(tuple(np.percentile(means, [2.5, 97.5])))
    assert estimate.point == pytest.approx(reference_iqm(scores))
    assert estimate.runs == 4


def test_the_interval_contains_the_estimate_and_repeats_for_a_seed():
    scores = [74.0, 84.0, 75.0, 79.0, 86.0]
    estimate = stats.iqm_interval(scores)
    assert estimate.low <= estimate.point <= estimate.high
    assert stats.iqm_interval(scores) == estimate  # default: a generator seeded 0, so tables regenerate alike
    assert (stats.iqm_interval(scores, rng=np.random.default_rng(1))
            == stats.iqm_interval(scores, rng=np.random.default_rng(1)))
    assert stats.iqm_interval([5.0, 5.0, 5.0]).format(1) == "5.0 [5.0, 5.0]"
    assert stats.iqm_interval([5.0]) == stats.Estimate(5.0, 5.0, 5.0, 1)


@pytest.mark.parametrize("x, y, lower", [
    ([3, 1], [2, 2], False),
    ([0.9, 0.9, 0.5], [0.9, 0.7], False),  # ties counted half
    ([70, 90], [80, 90], True),  # fewer iterations beat
    ([74, 84, 75], [79, 84, 86], True),
    ([1, 2, 3, 4], [1, 2, 3, 4], True),
])
def test_probability_of_improvement_is_the_pair_count(x, y, lower):
    expected = reference_poi(x, y, lower)
    assert stats.probability_of_improvement(x, y, lower_is_better=lower) == pytest.approx(float(expected))
    # the Mann-Whitney U of the better direction over n * m, as rliable computes it
    u = scipy.stats.mannwhitneyu(np.negative(x) if lower else x, np.negative(y) if lower else y).statistic
    assert stats.probability_of_improvement(x, y, lower_is_better=lower) == pytest.approx(u / (len(x) * len(y)))


def test_known_fractions():
    assert stats.probability_of_improvement([70, 90], [80, 90], lower_is_better=True) == 0.625  # 2.5 of 4
    assert stats.probability_of_improvement([74, 84, 75], [79, 84, 86], lower_is_better=True) == pytest.approx(7.5 / 9)
    assert stats.probability_of_improvement([1.0], [1.0]) == 0.5


def test_censored_pairs_count_only_where_the_data_show_the_order():
    # x: reached at 50, never reached by 100 (censored there); y: never reached by 200, never by 30 (ended at 30)
    x, cx = [50, 100], [False, True]
    y, cy = [200, 30], [True, True]
    # 50 < 200 (censored): x wins. 50 vs 30 censored: y is only known to be >= 30: a tie.
    # 100 censored vs 200 censored: a tie. 100 censored vs 30 censored: a tie (neither was seen at 0.9).
    assert reference_poi(x, y, True, cx, cy) == Fraction(5, 8)  # (1 + 3 halves) of 4
    assert stats.probability_of_improvement(x, y, lower_is_better=True, x_censored=cx, y_censored=cy) == 0.625
    # every censored run at the same budget: exactly the uncensored pair count
    x, y = [60, 200, 80], [200, 200, 90]
    plain = stats.probability_of_improvement(x, y, lower_is_better=True)
    censored = stats.probability_of_improvement(x, y, lower_is_better=True, x_censored=[False, True, False],
                                                y_censored=[True, True, False])
    assert plain == censored == pytest.approx(float(reference_poi(x, y, True)))


def test_the_poi_interval_resamples_each_group_independently():
    x, y = np.array([74.0, 84.0, 75.0]), np.array([79.0, 84.0, 86.0, 95.0])
    estimate = stats.poi_interval(x, y, lower_is_better=True, reps=200, rng=np.random.default_rng(5))
    rng = np.random.default_rng(5)
    ix, iy = rng.integers(0, 3, size=(200, 3, 1)), rng.integers(0, 4, size=(200, 4, 1))
    reference = [float(reference_poi(x[ix[r, :, 0]].tolist(), y[iy[r, :, 0]].tolist(), True)) for r in range(200)]
    assert (estimate.low, estimate.high) == pytest.approx(tuple(np.percentile(reference, [2.5, 97.5])))
    assert estimate.point == pytest.approx(float(reference_poi(x.tolist(), y.tolist(), True)))
    assert (estimate.runs, estimate.other_runs) == (3, 4)
    assert estimate.low <= estimate.point <= estimate.high
    assert stats.poi_interval([1, 2], [5, 6], lower_is_better=True).format() == "1.00 [1.00, 1.00]"


def test_the_average_over_tasks_resamples_each_task_and_group_independently():
    """Tasks of 3 vs 4, 2 vs 2 and 1 vs 3 runs (one censored): the mean of the tasks' pair counts, and the
    percentiles of that mean over resamples drawn task by task, X's runs then Y's."""
    x = [np.array([74.0, 84.0, 75.0]), np.array([120.0, 300.0]), np.array([90.0])]
    y = [np.array([79.0, 84.0, 86.0, 95.0]), np.array([130.0, 110.0]), np.array([80.0, 200.0, 95.0])]
    cx, cy = [None, [False, True], None], [None, [False, False], [False, True, False]]
    estimate = stats.average_poi_interval(x, y, lower_is_better=True, x_censored=cx, y_censored=cy, reps=300,
                                          rng=np.random.default_rng(7))
    masks = lambda masks, t, n: list(masks[t]) if masks[t] is not None else [False] * n  # noqa: E731
    rng, draws = np.random.default_rng(7), []
    for t in range(3):
        draws.append((rng.integers(0, len(x[t]), size=(300, len(x[t]), 1))[..., 0],
                      rng.integers(0, len(y[t]), size=(300, len(y[t]), 1))[..., 0]))
    reference = []
    for r in range(300):
        per_task = []
        for t, (ix, iy) in enumerate(draws):
            mx, my = np.array(masks(cx, t, len(x[t]))), np.array(masks(cy, t, len(y[t])))
            per_task.append(reference_poi(x[t][ix[r]].tolist(), y[t][iy[r]].tolist(), True,
                                          mx[ix[r]].tolist(), my[iy[r]].tolist()))
        reference.append(float(sum(per_task) / 3))
    point = sum(reference_poi(x[t].tolist(), y[t].tolist(), True, masks(cx, t, len(x[t])), masks(cy, t, len(y[t])))
                for t in range(3)) / 3
    assert estimate.point == pytest.approx(float(point))
    assert (estimate.low, estimate.high) == pytest.approx(tuple(np.percentile(reference, [2.5, 97.5])))
    assert (estimate.runs, estimate.other_runs) == (6, 9)


def test_the_average_over_tasks_of_equal_runs_is_the_matrix_figure_and_a_sure_task_adds_no_width():
    x, y = np.array([[1.0, 5.0], [3.0, 2.0], [2.0, 9.0]]), np.array([[2.0, 4.0], [2.5, 8.0], [0.5, 1.0]])
    average = stats.average_poi_interval(list(x.T), list(y.T))
    assert average.point == pytest.approx(stats.probability_of_improvement(x, y))
    # X beats Y in every pair of task 0 and loses every pair of task 1: 1 and 0 in every resample
    assert stats.average_poi_interval([[1, 2], [9, 8]], [[5, 6, 7], [1, 2]], lower_is_better=True).format() == \
        "0.50 [0.50, 0.50]"
    with pytest.raises(ValueError, match="2 tasks of the first group, 1 of the second"):
        stats.average_poi_interval([[1], [2]], [[1]])
    with pytest.raises(ValueError, match="x_censored holds 1 masks for 2 tasks"):
        stats.average_poi_interval([[1], [2]], [[1], [2]], x_censored=[[False]])


def test_the_unpaired_interval_resamples_the_groups_apart():
    """Partners that move together: the paired interval is a point, the unpaired one is wide."""
    x, y = [10.0, 20.0, 30.0, 40.0], [12.0, 22.0, 32.0, 42.0]
    paired = stats.paired_difference_interval(x, y, rng=np.random.default_rng(0))
    apart = stats.unpaired_difference_interval(x, y, rng=np.random.default_rng(0))
    assert (paired.point, paired.low, paired.high) == (-2.0, -2.0, -2.0)
    assert apart.point == -2.0 and apart.low < -10 and apart.high > 6 and (apart.runs, apart.other_runs) == (4, 4)
    with pytest.raises(ValueError, match="scores must be finite"):
        stats.unpaired_difference_interval([1.0, np.inf], [1.0])


def test_paired_tests_give_the_t_and_signed_rank_p_values():
    # -4, -2, -1, -5: mean -3, s = sqrt(10 / 3), t = -3 / (s / 2) with 3 degrees of freedom; all four
    # negative: the exact signed-rank p is 2 / 2**4
    t, w = stats.paired_tests([80, 75, 90, 70], [84, 77, 91, 75])
    assert t == pytest.approx(2 * scipy.stats.t.sf(3 / (np.sqrt(10 / 3) / 2), 3)) and w == 2 / 16
    assert all(np.isnan(stats.paired_tests([1.0], [0.0])))  # one pair: neither test is defined
    t, w = stats.paired_tests([1.0, 2.0], [1.0, 2.0])  # no difference at all
    assert np.isnan(t) and np.isnan(w)


@pytest.mark.parametrize("looks, pocock", [([1, 2], 0.0294), ([1, 2, 3], 0.0221), ([1, 2, 3, 4], 0.0182),
                                           ([1, 2, 3, 4, 5], 0.0158)])
def test_sequential_alpha_is_pococks_level_for_equally_spaced_looks(looks, pocock):
    """Pocock's (1977) nominal levels of K equally spaced looks at an overall 5 % (Jennison and Turnbull,
    2000, table 2.1); only the looks' ratios matter."""
    assert stats.sequential_alpha(looks) == pytest.approx(pocock, abs=4e-4)
    assert stats.sequential_alpha([3 * n for n in looks]) == pytest.approx(pocock, abs=4e-4)


def test_one_look_keeps_the_level_close_looks_cost_less_and_bad_looks_are_errors():
    assert stats.sequential_alpha([6]) == 0.05
    # looks after 3, 4, 5 and 6 runs are strongly correlated: a milder correction than 4 equally spaced looks
    assert 0.0182 + 1e-3 < stats.sequential_alpha([3, 4, 5, 6]) < 0.05
    for bad in ([], [3, 3], [0, 1], [4, 3]):
        with pytest.raises(ValueError, match=r"looks=.*allowed a non-empty increasing list of run counts"):
            stats.sequential_alpha(bad)


def test_the_median_interval_is_the_percentiles_of_a_resampling_loop():
    """median_interval = a loop over resamples of numpy's median on the same draws; the median and its checks."""
    scores = np.array([1.00, 0.96, 1.01, 1.00, 1.05, 1.03, 1.02])
    estimate = stats.median_interval(scores, reps=300, rng=np.random.default_rng(3))
    draws = np.random.default_rng(3).integers(0, len(scores), size=(300, len(scores), 1))
    medians = [np.median(scores[draws[r, :, 0]]) for r in range(300)]
    assert (estimate.low, estimate.high) == pytest.approx(tuple(np.percentile(medians, [2.5, 97.5])))
    assert estimate.point == 1.01 and estimate.runs == len(scores)
    assert stats.median_interval(scores) == stats.median_interval(scores)  # seeded 0 by default
    with pytest.raises(ValueError, match="no runs"):
        stats.median_interval([])
    with pytest.raises(ValueError, match="reps=0"):
        stats.median_interval([1.0], reps=0)


def test_the_paired_interval_is_the_percentiles_of_a_pair_resampling_loop():
    """Differences that vary: the interval is the 2.5 / 97.5 % points of a plain loop over the same draws."""
    x, y = np.array([80.0, 75.0, 90.0, 70.0, 66.0]), np.array([84.0, 77.0, 90.0, 75.0, 60.0])  # -4 -2 0 -5 6
    got = stats.paired_difference_interval(x, y, reps=500, rng=np.random.default_rng(3))
    draws = np.random.default_rng(3).integers(0, 5, size=(500, 5))
    means = [float(np.mean([x[i] - y[i] for i in row])) for row in draws]
    assert got.point == pytest.approx(-1.0)
    assert (got.low, got.high) == pytest.approx(tuple(np.percentile(means, [2.5, 97.5])))
    assert got.low < -1.0 < got.high


def test_the_hierarchical_interval_counts_checkpoints_not_pairs():
    """Two checkpoints whose forks differ by 0 and by 10: resampling pairs alone hides that the checkpoint
    decides; the two-stage bootstrap spans both checkpoints' means."""
    flat_pairs = [0.0, 0.0, 0.0, 0.0, 10.0, 10.0, 10.0, 10.0]
    both = stats.hierarchical_difference_interval([[0.0] * 4, [10.0] * 4], rng=np.random.default_rng(0))
    flat = stats.paired_difference_interval(flat_pairs, [0.0] * 8, rng=np.random.default_rng(0))
    assert both.point == flat.point == 5.0 and (both.runs, both.other_runs) == (8, 2)
    assert (both.low, both.high) == (0.0, 10.0)  # a resample may draw one checkpoint twice
    assert flat.low > 0.0 and flat.high < 10.0
    one = stats.hierarchical_difference_interval([[1.0, 3.0, 5.0]], reps=4000, rng=np.random.default_rng(1))
    pairs = stats.paired_difference_interval([1.0, 3.0, 5.0], [0.0] * 3, reps=4000, rng=np.random.default_rng(2))
    assert one.point == 3.0 and abs(one.low - pairs.low) <= 0.34 and abs(one.high - pairs.high) <= 0.34


def test_the_hierarchical_interval_matches_a_two_stage_loop_in_distribution():
    groups = [np.array([1.0, 2.0, 9.0]), np.array([4.0, 4.5]), np.array([-3.0, 0.0, 1.0, 2.0])]
    rng = np.random.default_rng(7)
    loop = []
    for _ in range(20_000):
        chosen = [groups[k] for k in rng.integers(0, 3, size=3)]
        loop.append(np.mean([g[rng.integers(0, len(g), size=len(g))].mean() for g in chosen]))
    got = stats.hierarchical_difference_interval(groups, reps=20_000, rng=np.random.default_rng(8))
    assert got.point == pytest.approx(np.mean([g.mean() for g in groups]))
    assert (got.low, got.high) == pytest.approx(tuple(np.percentile(loop, [2.5, 97.5])), abs=0.15)
    with pytest.raises(ValueError, match="one non-empty vector of finite paired differences per checkpoint"):
        stats.hierarchical_difference_interval([[1.0], []])
