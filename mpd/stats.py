"""Statistics over contexts: confidence intervals of a cell's mean, paired comparisons of two methods on the same
contexts, and tests of whether two runs differ beyond noise.

A cell's per-context values are independent draws (one context each, its own planning seed), so every interval
here resamples contexts: a 95 % percentile bootstrap (``scipy.stats.bootstrap``) over the cell's contexts, each
cell its own stratum. A paired comparison resamples the *pairs*: the same contexts for both methods, which is what
the runner gives every method. Success is 0 or 1 per context: its interval is Wilson's score interval, which,
unlike a bootstrap, does not collapse to a point at 0 % or 100 %.

Every random choice is seeded (``SEED``, a fresh generator per call): the same values give the same interval
whatever was computed before, so a report rebuilds identically. Non-finite values (a Vendi score needs two valid
trajectories; end-effector errors do not exist on joint-goal tasks) are dropped, pairs with one side missing too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

CONFIDENCE = 0.95
N_RESAMPLES = 2000  # bootstrap resamples: Monte Carlo error of a 95 % bound ~1 % of the interval's width
N_PERMUTATIONS = 9999  # random sign flips of a paired test; exact (every flip) when 2^n is fewer
ALPHA = 0.05  # false-discovery rate of the run comparison (Benjamini-Hochberg over its cells and metrics)
SEED = 0
Z95 = 1.959963984540054  # the normal quantile of a two-sided 95 % interval


@dataclass(frozen=True)
class Estimate:
    """A statistic with its 95 % interval over ``n`` contexts (NaN bounds when ``n`` < 2)."""

    value: float
    lo: float
    hi: float
    n: int

    @property
    def half_width(self) -> float:
        return (self.hi - self.lo) / 2

    def excludes(self, x: float = 0.0) -> bool:
        """Whether the interval lies wholly on one side of ``x`` (False when it is undefined)."""
        return bool(self.lo > x or self.hi < x)


def finite(x) -> np.ndarray:
    x = np.asarray(x, dtype=float).ravel()
    return x[np.isfinite(x)]


def iqm(x, axis: int = -1):
    """Interquartile mean: the mean of the middle 50 % (robust to a few failed contexts, unlike the mean)."""
    return stats.trim_mean(x, 0.25, axis=axis)


def _mean(x, axis: int = -1):
    return np.mean(x, axis=axis)


STATISTICS = {"mean": _mean, "iqm": iqm}


def bootstrap(x, statistic: str = "mean", n_resamples: int = N_RESAMPLES, seed: int = SEED) -> Estimate:
    """The statistic (``mean`` or ``iqm``) of the finite values of ``x`` and its 95 % percentile bootstrap
    interval over them."""
    if statistic not in STATISTICS:
        raise ValueError(f"statistic {statistic!r}: expected one of {', '.join(STATISTICS)}")
    fn = STATISTICS[statistic]
    x = finite(x)
    if len(x) == 0:
        return Estimate(math.nan, math.nan, math.nan, 0)
    value = float(fn(x))
    if len(x) == 1:
        return Estimate(value, math.nan, math.nan, 1)
    if np.all(x == x[0]):  # every resample is the same: the interval is the point (scipy warns and gives NaN)
        return Estimate(value, value, value, len(x))
    res = stats.bootstrap(
        (x,),
        fn,
        n_resamples=n_resamples,
        vectorized=True,
        confidence_level=CONFIDENCE,
        method="percentile",
        rng=np.random.default_rng(seed),
    )
    ci = res.confidence_interval
    return Estimate(value, float(ci.low), float(ci.high), len(x))


def wilson(k: float, n: int, z: float = Z95) -> tuple[float, float]:
    """95 % Wilson score interval of a rate of ``k`` successes in ``n`` trials."""
    if n == 0:
        return (math.nan, math.nan)
    p = k / n
    den = 1 + z * z / n
    c = (p + z * z / (2 * n)) / den
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(c - h, 0.0), min(c + h, 1.0))


def rate(x) -> Estimate:
    """A success rate (values 0 or 1 per context) with its Wilson interval."""
    x = finite(x)
    if len(x) == 0:
        return Estimate(math.nan, math.nan, math.nan, 0)
    if not np.all((x == 0) | (x == 1)):
        raise ValueError(f"a rate needs values 0 or 1 per context, got {sorted(set(x.tolist()))[:5]}")
    lo, hi = wilson(float(x.sum()), len(x))
    return Estimate(float(x.mean()), lo, hi, len(x))


def mean_interval(x, binary: bool = False) -> Estimate:
    """The mean over contexts and its 95 % interval: Wilson for a 0/1 metric, else the bootstrap."""
    return rate(x) if binary else bootstrap(x)


def pairs(a, b) -> tuple[np.ndarray, np.ndarray]:
    """The aligned values where both sides are finite."""
    a, b = np.asarray(a, dtype=float).ravel(), np.asarray(b, dtype=float).ravel()
    if a.shape != b.shape:
        raise ValueError(f"paired values need the same contexts: {a.shape[0]} vs {b.shape[0]}")
    keep = np.isfinite(a) & np.isfinite(b)
    return a[keep], b[keep]


@dataclass(frozen=True)
class Paired:
    """A against B on the same contexts: the mean difference A - B and the probability that A is better on a
    context (ties count one half), each with its 95 % interval from the same resampled contexts."""

    difference: Estimate
    p_improvement: Estimate


def paired(a, b, higher_is_better: bool = True, seed: int = SEED) -> Paired:
    """Compare A with B context by context (``a[i]`` and ``b[i]`` from the same context)."""
    a, b = pairs(a, b)
    d = a - b
    better = np.sign(d if higher_is_better else -d)
    # resampling the difference vector resamples contexts with their pair: the same seed gives both statistics
    # the same resampled contexts
    return Paired(bootstrap(d, seed=seed), bootstrap(0.5 + 0.5 * better, seed=seed))


def unpaired_difference(a, b, seed: int = SEED) -> Estimate:
    """mean(A) - mean(B) for values from different contexts, with a bootstrap interval that resamples each side's
    contexts on its own (each side a stratum)."""
    a, b = finite(a), finite(b)
    if len(a) == 0 or len(b) == 0:
        return Estimate(math.nan, math.nan, math.nan, min(len(a), len(b)))
    value = float(a.mean() - b.mean())
    if len(a) < 2 or len(b) < 2:
        return Estimate(value, math.nan, math.nan, min(len(a), len(b)))
    if np.all(a == a[0]) and np.all(b == b[0]):
        return Estimate(value, value, value, min(len(a), len(b)))
    res = stats.bootstrap(
        (a, b),
        lambda x, y, axis: np.mean(x, axis=axis) - np.mean(y, axis=axis),
        n_resamples=N_RESAMPLES,
        vectorized=True,
        confidence_level=CONFIDENCE,
        method="percentile",
        rng=np.random.default_rng(seed),
    )
    ci = res.confidence_interval
    return Estimate(value, float(ci.low), float(ci.high), min(len(a), len(b)))


def paired_pvalue(a, b, seed: int = SEED) -> float:
    """Two-sided p-value of "A and B are the same process" for paired values: a sign-flip permutation test of the
    mean difference (exact when every flip fits in ``N_PERMUTATIONS``). 1 when every pair is equal."""
    a, b = pairs(a, b)
    if len(a) < 2 or np.all(a == b):  # one pair: the exact sign-flip p-value is 1
        return 1.0
    res = stats.permutation_test(
        (a, b),
        lambda x, y, axis: np.mean(x - y, axis=axis),
        permutation_type="samples",
        vectorized=True,
        n_resamples=N_PERMUTATIONS,
        rng=np.random.default_rng(seed),
    )
    return float(res.pvalue)


def two_sample_pvalue(a, b, seed: int = SEED) -> float:
    """Two-sided p-value of "same distribution" for unpaired values (different contexts): a permutation test of
    the difference of means."""
    a, b = finite(a), finite(b)
    if len(a) < 2 or len(b) < 2:  # too few contexts on a side to test anything (no power: reported as 1)
        return 1.0
    if np.all(a == a[0]) and np.all(b == a[0]):
        return 1.0
    res = stats.permutation_test(
        (a, b),
        lambda x, y, axis: np.mean(x, axis=axis) - np.mean(y, axis=axis),
        permutation_type="independent",
        vectorized=True,
        n_resamples=N_PERMUTATIONS,
        rng=np.random.default_rng(seed),
    )
    return float(res.pvalue)


def discoveries(pvalues, alpha: float = ALPHA) -> np.ndarray:
    """Which p-values are significant with the false-discovery rate held at ``alpha`` (Benjamini-Hochberg). When
    every null hypothesis holds (a faithful reproduction), the chance of flagging anything is at most ``alpha``."""
    p = np.asarray(pvalues, dtype=float)
    if p.size == 0:
        return np.zeros(0, dtype=bool)
    return stats.false_discovery_control(p, method="bh") <= alpha


def contexts_needed(sd: float, half_width: float, z: float = Z95) -> int:
    """Contexts for a 95 % interval of the mean of half-width ``half_width`` when the per-context standard
    deviation is ``sd`` (normal approximation: n = (z sd / h)^2)."""
    if not half_width > 0:
        raise ValueError(f"half_width {half_width!r}: must be > 0")
    if not np.isfinite(sd):
        return 0
    return max(2, math.ceil((z * sd / half_width) ** 2))


__all__ = [
    "ALPHA",
    "CONFIDENCE",
    "N_RESAMPLES",
    "Estimate",
    "Paired",
    "bootstrap",
    "contexts_needed",
    "discoveries",
    "iqm",
    "mean_interval",
    "paired",
    "paired_pvalue",
    "rate",
    "two_sample_pvalue",
    "unpaired_difference",
    "wilson",
]
