"""Interval estimates over training runs: interquartile mean, stratified-bootstrap CIs, probability of improvement.

The definitions are those of rliable (Agarwal et al., 2021, "Deep Reinforcement Learning at the Edge
of the Statistical Precipice"), written out here with numpy alone: rliable itself pulls in arch,
seaborn and pandas for what is a few lines of array code, so it is not a dependency.

- **IQM**, the interquartile mean: the mean of the middle 50 % of the scores, ``int(0.25 · N)``
  scores cut from each end of the N sorted scores (all runs of all tasks pooled), as
  ``scipy.stats.trim_mean(scores, 0.25, axis=None)``, which rliable's ``aggregate_iqm`` calls. With
  3 runs nothing is cut (the IQM is the mean); with 4 it is the mean of the middle two.
- **95 % CI**: the percentile interval of the statistic over 2,000 stratified-bootstrap resamples:
  each resample draws, within each task, as many runs as it has, with replacement (for one task: a
  plain bootstrap of the runs). The draws come from a ``numpy.random.Generator``; by default a fresh
  one seeded 0, so that a table regenerates to the same digits.
- **Paired differences** (forks of one checkpoint, pair by pair): the mean of the pairs'
  differences X − Y with the percentile interval of 2,000 bootstrap resamples of the pairs (each
  resample draws as many pairs as there are, with replacement), :func:`paired_difference_interval`.
  With few pairs a percentile interval is too narrow (it covers less than 95 %), so
  :func:`paired_tests` gives the classical small-sample checks beside it: the paired t-test and the
  Wilcoxon signed-rank test (scipy).
- **Repeated looks** (a sequential design: runs added until an interval decides): an interval read
  after every added run excludes a value that holds more often than its nominal 5 %.
  :func:`sequential_alpha` gives Pocock's constant per-look level for looks at the given numbers of
  runs (the largest of K correlated statistics exceeds it with probability 5 % in all), with which
  every look's interval is to be drawn instead.
- **Probability of improvement** P(X beats Y): over all pairs of a run of X and a run of Y (of the
  same task), the fraction where X's run is better plus half the fraction of ties (the Mann-Whitney
  U statistic over n · m), averaged over tasks. Its CI bootstraps the runs of X and of Y
  independently (rliable's ``StratifiedIndependentBootstrap``); :func:`average_poi_interval` averages it
  over tasks whose numbers of runs differ.

One addition for right-censored scores (a run that never reached a threshold, recorded at the
iteration it was censored at: its true score is that or worse): a pair's order counts only where the
data show it. X's run beats Y's if X's is observed (not censored) and strictly better than Y's
recorded value (Y's true value is at least as bad as recorded); a pair where neither is shown
better (two censored runs, or an observed run no better than a censored one's recorded value)
counts as a tie. Without censored scores this is exactly the Mann-Whitney fraction above; with every
censored run at the same budget too (they tie among themselves and lose to every observed run).

>>> iqm([1.0, 2.0, 3.0, 4.0, 100.0, 5.0, 6.0, 7.0])  # 2 cut from each end of 8: mean of 3, 4, 5, 6
4.5
>>> probability_of_improvement([3, 1], [2, 2])  # 3 > 2 twice, 1 < 2 twice
0.5
>>> probability_of_improvement([70, 90], [80, 90], lower_is_better=True)  # 70 beats both; 90 ties 90
0.625
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Estimate", "average_poi_interval", "bootstrap_indices", "hierarchical_difference_interval", "iqm",
           "iqm_interval", "median_interval", "paired_difference_interval", "paired_tests", "poi_interval",
           "probability_of_improvement", "sequential_alpha", "unpaired_difference_interval"]

REPS = 2000
"""Bootstrap resamples per interval (rliable's default)."""

ALPHA = 0.05
"""1 − the intervals' confidence level: 95 % intervals."""


@dataclass(frozen=True)
class Estimate:
    """A point estimate, its percentile-bootstrap interval ``[low, high]``, and the runs it rests on
    (``runs``: one group's runs; ``other_runs``: the second group's, for a probability of improvement)."""

    point: float
    low: float
    high: float
    runs: int
    other_runs: int = 0

    def format(self, digits: int = 2) -> str:
        """``point [low, high]`` with ``digits`` decimals."""
        return f"{self.point:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]"


def _matrix(scores, name: str) -> np.ndarray:
    """``scores`` as a float ``[runs, tasks]`` matrix (a 1-D sequence is one task); no NaN, at least one run."""
    array = np.asarray(scores, dtype=float)
    if array.ndim == 1:
        array = array[:, None]
    if array.ndim != 2:
        raise ValueError(f"{name}: scores of shape {array.shape}; allowed: [runs] or [runs, tasks]")
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise ValueError(f"{name}: no runs (scores of shape {array.shape}); an estimate needs at least one run")
    if np.isnan(array).any():
        raise ValueError(f"{name}: a score is NaN; every run needs a score "
                         "(count a censored run at its last iteration)")
    return array


def _iqm_last_axis(values: np.ndarray) -> np.ndarray:
    """The interquartile mean along the last axis (``int(0.25 · N)`` values cut from each end)."""
    n = values.shape[-1]
    cut = int(0.25 * n)
    return np.sort(values, axis=-1)[..., cut : n - cut].mean(axis=-1)


def iqm(scores) -> float:
    """The interquartile mean of ``scores`` (``[runs]`` or ``[runs, tasks]``, pooled): the mean of the middle 50 %.

    >>> iqm([5.0, 1.0, 3.0])  # 3 runs: nothing cut, the mean
    3.0
    """
    return float(_iqm_last_axis(_matrix(scores, "iqm").ravel()))


def bootstrap_indices(runs: int, tasks: int, reps: int, rng: np.random.Generator) -> np.ndarray:
    """``[reps, runs, tasks]`` run indices: per resample and task, ``runs`` draws with replacement
    from that task's runs (the stratified bootstrap)."""
    return rng.integers(0, runs, size=(reps, runs, tasks))


def _resample(matrix: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``matrix[idx[r, i, t], t]`` for every resample r, draw i and task t: ``[reps, runs, tasks]``."""
    return np.take_along_axis(matrix[None], idx, axis=1)


def _rng(rng: np.random.Generator | None) -> np.random.Generator:
    return np.random.default_rng(0) if rng is None else rng


def _percentiles(samples: np.ndarray, alpha: float) -> tuple[float, float]:
    low, high = np.percentile(samples, [100 * alpha / 2, 100 * (1 - alpha / 2)])
    return float(low), float(high)


def _check(reps: int, alpha: float) -> None:
    if reps < 1:
        raise ValueError(f"reps={reps}: the bootstrap needs at least 1 resample (default {REPS})")
    if not 0 < alpha < 1:
        raise ValueError(f"alpha={alpha}: allowed 0 < alpha < 1 (0.05 for a 95 % interval)")


def iqm_interval(scores, *, reps: int = REPS, alpha: float = ALPHA, rng: np.random.Generator | None = None) -> Estimate:
    """The IQM of ``scores`` (``[runs]`` or ``[runs, tasks]``) and its stratified-bootstrap ``1 − alpha`` interval.

    >>> iqm_interval([4.0, 4.0, 4.0]).format(1)
    '4.0 [4.0, 4.0]'
    """
    _check(reps, alpha)
    matrix = _matrix(scores, "iqm_interval")
    runs, tasks = matrix.shape
    samples = _resample(matrix, bootstrap_indices(runs, tasks, reps, _rng(rng)))
    low, high = _percentiles(_iqm_last_axis(samples.reshape(reps, runs * tasks)), alpha)
    return Estimate(iqm(matrix), low, high, runs)


def median_interval(scores, *, reps: int = REPS, alpha: float = ALPHA,
                    rng: np.random.Generator | None = None) -> Estimate:
    """The median of ``scores`` (``[runs]``, or ``[runs, tasks]`` pooled) and its stratified-bootstrap ``1 − alpha``
    interval, for figures whose runs report medians (``docs/iteration_rounds.py``: a benchmark's rounds).

    >>> median_interval([1.0, 1.0, 1.0]).format()
    '1.00 [1.00, 1.00]'
    """
    _check(reps, alpha)
    matrix = _matrix(scores, "median_interval")
    runs, tasks = matrix.shape
    samples = _resample(matrix, bootstrap_indices(runs, tasks, reps, _rng(rng)))
    low, high = _percentiles(np.median(samples.reshape(reps, runs * tasks), axis=-1), alpha)
    return Estimate(float(np.median(matrix)), low, high, runs)


def _censored(mask, shape: tuple[int, int], name: str) -> np.ndarray:
    if mask is None:
        return np.zeros(shape, dtype=bool)
    array = np.asarray(mask, dtype=bool)
    array = array[:, None] if array.ndim == 1 else array
    if array.shape != shape:
        raise ValueError(f"{name}: a mask of shape {array.shape} for scores of shape {shape}; "
                         "allowed: the scores' shape")
    return array


def _poi(x: np.ndarray, y: np.ndarray, cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
    """P(X beats Y) for higher-is-better ``x [..., n, T]``, ``y [..., m, T]`` and their censored masks: ``[...]``."""
    xs, ys = x[..., :, None, :], y[..., None, :, :]
    better = (xs > ys) & ~cx[..., :, None, :]  # x observed and above y's value: y's true value is at most that
    worse = (ys > xs) & ~cy[..., None, :, :]
    per_task = (better + 0.5 * (~better & ~worse)).mean(axis=(-3, -2))
    return per_task.mean(axis=-1)


def _oriented(x, y, lower_is_better, x_censored, y_censored, name):
    x, y = _matrix(x, f"{name} (first group)"), _matrix(y, f"{name} (second group)")
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"{name}: {x.shape[1]} tasks in the first group, {y.shape[1]} in the second; "
                         "allowed: the same tasks")
    cx = _censored(x_censored, x.shape, f"{name} x_censored")
    cy = _censored(y_censored, y.shape, f"{name} y_censored")
    sign = -1.0 if lower_is_better else 1.0
    return sign * x, sign * y, cx, cy


def probability_of_improvement(x, y, *, lower_is_better: bool = False, x_censored=None, y_censored=None) -> float:
    """P(a run of X beats a run of Y): better in a pair, ties counted half, averaged over tasks.

    ``x`` and ``y`` are ``[runs]`` or ``[runs, tasks]`` scores (the runs may differ in number, the
    tasks may not); ``lower_is_better`` for scores such as iterations to a threshold, where beating
    means strictly fewer. ``x_censored`` / ``y_censored`` mark scores known only as a bound (see the
    module's docstring): a pair's order counts only where the data show it, else it is a tie.

    >>> probability_of_improvement([100, 50], [100, 100], lower_is_better=True, x_censored=[True, False],
    ...                            y_censored=[True, True])  # 50 beats both; censored 100 ties both
    0.75
    """
    x, y, cx, cy = _oriented(x, y, lower_is_better, x_censored, y_censored, "probability_of_improvement")
    return float(_poi(x, y, cx, cy))


def poi_interval(x, y, *, lower_is_better: bool = False, x_censored=None, y_censored=None, reps: int = REPS,
                 alpha: float = ALPHA, rng: np.random.Generator | None = None) -> Estimate:
    """:func:`probability_of_improvement` and its ``1 − alpha`` interval, the runs of X and of Y
    resampled independently (within each task)."""
    _check(reps, alpha)
    x, y, cx, cy = _oriented(x, y, lower_is_better, x_censored, y_censored, "poi_interval")
    rng = _rng(rng)
    ix = bootstrap_indices(x.shape[0], x.shape[1], reps, rng)
    iy = bootstrap_indices(y.shape[0], y.shape[1], reps, rng)
    samples = _poi(_resample(x, ix), _resample(y, iy), _resample(cx, ix), _resample(cy, iy))
    low, high = _percentiles(samples, alpha)
    return Estimate(float(_poi(x, y, cx, cy)), low, high, x.shape[0], y.shape[0])


def average_poi_interval(x, y, *, lower_is_better: bool = False, x_censored=None, y_censored=None,
                         reps: int = REPS, alpha: float = ALPHA, rng: np.random.Generator | None = None) -> Estimate:
    """:func:`probability_of_improvement` averaged over tasks whose run counts may differ, and its ``1 − alpha``
    interval: rliable's average probability of improvement, the runs of X and of Y resampled independently
    within each task (task by task, X's runs then Y's).

    ``x`` and ``y`` are sequences of one ``[runs]`` score vector per task (the same tasks, in the same order);
    ``x_censored`` / ``y_censored`` likewise, one mask per task, or None. ``runs`` and ``other_runs`` of the
    result count the runs of all tasks.

    >>> average_poi_interval([[1, 2], [9]], [[5, 6, 7], [1]], lower_is_better=True).format()  # 1 and 0
    '0.50 [0.50, 0.50]'
    """
    _check(reps, alpha)
    if len(x) != len(y) or not len(x):
        raise ValueError(f"average_poi_interval: {len(x)} tasks of the first group, {len(y)} of the second; "
                         "allowed: one score vector per task for each, the same tasks, at least one")
    masks = []
    for name, mask in (("x_censored", x_censored), ("y_censored", y_censored)):
        if mask is not None and len(mask) != len(x):
            raise ValueError(f"average_poi_interval: {name} holds {len(mask)} masks for {len(x)} tasks; "
                             "allowed: one per task, or None")
        masks.append(mask if mask is not None else [None] * len(x))
    rng, point, samples = _rng(rng), 0.0, np.zeros(reps)
    for task, (xt, yt, mx, my) in enumerate(zip(x, y, *masks, strict=True)):
        xt, yt, cx, cy = _oriented(xt, yt, lower_is_better, mx, my, f"average_poi_interval (task {task})")
        if xt.shape[1] != 1:
            raise ValueError(f"average_poi_interval (task {task}): scores of shape {xt.shape}; allowed: [runs]")
        ix = bootstrap_indices(xt.shape[0], 1, reps, rng)
        iy = bootstrap_indices(yt.shape[0], 1, reps, rng)
        point += float(_poi(xt, yt, cx, cy)) / len(x)
        samples += _poi(_resample(xt, ix), _resample(yt, iy), _resample(cx, ix), _resample(cy, iy)) / len(x)
    low, high = _percentiles(samples, alpha)
    return Estimate(point, low, high, sum(len(t) for t in x), sum(len(t) for t in y))


def paired_difference_interval(x, y, *, reps: int = REPS, alpha: float = ALPHA,
                               rng: np.random.Generator | None = None) -> Estimate:
    """The mean of the paired differences ``x[i] − y[i]`` and its ``1 − alpha`` percentile-bootstrap
    interval, the pairs resampled with replacement (``runs``: the number of pairs).

    >>> paired_difference_interval([80, 75, 90], [84, 77, 90]).format(1)  # -4, -2, 0
    '-2.0 [-4.0, 0.0]'
    """
    _check(reps, alpha)
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if x.ndim != 1 or x.shape != y.shape or not len(x):
        raise ValueError(f"paired_difference_interval needs two score vectors of one length >= 1 (pair by pair), "
                         f"got shapes {x.shape} and {y.shape}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("paired_difference_interval: scores must be finite (count a censored run at its bound)")
    difference = x - y
    idx = _rng(rng).integers(0, len(difference), size=(reps, len(difference)))
    low, high = _percentiles(difference[idx].mean(1), alpha)
    return Estimate(float(difference.mean()), low, high, len(difference))


def hierarchical_difference_interval(differences, *, reps: int = REPS, alpha: float = ALPHA,
                                     rng: np.random.Generator | None = None) -> Estimate:
    """The mean paired difference over forks from several checkpoints, and its two-stage bootstrap interval.

    ``differences`` holds one vector of paired differences ``x − y`` per checkpoint (the forks of one
    checkpoint share its first iterations, so they are not independent of each other). Each resample
    draws as many checkpoints as there are, with replacement, then within each drawn checkpoint as many
    of its pairs, with replacement; the statistic is the mean over checkpoints of their mean difference
    (each checkpoint weighs the same). ``runs`` counts the pairs, ``other_runs`` the checkpoints.

    >>> hierarchical_difference_interval([[1.0, 3.0], [2.0, 2.0, 2.0]]).point  # means 2 and 2
    2.0
    """
    _check(reps, alpha)
    groups = [np.asarray(d, dtype=float) for d in differences]
    if not groups or any(g.ndim != 1 or not len(g) or not np.isfinite(g).all() for g in groups):
        raise ValueError("hierarchical_difference_interval needs one non-empty vector of finite paired "
                         f"differences per checkpoint, got {len(groups)} vectors")
    rng = _rng(rng)
    drawn = rng.integers(0, len(groups), size=(reps, len(groups)))  # stage 1: the checkpoints of each resample
    slots = np.empty((reps, len(groups)))
    for slot in range(len(groups)):  # stage 2, per slot: the drawn checkpoint's pairs, resampled anew
        for k, group in enumerate(groups):  # (a handful of checkpoints: K² small resamples)
            within = group[rng.integers(0, len(group), size=(reps, len(group)))].mean(1)
            slots[:, slot] = np.where(drawn[:, slot] == k, within, slots[:, slot])
    samples = slots.mean(1)
    low, high = _percentiles(samples, alpha)
    point = float(np.mean([g.mean() for g in groups]))
    return Estimate(point, low, high, sum(len(g) for g in groups), len(groups))


def unpaired_difference_interval(x, y, *, reps: int = REPS, alpha: float = ALPHA,
                                 rng: np.random.Generator | None = None) -> Estimate:
    """The difference of the means ``mean(x) − mean(y)`` and its ``1 − alpha`` percentile-bootstrap
    interval, ``x`` and ``y`` resampled apart: the same runs as :func:`paired_difference_interval`
    reads, as if they were not paired. Where the pairs' partners do not correlate, pairing removes
    no noise and the two intervals are alike.

    >>> unpaired_difference_interval([80, 75, 90], [84, 77, 90]).point
    -2.0
    """
    _check(reps, alpha)
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if x.ndim != 1 or y.ndim != 1 or not len(x) or not len(y):
        raise ValueError(f"unpaired_difference_interval needs two score vectors of length >= 1, "
                         f"got shapes {x.shape} and {y.shape}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("unpaired_difference_interval: scores must be finite (count a censored run at its bound)")
    rng = _rng(rng)
    ix = rng.integers(0, len(x), size=(reps, len(x)))
    iy = rng.integers(0, len(y), size=(reps, len(y)))
    low, high = _percentiles(x[ix].mean(1) - y[iy].mean(1), alpha)
    return Estimate(float(x.mean() - y.mean()), low, high, len(x), len(y))


def sequential_alpha(looks, alpha: float = ALPHA, *, draws: int = 1_000_000,
                     rng: np.random.Generator | None = None) -> float:
    """Pocock's nominal two-sided level for each of K looks at a comparison, so that the K looks together
    reject a true null with probability ``alpha``: a design that adds runs and looks after each (at
    ``looks`` = 3, 4, 5, 6 runs per group, say) draws every look's interval at ``1 − sequential_alpha``
    instead of ``1 − alpha``.

    The looks' statistics are taken as a standardized sum of independent runs, Z_k = S(n_k) / √n_k
    (information grows with the runs), and the constant c with P(max_k |Z_k| > c) = ``alpha`` is the
    ``1 − alpha`` quantile of the maximum over ``draws`` simulated sequences (seeded: the same digits on
    every call). One look gives ``alpha`` itself. For K equally spaced looks at alpha = 0.05 it gives
    Pocock's (1977) 0.0294, 0.0221, 0.0182, 0.0158 for K = 2 … 5 (``tests/test_stats.py``).

    Args:
        looks: the numbers of runs per group at each look, increasing (e.g. ``[3, 4, 5, 6]``).
        alpha: the overall level. Default 0.05.
        draws: simulated sequences.
        rng: draws them (default: a fresh generator seeded 0).
    """
    import scipy.stats

    sizes = np.asarray(list(looks), dtype=float)
    if sizes.ndim != 1 or not len(sizes) or not np.all(sizes > 0) or np.any(np.diff(sizes) <= 0):
        raise ValueError(f"looks={list(looks)}: allowed a non-empty increasing list of run counts, each 1 or more")
    _check(draws, alpha)
    if len(sizes) == 1:
        return alpha
    rng, steps, largest = _rng(rng), np.sqrt(np.diff(sizes, prepend=0.0)), []
    for start in range(0, draws, 100_000):  # in chunks: a few MB at a time
        walk = np.cumsum(rng.standard_normal((min(100_000, draws - start), len(sizes))) * steps, axis=1)
        largest.append((np.abs(walk) / np.sqrt(sizes)).max(1))
    return float(2 * scipy.stats.norm.sf(np.quantile(np.concatenate(largest), 1 - alpha)))


def paired_tests(x, y) -> tuple[float, float]:
    """Two-sided p-values of the paired differences ``x[i] − y[i]`` having mean 0 (paired t-test) and being
    symmetric about 0 (Wilcoxon signed-rank test, zero differences dropped; exact for small samples
    without ties), from ``scipy.stats``. NaN where a test is undefined (fewer than 2 pairs, all differences
    equal for the t-test, all zero for Wilcoxon).

    >>> [round(p, 3) for p in paired_tests([80, 75, 90, 70], [84, 77, 91, 75])]  # -4, -2, -1, -5
    [0.046, 0.125]
    """
    import scipy.stats

    difference = np.asarray(x, dtype=float) - np.asarray(y, dtype=float)
    if difference.ndim != 1 or not np.isfinite(difference).all():
        raise ValueError("paired_tests needs two finite score vectors of one length (pair by pair)")
    t = w = float("nan")
    if len(difference) >= 2 and np.ptp(difference) > 0:
        t = float(scipy.stats.ttest_1samp(difference, 0.0).pvalue)
    if len(difference) >= 2 and np.any(difference != 0):
        w = float(scipy.stats.wilcoxon(difference).pvalue)
    return t, w
