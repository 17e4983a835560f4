"""The tests behind the claims table: TOST, step-wise monotonicity, interior minima, per-seed
slopes, and how verdicts of several parts combine."""

import numpy as np
import pytest
from scipy import stats as sps

from resloc.experiments.stats import (
    Estimate,
    Verdict,
    combine_verdicts,
    interior_minimum,
    monotone_steps,
    per_seed_slopes,
    slopes,
    tost,
    verdict_directional,
)


def test_tost_matches_two_scipy_one_sided_tests():
    rng = np.random.default_rng(3)
    for mean in (0.0, 0.3, 0.45, 0.8):
        x = rng.normal(mean, 1.0, 25)
        res = tost(x, -0.5, 0.5)
        p_low = sps.ttest_1samp(x, -0.5, alternative="greater").pvalue
        p_high = sps.ttest_1samp(x, 0.5, alternative="less").pvalue
        assert res.p_value == pytest.approx(max(p_low, p_high), rel=1e-10)
        # The decision is the 90% interval inside the margins.
        lo, hi = sps.t.interval(0.90, x.size - 1, loc=x.mean(), scale=sps.sem(x))
        assert res.estimate.lo == pytest.approx(lo) and res.estimate.hi == pytest.approx(hi)
        assert res.equivalent == (-0.5 < lo and hi < 0.5)
        assert res.smallest_margin == pytest.approx(max(abs(lo), abs(hi)))


def test_tost_edge_cases():
    assert tost(np.full(5, 0.1), -0.2, 0.2).equivalent
    assert not tost(np.full(5, 0.3), -0.2, 0.2).equivalent
    assert not tost([0.1], -0.2, 0.2).equivalent  # one seed decides nothing
    assert tost([0.1, np.nan, 0.11, 0.09], -0.2, 0.2).estimate.n == 3
    with pytest.raises(ValueError, match="low < high"):
        tost(np.zeros(4), 0.2, -0.2)


def test_verdict_directional_prefers_equivalence():
    tight_small = Estimate(-0.001, 0.0002, 10)
    eq = tost(-0.001 + 1e-4 * np.arange(10), -0.05, 0.05)
    assert verdict_directional(tight_small, eq, "below") is Verdict.NOT_REPRODUCED
    wide = Estimate(0.0, 1.0, 10)
    eq_wide = tost(np.linspace(-3, 3, 10), -0.05, 0.05)
    assert verdict_directional(wide, eq_wide, "below") is Verdict.INCONCLUSIVE
    big = Estimate(-1.0, 0.1, 10)
    eq_big = tost(-1.0 + 0.01 * np.arange(10), -0.05, 0.05)
    assert verdict_directional(big, eq_big, "below") is Verdict.HOLDS
    assert verdict_directional(big, eq_big, "above") is Verdict.DOES_NOT_HOLD
    with pytest.raises(ValueError, match="side"):
        verdict_directional(big, eq_big, "sideways")


def test_combine_verdicts_with_not_reproduced():
    yes, no, absent, unsure = (
        Verdict.HOLDS,
        Verdict.DOES_NOT_HOLD,
        Verdict.NOT_REPRODUCED,
        Verdict.INCONCLUSIVE,
    )
    assert combine_verdicts(yes, absent) is absent
    assert combine_verdicts(unsure, absent) is absent
    assert combine_verdicts(absent, no) is no
    assert combine_verdicts(yes, unsure) is unsure


def test_monotone_steps():
    rng = np.random.default_rng(0)
    grid = np.arange(5.0)[:, None]
    rising = grid + 0.01 * rng.standard_normal((5, 8))
    assert monotone_steps(rising).direction == 1
    assert monotone_steps(-rising).direction == -1
    flat_step = rising.copy()
    flat_step[3] = flat_step[2] + 0.01 * rng.standard_normal(8)
    mono = monotone_steps(flat_step)
    assert mono.direction == 0 and mono.significant_steps == 3
    with pytest.raises(ValueError):
        monotone_steps(np.zeros(4))


def test_interior_minimum():
    rng = np.random.default_rng(1)
    valley = np.array([3.0, 1.0, 2.0])[:, None] + 0.05 * rng.standard_normal((3, 8))
    res = interior_minimum(valley)
    assert res.index == 1 and res.confirmed and res.to_first.hi < 0 and res.to_last.hi < 0
    assert not interior_minimum(np.arange(3.0)[:, None] + 0 * valley).confirmed  # at an end
    shallow = np.array([1.0, 0.99, 1.0])[:, None] + 0.2 * rng.standard_normal((3, 8))
    assert not interior_minimum(shallow).confirmed


def test_per_seed_slopes_keep_seeds_paired():
    y = np.array([[0.0, 1.0, np.nan], [1.0, 3.0, 1.0], [2.0, 5.0, 2.0]])
    s = per_seed_slopes([0.0, 1.0, 2.0], y)
    assert s[0] == pytest.approx(1.0) and s[1] == pytest.approx(2.0) and np.isnan(s[2])
    assert slopes([0.0, 1.0, 2.0], y).n == 2
    # No spread in x for one seed: no slope there.
    x = np.array([[0.0, 1.0], [0.0, 2.0], [0.0, 3.0]])
    assert np.isnan(per_seed_slopes(x, y[:, :2])[0])
