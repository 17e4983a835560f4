"""Statistics over seeds: Student-t intervals against scipy, paired differences, slopes,
verdict rules."""

import math

import numpy as np
import pytest
from scipy import stats as sps

from resloc.experiments.stats import (
    Estimate,
    Verdict,
    combine_verdicts,
    mean_ci,
    mean_ci_series,
    paired_difference,
    ratio,
    slopes,
    verdict_above,
    verdict_below,
)


@pytest.mark.parametrize("n", [2, 3, 5, 10, 40])
@pytest.mark.parametrize("level", [0.9, 0.95, 0.99])
def test_mean_ci_matches_scipy_t_interval(rng, n, level):
    x = rng.normal(3.0, 2.0, size=n)
    est = mean_ci(x, level)
    lo, hi = sps.t.interval(level, n - 1, loc=x.mean(), scale=sps.sem(x))
    assert est.n == n and est.level == level
    assert est.mean == pytest.approx(x.mean(), rel=1e-12)
    assert est.lo == pytest.approx(lo, rel=1e-12) and est.hi == pytest.approx(hi, rel=1e-12)


def test_mean_ci_edge_cases():
    one = mean_ci([2.5])
    assert one.mean == 2.5 and one.n == 1 and math.isnan(one.half) and not one.defined
    assert one.format() == "2.5 (n=1)"
    none = mean_ci([])
    assert none.n == 0 and math.isnan(none.mean) and none.format() == "-"
    # Non-finite samples are left out.
    est = mean_ci([1.0, np.nan, 3.0, np.inf])
    ref = mean_ci([1.0, 3.0])
    assert est == ref and est.n == 2
    # Constant samples: zero-width interval.
    const = mean_ci([0.7] * 5)
    assert const.half == 0.0 and const.lo == const.hi == pytest.approx(0.7)
    assert Estimate(1.0, 0.5, 3).format(".2f") == "1.00 ± 0.50"


def test_mean_ci_series_equals_columnwise(rng):
    x = rng.normal(size=(7, 6))
    x[2, 3] = np.nan
    x[4, :5] = np.nan  # one finite sample: no interval
    x[5, :] = np.nan  # no sample
    mean, half = mean_ci_series(x)
    for k in range(7):
        est = mean_ci(x[k])
        np.testing.assert_equal(np.isnan(mean[k]), math.isnan(est.mean))
        if est.n:
            assert mean[k] == pytest.approx(est.mean, rel=1e-12)
        if est.n >= 2:
            assert half[k] == pytest.approx(est.half, rel=1e-12)
        else:
            assert np.isnan(half[k])


def test_paired_difference_matches_scipy_ttest_rel(rng):
    common = rng.normal(size=12) * 10.0  # shared seed-to-seed variation
    a = common + rng.normal(0.0, 0.1, 12)
    b = common + 0.2 + rng.normal(0.0, 0.1, 12)
    d = paired_difference(a, b)
    ci = sps.ttest_rel(a, b).confidence_interval(0.95)
    assert d.lo == pytest.approx(ci.low, rel=1e-10) and d.hi == pytest.approx(ci.high, rel=1e-10)
    # Pairing removes the shared variation: the unpaired intervals overlap, the paired one
    # excludes 0.
    assert mean_ci(a).hi > mean_ci(b).lo and d.hi < 0
    with pytest.raises(ValueError):
        paired_difference([1.0, 2.0], [1.0])


def test_ratio_and_slopes(rng):
    r = ratio([2.0, 4.0, 6.0], [1.0, 2.0, 3.0])
    assert r.mean == pytest.approx(2.0) and r.half == pytest.approx(0.0)
    x = np.array([0.2, 0.3, 0.4, 0.5])
    y = 3.0 * x[:, None] + 1.0 + rng.normal(0.0, 1e-3, size=(4, 8))
    s = slopes(x, y)
    assert s.n == 8 and s.mean == pytest.approx(3.0, abs=0.02) and 0.0 < s.half < 0.02
    # Per-seed x: each seed's own abscissae.
    xs = x[:, None] + rng.uniform(0.0, 0.05, size=(4, 8))
    s2 = slopes(xs, -2.0 * xs + 5.0)
    assert s2.mean == pytest.approx(-2.0) and s2.half == pytest.approx(0.0, abs=1e-9)
    # Seeds with a non-finite value are left out.
    y[1, 0] = np.nan
    assert slopes(x, y).n == 7
    with pytest.raises(ValueError):
        slopes(x, y[:3])


def test_verdict_rules():
    assert verdict_below(Estimate(-1.0, 0.5, 5)) is Verdict.HOLDS
    assert verdict_below(Estimate(1.0, 0.5, 5)) is Verdict.DOES_NOT_HOLD
    assert verdict_below(Estimate(0.2, 0.5, 5)) is Verdict.INCONCLUSIVE
    assert verdict_below(Estimate(0.1, 0.05, 5), bound=0.25) is Verdict.HOLDS
    assert verdict_above(Estimate(1.0, 0.5, 5)) is Verdict.HOLDS
    assert verdict_above(Estimate(-1.0, 0.5, 5)) is Verdict.DOES_NOT_HOLD
    assert verdict_above(Estimate(1.0, float("nan"), 1)) is Verdict.INCONCLUSIVE
    yes, no, unsure = Verdict.HOLDS, Verdict.DOES_NOT_HOLD, Verdict.INCONCLUSIVE
    assert combine_verdicts(yes, yes) is yes
    assert combine_verdicts(yes, unsure) is unsure
    assert combine_verdicts(unsure, no, yes) is no
    assert combine_verdicts() is unsure
