"""Exact small-sample tests beside the bootstrap intervals: Mann-Whitney for runs, Wilcoxon and sign for pairs.

A percentile-bootstrap interval over 3 runs per group, or 8 pairs, covers less than its nominal
95 %: it cannot tell a difference from the luck of a few seeds on its own. These tests hold their
level at any sample size, because they compare the observed statistic with its distribution over
every relabelling the null hypothesis allows (enumerated where there are few, else drawn from a
seeded generator: the same digits on every call). ``gchgg.analysis.claims`` decides a claim only
where the interval and the test agree.

- :func:`mann_whitney`: independent runs of X and Y. The statistic is P(X beats Y) of
  :mod:`gchgg.analysis.stats` (ties half; a censored run beaten only where the data show it), its
  null distribution that of every split of the pooled runs into groups of the observed sizes. Without
  ties or censoring it is ``scipy.stats.mannwhitneyu(x, y, method="exact")``. 3 runs against 3 have
  20 splits: no two-sided p-value below 2/20 = 0.10.
  :func:`mann_whitney_tasks` averages it over tasks, each task's runs relabelled apart.
- :func:`wilcoxon`: pairs. The signed-rank sum of the nonzero differences (tied magnitudes get their
  mean rank) against every flip of their signs; without ties or zeros it is
  ``scipy.stats.wilcoxon(d, method="exact")``.
- :func:`sign_test`: pairs. The count of positive differences among the nonzero ones, binomial(n, ½).

Every p-value is two-sided unless ``alternative`` says otherwise: ``"greater"`` tests X better
than Y (higher, or lower where ``lower_is_better``), ``"less"`` the reverse.

>>> round(mann_whitney([1, 2, 3], [4, 5, 6]), 3)  # the most extreme of 20 splits, both tails
0.1
>>> round(wilcoxon([5, 6, 7, 8], [1, 2, 3, 4]), 3)  # all 4 differences positive: 2 of 16 flips as extreme
0.125
>>> round(sign_test([5, 6, 7, 8, 9, 10], [1, 2, 3, 4, 5, 6]), 4)  # 6 of 6 positive
0.0312
"""

from __future__ import annotations

import itertools
import math

import numpy as np

__all__ = ["ALTERNATIVES", "DRAWS", "ENUMERATE", "mann_whitney", "mann_whitney_tasks", "sign_test", "wilcoxon"]

ALTERNATIVES = ("two-sided", "greater", "less")
"""The hypotheses a test can take: X differs from Y, X is better, X is worse."""

ENUMERATE = 100_000
"""Relabellings enumerated whole up to this many (3 runs against 3: 20; 8 against 8: 12,870)."""

DRAWS = 20_000
"""Relabellings drawn at random where there are more than :data:`ENUMERATE` (a p-value near 0.05 then
carries a standard error of about 0.0015)."""

_TOLERANCE = 1e-9  # statistics equal up to float rounding count as equally extreme


def _vector(values, name: str) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    if array.ndim != 1 or not len(array) or not np.isfinite(array).all():
        raise ValueError(f"{name}: allowed a non-empty vector of finite scores, got {np.asarray(values)!r} "
                         "(count a censored run at its bound and mark it censored)")
    return array


def _check_alternative(alternative: str) -> None:
    if alternative not in ALTERNATIVES:
        raise ValueError(f"alternative={alternative!r}: allowed {', '.join(ALTERNATIVES)}")


def _p_value(null: np.ndarray, observed: float, centre: float, alternative: str, exact: bool) -> float:
    """The share of the null statistics at least as extreme as ``observed`` (``centre``: their mean);
    drawn (not enumerated) statistics count the observed labelling once more, so that p is never 0."""
    if alternative == "greater":
        extreme = null >= observed - _TOLERANCE
    elif alternative == "less":
        extreme = null <= observed + _TOLERANCE
    else:
        extreme = np.abs(null - centre) >= abs(observed - centre) - _TOLERANCE
    count = int(extreme.sum())
    return count / len(null) if exact else (count + 1) / (len(null) + 1)


def _beats(pooled: np.ndarray, censored: np.ndarray) -> np.ndarray:
    """``[N, N]``: 1 where run i is shown better than run j (observed and strictly higher), 0 where j is shown
    better than i, ½ where neither is shown (the pair's tie of ``stats.probability_of_improvement``)."""
    higher = pooled[:, None] > pooled[None, :]
    shown_better = higher & ~censored[:, None]
    shown_worse = higher.T & ~censored[None, :]
    return shown_better + 0.5 * (~shown_better & ~shown_worse)


def mann_whitney(x, y, *, lower_is_better: bool = False, x_censored=None, y_censored=None,
                 alternative: str = "two-sided", enumerate_up_to: int = ENUMERATE, draws: int = DRAWS,
                 rng: np.random.Generator | None = None) -> float:
    """The permutation p-value of P(X beats Y) = ½ for independent runs ``x`` and ``y`` (one task).

    Args:
        x, y: the runs' scores, ``[n]`` and ``[m]``.
        lower_is_better: scores such as iterations to a threshold, where beating means fewer.
        x_censored, y_censored: masks of scores known only as a bound (a run that never reached the
            threshold, at its last iteration); as in :func:`gchgg.analysis.stats.probability_of_improvement`.
        alternative: ``"two-sided"``, ``"greater"`` (X better) or ``"less"``.
        enumerate_up_to: at most this many splits are enumerated; above, ``draws`` are drawn from ``rng``.
        draws: splits drawn where there are more than ``enumerate_up_to``.
        rng: draws them (default: a fresh generator seeded 0).

    >>> round(mann_whitney([70, 80, 90], [100, 100, 100], lower_is_better=True,
    ...                    y_censored=[True, True, True], alternative="greater"), 3)  # 1 of 20 splits
    0.05
    """
    return mann_whitney_tasks(
        [x], [y], lower_is_better=lower_is_better, alternative=alternative, enumerate_up_to=enumerate_up_to,
        draws=draws, rng=rng, x_censored=None if x_censored is None else [x_censored],
        y_censored=None if y_censored is None else [y_censored])


