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

__all__ = ["ALTERNATIVES", "ENUMERATE", "mann_whitney", "sign_test", "wilcoxon"]

ALTERNATIVES = ("two-sided", "greater", "less")
"""The hypotheses a test can take: X differs from Y, X is better, X is worse."""

ENUMERATE = 1_000_000
"""Relabellings enumerated whole; above this many, that many are drawn at random instead."""

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
                 alternative: str = "two-sided", draws: int = ENUMERATE, rng: np.random.Generator | None = None
                 ) -> float:
    """The permutation p-value of P(X beats Y) = ½ for independent runs ``x`` and ``y`` (one task).

    Args:
        x, y: the runs' scores, ``[n]`` and ``[m]``.
        lower_is_better: scores such as iterations to a threshold, where beating means fewer.
        x_censored, y_censored: masks of scores known only as a bound (a run that never reached the
            threshold, at its last iteration); as in :func:`gchgg.analysis.stats.probability_of_improvement`.
        alternative: ``"two-sided"``, ``"greater"`` (X better) or ``"less"``.
        draws: at most this many splits are enumerated; above, this many are drawn from ``rng``.
        rng: draws them (default: a fresh generator seeded 0).

    >>> round(mann_whitney([70, 80, 90], [100, 100, 100], lower_is_better=True,
    ...                    y_censored=[True, True, True], alternative="greater"), 3)  # 1 of 20 splits
    0.05
    """
    _check_alternative(alternative)
    x, y = _vector(x, "mann_whitney x"), _vector(y, "mann_whitney y")
    n, m = len(x), len(y)
    masks = []
    for name, mask, size in (("x_censored", x_censored, n), ("y_censored", y_censored, m)):
        mask = np.zeros(size, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        if mask.shape != (size,):
            raise ValueError(f"mann_whitney {name}: a mask of shape {mask.shape} for {size} scores; allowed: ({size},)")
        masks.append(mask)
    sign = -1.0 if lower_is_better else 1.0
    beats = _beats(sign * np.concatenate([x, y]), np.concatenate(masks))
    total = math.comb(n + m, n)
    if total <= draws:
        splits = np.array(list(itertools.combinations(range(n + m), n)), dtype=np.int64)
    else:
        generator = np.random.default_rng(0) if rng is None else rng
        splits = np.argsort(generator.random((draws, n + m)), axis=1)[:, :n]
    member = np.zeros((len(splits), n + m))
    np.put_along_axis(member, splits, 1.0, axis=1)
    null = ((member @ beats) * (1.0 - member)).sum(1) / (n * m)  # P(X beats Y) of each split
    observed = float(beats[:n, n:].mean())
    return _p_value(null, observed, 0.5, alternative, exact=total <= draws)


def _differences(x, y, name: str) -> np.ndarray:
    x, y = _vector(x, f"{name} x"), _vector(y, f"{name} y")
    if x.shape != y.shape:
        raise ValueError(f"{name}: {len(x)} scores of X and {len(y)} of Y; allowed: one of each per pair")
    return x - y


def wilcoxon(x, y, *, lower_is_better: bool = False, alternative: str = "two-sided", draws: int = ENUMERATE,
             rng: np.random.Generator | None = None) -> float:
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
    if 2**n <= draws:
        signs = (np.arange(2**n)[:, None] >> np.arange(n)[None, :]) & 1
    else:
        signs = (np.random.default_rng(0) if rng is None else rng).integers(0, 2, size=(draws, n))
    null = signs @ ranks
    observed = float(ranks[difference > 0].sum())
    return _p_value(null, observed, ranks.sum() / 2, alternative, exact=2**n <= draws)


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
