"""Intervals and tests over contexts (``mpd.stats``) against direct computations: resampling written out with
numpy, scipy's binomial Wilson interval, the Benjamini-Hochberg rule by hand."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.stats import binomtest

from mpd import stats

ROOT = Path(__file__).resolve().parents[1]
# a fixed table: 20 contexts' fraction valid, skewed with a few failed contexts (zeros), as MPD's is with the
# extra objects; written out so that no rerun of a committed run can change this test
FIXED = np.array(
    [0.31, 0.0, 0.52, 0.18, 0.07, 0.44, 0.29, 0.0, 0.61, 0.25]
    + [0.12, 0.38, 0.05, 0.47, 0.22, 0.33, 0.0, 0.56, 0.19, 0.41]
)
REF_RESAMPLES = 40_000


def _direct(x: np.ndarray, stat, seed: int = 12345) -> tuple[float, float]:
    """Percentile bootstrap written out: resample contexts with replacement, take the 2.5 and 97.5 percentiles."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(x), size=(REF_RESAMPLES, len(x)))
    values = stat(x[idx])
    return float(np.percentile(values, 2.5)), float(np.percentile(values, 97.5))


def _iqm_by_hand(samples: np.ndarray) -> np.ndarray:
    s = np.sort(samples, axis=-1)
    n = s.shape[-1]
    cut = int(0.25 * n)
    return s[..., cut : n - cut].mean(axis=-1)


@pytest.mark.parametrize(
    ("statistic", "direct"),
    [("mean", lambda s: s.mean(axis=-1)), ("iqm", _iqm_by_hand)],
    ids=["mean", "iqm"],
)
def test_bootstrap_matches_direct_resampling(statistic, direct):
    est = stats.bootstrap(FIXED, statistic)
    lo, hi = _direct(FIXED, direct)
    assert est.value == pytest.approx(float(direct(FIXED[None])[0]))
    assert est.n == 20
    # the Monte Carlo error of a 2.5 % quantile with 2000 resamples is a few % of the half-width
    tol = 0.06 * (hi - lo) / 2
    assert est.lo == pytest.approx(lo, abs=tol) and est.hi == pytest.approx(hi, abs=tol)
    assert est.lo < est.value < est.hi


def test_bootstrap_on_the_committed_table_cells():
    """Every cell of a committed run: the interval agrees with the resampling written out."""
    df = pd.read_parquet(ROOT / "reports" / "eval-2d-cpu" / "results.parquet")
    for _, g in list(df.groupby("cell_key"))[:6]:
        x = g["fraction_valid"].to_numpy(float)
        est = stats.bootstrap(x)
        if np.all(x == x[0]):
            assert est.lo == est.hi == x[0]
            continue
        lo, hi = _direct(x, lambda s: s.mean(axis=-1))
        # Monte Carlo error of a 2000-resample percentile on a few discrete values: up to 7.3 % of the half-width
        # over the cells of the committed eval-2d-cpu run
        tol = 0.12 * (hi - lo) / 2
        assert est.lo == pytest.approx(lo, abs=tol) and est.hi == pytest.approx(hi, abs=tol)


def test_seeded_and_independent_of_call_order():
    a = stats.bootstrap(FIXED)
    stats.bootstrap(np.arange(7.0))  # another call in between must not move the next interval
    assert stats.bootstrap(FIXED) == a
    assert stats.bootstrap(FIXED, seed=1) != a


def test_missing_values_constant_and_single_context():
    assert stats.bootstrap(np.r_[FIXED, np.nan, np.inf]) == stats.bootstrap(FIXED)
    c = stats.bootstrap([0.4, 0.4, 0.4])
    assert c.value == pytest.approx(0.4) and c.lo == c.hi == c.value and c.n == 3
    one = stats.bootstrap([0.7])
    assert one.value == 0.7 and math.isnan(one.lo) and math.isnan(one.hi)
    none = stats.bootstrap([np.nan])
    assert none.n == 0 and math.isnan(none.value)
    with pytest.raises(ValueError, match="statistic 'median'"):
        stats.bootstrap(FIXED, "median")


