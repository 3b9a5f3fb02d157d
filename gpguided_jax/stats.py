"""Summary statistics over seeds, with rliable's definitions (Agarwal et al., NeurIPS 2021).

NumPy, for finished runs (not traced):

* `t_interval`: the mean over seeds and the half-width of its Student-t interval (every t-interval
  of the project's summaries, tables and figures);
* `iqm`: the interquartile mean, ``scipy.stats.trim_mean(x, 0.25)`` (rliable `aggregate_iqm`);
* `bootstrap_ci`: the percentile interval of a statistic over bootstrap resamples of the seeds
  (with one task, one environment, rliable's "stratified" bootstrap resamples the runs, seeds,
  of each method with replacement);
* `probability_of_improvement`: P(X > Y) = U / (n m) with U the Mann-Whitney statistic of
  `scipy.stats.mannwhitneyu(x, y, alternative="greater")` (ties count one half), rliable's
  `probability_of_improvement`; its interval resamples the seeds of X and of Y independently.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

DEFAULT_REPS = 20_000


def trim_mean(a, proportiontocut: float, axis: int = 0) -> np.ndarray:
    """``scipy.stats.trim_mean`` for NumPy arrays, the same operations (so the same bits): the
    mean after cutting int(proportiontocut * n) values from each end along `axis`. In NumPy
    because importing scipy.stats loads SciPy's OpenBLAS, whose thread count the command line
    must set before it loads (`runtime.single_threaded_lapack`), and takes over a second."""
    a = np.asarray(a)
    n = a.shape[axis]
    low = int(proportiontocut * n)
    high = n - low
    if low > high:
        raise ValueError("Proportion too big.")
    part = np.partition(a, (low, high - 1), axis)
    keep = [slice(None)] * part.ndim
    keep[axis] = slice(low, high)
    return np.mean(part[tuple(keep)], axis=axis)


def t_quantile(q, df):
    """``scipy.stats.t.ppf(q, df)``: the same function (`scipy.special.stdtrit`, which scipy.stats
    calls), the same bits, without importing scipy.stats (slow to import, and it loads OpenBLAS,
    see `trim_mean`)."""
    from scipy import special

    return special.stdtrit(df, q)


def t_interval(samples, axis: int = 0, confidence: float = 0.95):
    """Mean and half-width of the Student-t confidence interval of the mean along `axis`:
    (mean, half_width), the interval mean +- half_width. The half-width is NaN for fewer than two
    samples (a caller that draws a band of zero width then says so)."""
    x = np.asarray(samples, float)
    n = x.shape[axis]
    mean = x.mean(axis=axis)
    if n < 2:
        return mean, np.full_like(mean, np.nan)
    return mean, t_quantile(0.5 + confidence / 2, n - 1) * x.std(axis=axis, ddof=1) / np.sqrt(n)


def iqm(x) -> float:
    """Interquartile mean: the mean of the middle 50% (25% trimmed from each end)."""
    return float(trim_mean(np.asarray(x, float).ravel(), proportiontocut=0.25))


def _trim_mean_rows(samples: np.ndarray) -> np.ndarray:
    return trim_mean(samples, proportiontocut=0.25, axis=1)


def bootstrap_ci(x, statistic: Callable = _trim_mean_rows, *, reps: int = DEFAULT_REPS,
                 confidence: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of `statistic` over resamples of the seeds.

    Args:
      x: (n,) per-seed scores.
      statistic: maps (reps, n) resamples to (reps,) values (default: the IQM of each row).
      reps: number of bootstrap resamples.
      confidence: coverage of the interval.
      seed: NumPy seed of the resampling (the intervals are reproducible).
    """
    x = np.asarray(x, float).ravel()
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(x), size=(reps, len(x)))
    values = statistic(x[idx])
    tail = 50.0 * (1.0 - confidence)
    lo, hi = np.percentile(values, [tail, 100.0 - tail])
    return float(lo), float(hi)


def probability_of_improvement(x, y) -> float:
    """P(X > Y) for one task: the Mann-Whitney U of x over y divided by n m (ties count 1/2)."""
    x, y = np.asarray(x, float).ravel(), np.asarray(y, float).ravel()
    greater = (x[:, None] > y[None, :]).sum()
    ties = (x[:, None] == y[None, :]).sum()
    return float((greater + 0.5 * ties) / (len(x) * len(y)))


def probability_of_improvement_ci(x, y, *, reps: int = DEFAULT_REPS, confidence: float = 0.95,
                                  seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of P(X > Y), resampling the seeds of x and y independently."""
    x, y = np.asarray(x, float).ravel(), np.asarray(y, float).ravel()
    rng = np.random.default_rng(seed)
    ix = rng.integers(0, len(x), size=(reps, len(x)))
    iy = rng.integers(0, len(y), size=(reps, len(y)))
    # P(X > Y) of each resample through ranks: with both samples sorted, count pairs by searchsorted.
    xs, ys = x[ix], np.sort(y[iy], axis=1)
    below = np.stack([np.searchsorted(ys[r], xs[r], side="left") for r in range(reps)])
    at_or_below = np.stack([np.searchsorted(ys[r], xs[r], side="right") for r in range(reps)])
    values = (below + 0.5 * (at_or_below - below)).sum(axis=1) / (len(x) * len(y))
    tail = 50.0 * (1.0 - confidence)
    lo, hi = np.percentile(values, [tail, 100.0 - tail])
    return float(lo), float(hi)
