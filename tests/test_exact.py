"""gchgg.analysis.exact gives scipy's p-values where scipy's are exact, and holds with ties and censoring."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.stats

from gchgg.analysis import exact


@pytest.mark.parametrize("n, m", [(3, 3), (4, 6), (8, 8), (10, 12)])
@pytest.mark.parametrize("alternative", exact.ALTERNATIVES)
def test_mann_whitney_is_scipys_exact_test_without_ties(n, m, alternative):
    rng = np.random.default_rng(n * 100 + m)
    x, y = rng.normal(size=n) + 0.8, rng.normal(size=m)
    expected = scipy.stats.mannwhitneyu(x, y, method="exact", alternative=alternative).pvalue
    got = exact.mann_whitney(x, y, alternative=alternative, enumerate_up_to=10**6)
    assert got == pytest.approx(expected, rel=1e-9)


def test_three_runs_against_three_cannot_go_below_a_tenth():
    assert exact.mann_whitney([1, 2, 3], [4, 5, 6]) == pytest.approx(0.1)
    assert exact.mann_whitney([1, 2, 3], [4, 5, 6], alternative="less") == pytest.approx(0.05)


def test_mann_whitney_counts_a_tie_half_and_a_censored_pair_as_a_tie():
    """A brute-force reference: every split of the pooled runs scored by hand with the censoring rule."""
    x, cx = np.array([70.0, 120.0, 200.0]), np.array([False, False, True])
    y, cy = np.array([90.0, 200.0, 200.0, 120.0]), np.array([False, True, True, False])
    runs = list(zip(np.concatenate([x, y]), np.concatenate([cx, cy]), strict=True))

    def fewer_is_shown(a, b):  # a reached the threshold sooner than b, as far as the data show
        return not a[1] and a[0] < b[0]

    def score(group):
        other = [r for i, r in enumerate(runs) if i not in group]
        pairs = [(runs[i], o) for i in group for o in other]
        return sum(1.0 if fewer_is_shown(a, b) else 0.0 if fewer_is_shown(b, a) else 0.5 for a, b in pairs) / len(pairs)

    null = [score(set(g)) for g in itertools.combinations(range(7), 3)]
    observed = score({0, 1, 2})
    expected = np.mean([abs(s - 0.5) >= abs(observed - 0.5) - 1e-12 for s in null])
    got = exact.mann_whitney(x, y, lower_is_better=True, x_censored=cx, y_censored=cy)
    assert got == pytest.approx(expected)
    assert 0 < got < 1


@pytest.mark.parametrize("n", [4, 8, 12])
@pytest.mark.parametrize("alternative", exact.ALTERNATIVES)
def test_wilcoxon_is_scipys_exact_test_without_ties_or_zeros(n, alternative):
    rng = np.random.default_rng(n)
    x, y = rng.normal(size=n) + 0.5, rng.normal(size=n)
    expected = scipy.stats.wilcoxon(x - y, method="exact", alternative=alternative).pvalue
    assert exact.wilcoxon(x, y, alternative=alternative) == pytest.approx(expected, rel=1e-9)


def test_wilcoxon_with_tied_magnitudes_is_the_permutation_test_of_mean_ranks():
    x, y = np.array([3.0, 5.0, 1.0, 4.0, 6.0]), np.array([1.0, 3.0, 3.0, 4.0, 2.0])  # 2, 2, -2, 0, 4
    expected = scipy.stats.wilcoxon(x - y, method=scipy.stats.PermutationMethod(n_resamples=np.inf),
                                    zero_method="wilcox").pvalue
    assert exact.wilcoxon(x, y) == pytest.approx(expected)


def test_the_push_new_forks_statistics_of_the_issue():
    """8 pairs with 6 positive and 2 negative differences: the sign test's p is 0.289 (issue 72)."""
    assert exact.sign_test([1] * 6 + [0] * 2, [0] * 6 + [1] * 2) == pytest.approx(0.2890625)


@pytest.mark.parametrize("alternative", exact.ALTERNATIVES)
def test_sign_test_is_scipys_binomial_test(alternative):
    x, y = np.array([5, 6, 7, 1, 9, 9, 3]), np.array([4, 2, 7, 3, 1, 0, 1])  # 5 up, 1 down, 1 equal
    assert exact.sign_test(x, y, alternative=alternative) == pytest.approx(
        scipy.stats.binomtest(5, 6, 0.5, alternative=alternative).pvalue)
    assert exact.sign_test(x, y, lower_is_better=True, alternative="less") == pytest.approx(
        exact.sign_test(x, y, alternative="greater"))


def test_drawn_relabellings_approach_the_enumerated_p_value_and_repeat():
    rng = np.random.default_rng(5)
    x, y = rng.normal(size=9) + 0.7, rng.normal(size=9)
    whole = exact.mann_whitney(x, y)
    drawn = exact.mann_whitney(x, y, enumerate_up_to=0)
    assert drawn == exact.mann_whitney(x, y, enumerate_up_to=0)  # seeded: the same digits
    assert drawn == pytest.approx(whole, abs=0.01)
    assert exact.wilcoxon(x, y, enumerate_up_to=0, draws=5_000) == pytest.approx(exact.wilcoxon(x, y), abs=0.03)


def test_the_tasks_test_relabels_each_task_apart():
    """A brute-force reference over two tasks: every pair of splits, the average of the two tasks' fractions."""
    x1, y1, x2, y2 = [3.0, 9.0], [1.0, 2.0, 4.0], [5.0, 6.0, 7.0], [2.0, 8.0]

    def fraction(a, b):
        return np.mean([1.0 if u > v else 0.5 if u == v else 0.0 for u in a for v in b])

    def splits(x, y):
        pooled = x + y
        for group in itertools.combinations(range(len(pooled)), len(x)):
            yield [pooled[i] for i in group], [pooled[i] for i in range(len(pooled)) if i not in group]

    null = [(fraction(a1, b1) + fraction(a2, b2)) / 2 for a1, b1 in splits(x1, y1) for a2, b2 in splits(x2, y2)]
    observed = (fraction(x1, y1) + fraction(x2, y2)) / 2
    expected = np.mean([v >= observed - 1e-12 for v in null])
    assert exact.mann_whitney_tasks([x1, x2], [y1, y2], alternative="greater") == pytest.approx(expected)
    assert exact.mann_whitney_tasks([x1], [y1]) == pytest.approx(exact.mann_whitney(x1, y1))
    with pytest.raises(ValueError, match="2 tasks of X and 1 of Y"):
        exact.mann_whitney_tasks([x1, x2], [y1])


@pytest.mark.parametrize("call, match", [
    (lambda: exact.mann_whitney([1, 2], [3, float("nan")]), "finite"),
    (lambda: exact.mann_whitney([1, 2], [3, 4], alternative="bigger"), "alternative='bigger'"),
    (lambda: exact.mann_whitney([1, 2], [3, 4], x_censored=[True]), "x_censored"),
    (lambda: exact.wilcoxon([1, 2], [3]), "one of each per pair"),
    (lambda: exact.sign_test([], []), "non-empty"),
])
def test_bad_input_is_refused_by_name(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_no_difference_gives_one():
    assert exact.wilcoxon([1, 2, 3], [1, 2, 3]) == 1.0 and exact.sign_test([1, 2], [1, 2]) == 1.0