@pytest.mark.parametrize(("k", "n"), [(0, 8), (8, 8), (13, 20), (1, 3)])
def test_rate_interval_is_wilsons(k, n):
    ref = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    est = stats.rate([1.0] * k + [0.0] * (n - k))
    assert est.value == pytest.approx(k / n)
    assert est.lo == pytest.approx(ref.low, abs=1e-12) and est.hi == pytest.approx(ref.high, abs=1e-12)
    assert est.hi - est.lo > 0.1  # unlike a bootstrap, not a point at 0 % or 100 %
    with pytest.raises(ValueError, match=r"values 0 or 1 per context, got \[0.0, 100.0\]"):
        stats.rate([0.0, 100.0])


def test_paired_difference_resamples_contexts_jointly():
    rng = np.random.default_rng(0)
    context = rng.random(20)  # what a context does to every method: the paired design cancels it
    a = context + 0.05 + rng.normal(0, 0.02, 20)
    b = context + rng.normal(0, 0.02, 20)
    p = stats.paired(a, b)
    rng2 = np.random.default_rng(99)
    idx = rng2.integers(0, 20, size=(REF_RESAMPLES, 20))
    diffs = (a[idx] - b[idx]).mean(axis=-1)  # the same resampled contexts for both methods
    lo, hi = np.percentile(diffs, [2.5, 97.5])
    tol = 0.06 * (hi - lo) / 2
    assert p.difference.value == pytest.approx(np.mean(a - b))
    assert p.difference.lo == pytest.approx(lo, abs=tol) and p.difference.hi == pytest.approx(hi, abs=tol)
    assert p.difference.excludes(0.0)
    # resampling the two methods independently would see the contexts' spread: a far wider interval
    unpaired = stats.unpaired_difference(a, b)
    assert unpaired.hi - unpaired.lo > 4 * (p.difference.hi - p.difference.lo)
    assert not unpaired.excludes(0.0)
    better = np.where(a > b, 1.0, np.where(a == b, 0.5, 0.0))
    assert p.p_improvement.value == pytest.approx(better.mean())
    lower = stats.paired(a, b, higher_is_better=False)
    assert lower.p_improvement.value == pytest.approx(1 - better.mean())


def test_paired_drops_pairs_with_a_missing_side():
    a = np.array([1.0, np.nan, 3.0, 4.0])
    b = np.array([0.0, 1.0, np.nan, 3.0])
    p = stats.paired(a, b)
    assert p.difference.n == 2 and p.difference.value == pytest.approx(1.0)
    with pytest.raises(ValueError, match="same contexts"):
        stats.paired([1.0, 2.0], [1.0])


def test_permutation_tests_see_a_shift_not_noise():
    rng = np.random.default_rng(1)
    a = rng.random(20)
    noise = a + rng.normal(0, 0.03, 20)
    assert stats.paired_pvalue(noise, a) > 0.05
    assert stats.paired_pvalue(noise + 0.05, a) < 0.001
    assert stats.paired_pvalue(a, a) == 1.0
    # 8 contexts: every one of the 2^8 sign flips; a shift on all 8 has p = 2/256
    assert stats.paired_pvalue(a[:8] + 1.0, a[:8]) == pytest.approx(2 / 256)
    assert stats.two_sample_pvalue(rng.random(20) + 0.5, rng.random(20)) < 0.01
    assert stats.two_sample_pvalue(rng.random(20), rng.random(20)) > 0.05


def test_discoveries_are_benjamini_hochberg():
    p = np.array([0.001, 0.008, 0.039, 0.041, 0.042, 0.06, 0.074, 0.205, 0.212, 0.216])
    # by hand: the largest k with p_(k) <= k/m * alpha, here k = 2 (0.008 <= 0.01, 0.039 > 0.015)
    assert stats.discoveries(p).tolist() == [True, True] + [False] * 8
    assert stats.discoveries([]).size == 0


def test_contexts_needed_gives_the_half_width():
    n = stats.contexts_needed(0.2, 0.05)
    assert n == math.ceil((1.959963984540054 * 0.2 / 0.05) ** 2) == 62
    x = np.random.default_rng(5).normal(0.5, 0.2, 4 * n)
    halves = [stats.bootstrap(x[i * n : (i + 1) * n]).half_width for i in range(4)]
    assert np.mean(halves) == pytest.approx(0.05, rel=0.2)
    with pytest.raises(ValueError, match="half_width 0"):
        stats.contexts_needed(0.2, 0)