def mann_whitney_tasks(xs, ys, *, lower_is_better: bool = False, x_censored=None, y_censored=None,
                       alternative: str = "two-sided", enumerate_up_to: int = ENUMERATE, draws: int = DRAWS,
                       rng: np.random.Generator | None = None) -> float:
    """:func:`mann_whitney` over several tasks: the statistic is P(X beats Y) averaged over the tasks
    (rliable's average probability of improvement), the relabellings split each task's runs apart
    (a stratified permutation test). ``xs``, ``ys``: one score vector per task; the masks likewise.

    >>> round(mann_whitney_tasks([[1, 2], [1, 2]], [[3, 4], [3, 4]], alternative="less"), 3)  # 1/6 · 1/6
    0.028
    """
    _check_alternative(alternative)
    if len(xs) != len(ys) or not len(xs):
        raise ValueError(f"mann_whitney_tasks: {len(xs)} tasks of X and {len(ys)} of Y; allowed: the same tasks, "
                         "at least one")
    sign = -1.0 if lower_is_better else 1.0
    tasks = []
    for t, (x, y) in enumerate(zip(xs, ys, strict=True)):
        x, y = _vector(x, f"mann_whitney x (task {t})"), _vector(y, f"mann_whitney y (task {t})")
        masks = []
        for name, given, size in (("x_censored", x_censored, len(x)), ("y_censored", y_censored, len(y))):
            mask = np.zeros(size, dtype=bool) if given is None else np.asarray(given[t], dtype=bool)
            if mask.shape != (size,):
                raise ValueError(f"mann_whitney {name} (task {t}): a mask of shape {mask.shape} for {size} scores; "
                                 f"allowed: ({size},)")
            masks.append(mask)
        tasks.append((len(x), len(y), _beats(sign * np.concatenate([x, y]), np.concatenate(masks))))
    total = math.prod(math.comb(n + m, n) for n, m, _ in tasks)
    exact = total <= enumerate_up_to
    generator = None if exact else (np.random.default_rng(0) if rng is None else rng)
    null, observed = 0.0, 0.0
    for task, (n, m, beats) in enumerate(tasks):
        if exact:  # every combination of the tasks' splits: task t's split varies slowest for t = 0
            splits = np.array(list(itertools.combinations(range(n + m), n)), dtype=np.int64)
            inner = math.prod(math.comb(a + b, a) for a, b, _ in tasks[task + 1:])
            splits = np.repeat(splits, inner, axis=0)
            splits = np.tile(splits, (total // len(splits), 1))
        else:
            splits = np.argsort(generator.random((draws, n + m)), axis=1)[:, :n]
        member = np.zeros((len(splits), n + m))
        np.put_along_axis(member, splits, 1.0, axis=1)
        null = null + ((member @ beats) * (1.0 - member)).sum(1) / (n * m) / len(tasks)
        observed += float(beats[:n, n:].mean()) / len(tasks)
    return _p_value(np.asarray(null), observed, 0.5, alternative, exact=exact)


def _differences(x, y, name: str) -> np.ndarray:
    x, y = _vector(x, f"{name} x"), _vector(y, f"{name} y")
    if x.shape != y.shape:
        raise ValueError(f"{name}: {len(x)} scores of X and {len(y)} of Y; allowed: one of each per pair")
    return x - y


def wilcoxon(x, y, *, lower_is_better: bool = False, alternative: str = "two-sided",
             enumerate_up_to: int = ENUMERATE, draws: int = DRAWS, rng: np.random.Generator | None = None) -> float:
    """The sign-flip p-value of the Wilcoxon signed-rank sum of the pairs' differences ``x[i] − y[i]``
    (zero differences dropped; 1.0 where none is left).

    >>> round(wilcoxon([1, 2, 3, 4, 5, 6], [2, 0, 0, 0, 0, 0]), 4)  # ranks 1 (negative) .. 6: T+ = 20
    0.0625
    """
    import scipy.stats

    _check_alternative(alternative)
    difference = _differences(x, y, "wilcoxon") * (-1.0 if lower_is_better else 1.0)
    difference = difference[difference != 0]
    if not len(difference):
        return 1.0
    ranks = scipy.stats.rankdata(np.abs(difference))  # tied magnitudes share their mean rank
    n = len(difference)
    if 2**n <= enumerate_up_to:
        signs = (np.arange(2**n)[:, None] >> np.arange(n)[None, :]) & 1
    else:
        signs = (np.random.default_rng(0) if rng is None else rng).integers(0, 2, size=(draws, n))
    null = signs @ ranks
    observed = float(ranks[difference > 0].sum())
    return _p_value(null, observed, ranks.sum() / 2, alternative, exact=2**n <= enumerate_up_to)


def sign_test(x, y, *, lower_is_better: bool = False, alternative: str = "two-sided") -> float:
    """The binomial p-value of the count of pairs where X is better, among the pairs that differ (1.0 where none do).

    >>> round(sign_test([1, 2, 3], [1, 2, 3]), 1)
    1.0
    """
    import scipy.stats

    _check_alternative(alternative)
    difference = _differences(x, y, "sign_test") * (-1.0 if lower_is_better else 1.0)
    nonzero = int((difference != 0).sum())
    if not nonzero:
        return 1.0
    return float(scipy.stats.binomtest(int((difference > 0).sum()), nonzero, 0.5, alternative=alternative).pvalue)
