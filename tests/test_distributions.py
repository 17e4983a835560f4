"""The chi-square quantiles and the binomial test of resloc.distributions equal
scipy.stats' to 1e-10, and a run no longer imports scipy.stats."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from resloc.distributions import binomtest_pvalue, chi2, chi2_isf, chi2_ppf

DOFS = [1, 2, 3, 4, 6, 51_000, 3_264_000]
PROBABILITIES = [1e-12, 1e-6, 1e-3, 0.025, 0.05, 0.5, 0.95, 0.975, 0.999, 1 - 1e-9]


@pytest.mark.parametrize("dof", DOFS)
def test_chi2_quantiles_equal_scipy_stats(dof):
    q = np.array(PROBABILITIES)
    np.testing.assert_allclose(chi2_ppf(q, dof), stats.chi2.ppf(q, dof), rtol=1e-10)
    np.testing.assert_allclose(chi2_isf(q, dof), stats.chi2.isf(q, dof), rtol=1e-10)
    for p in PROBABILITIES:  # scalars in, floats out
        assert isinstance(chi2_ppf(p, dof), float)
        assert chi2.isf(p, dof) == pytest.approx(stats.chi2.isf(p, dof), rel=1e-10)


def test_chi2_known_values_and_domain():
    assert chi2_ppf(0.95, 3) == pytest.approx(7.814727903251178, rel=1e-12)
    assert chi2_isf(1e-3, 2) == pytest.approx(-2.0 * np.log(1e-3), rel=1e-12)  # closed form
    assert chi2_ppf(0.0, 2) == 0.0
    assert np.isinf(chi2_ppf(1.0, 2))
    assert np.isnan(chi2_ppf(1.5, 2))


def _cases():
    rng = np.random.default_rng(7)
    cases = [(0, 10, 0.5), (10, 10, 0.5), (5, 10, 0.5), (0, 1, 0.3), (1, 1, 0.3)]
    cases += [(k, 10, p) for k in (0, 5, 10) for p in (0.0, 1.0)]
    for _ in range(300):
        n = int(rng.integers(1, 60_000))
        p = float(rng.choice([0.05, 0.01, 0.5, 0.3, rng.random()]))
        spread = 4.0 * np.sqrt(n * p * (1 - p)) + 1.0
        cases.append((int(np.clip(rng.normal(p * n, spread), 0, n)), n, p))
    return cases


def test_binomtest_pvalue_equals_scipy_stats():
    for k, n, p in _cases():
        expected = stats.binomtest(k, n, p).pvalue
        assert binomtest_pvalue(k, n, p) == pytest.approx(expected, rel=1e-10, abs=1e-300), (
            k,
            n,
            p,
        )


@pytest.mark.parametrize("args", [(11, 10, 0.5), (-1, 10, 0.5), (1, 0, 0.5), (1, 10, 1.5)])
def test_binomtest_pvalue_rejects_bad_arguments(args):
    with pytest.raises(ValueError, match="binomtest_pvalue"):
        binomtest_pvalue(*args)


def test_a_run_does_not_import_scipy_stats():
    code = (
        "import sys\n"
        "from resloc.experiments.config import default_scenario\n"
        "from resloc.experiments.runner import run_scenario\n"
        "r = run_scenario(default_scenario().replace(**{'run.steps': 20}))\n"
        "r.summary()\n"
        "print('scipy.stats' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True
    )
    assert out.stdout.strip() == "False"
