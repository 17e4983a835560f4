"""Chi-square quantiles and the two-sided binomial test, from :mod:`scipy.special`.

``scipy.stats`` costs about 0.37 s to import (measured on top of the scipy modules a run
already loads, which include ``scipy.special``); a run needs three quantiles and one p-value
from it. These functions give the same numbers (tested against ``scipy.stats`` to 1e-10)
without that import. :mod:`scipy.special` itself (about 0.3 s) is imported on the first
call: a run needs it only for its summary, not to start.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["binomtest_pvalue", "chi2", "chi2_isf", "chi2_ppf"]


def _special():
    from scipy import special

    return special


def chi2_ppf(q: float | np.ndarray, dof: float | np.ndarray) -> float | np.ndarray:
    """Chi-square quantile: the ``x`` with ``P(X <= x) = q`` for ``X ~ chi2(dof)``.

    ``chi2(dof)`` is ``Gamma(dof / 2, scale 2)``, so ``x = 2 P^{-1}(dof / 2, q)`` with the
    regularized lower incomplete gamma function ``P``.

    Parameters
    ----------
    q : float or ndarray
        Probability in ``[0, 1]``.
    dof : float or ndarray
        Degrees of freedom (> 0), broadcast against ``q``.

    Returns
    -------
    float or ndarray
        ``nan`` outside the domain.
    """
    out = 2.0 * _special().gammaincinv(np.multiply(0.5, dof), q)
    return float(out) if np.ndim(out) == 0 else out


def chi2_isf(p: float | np.ndarray, dof: float | np.ndarray) -> float | np.ndarray:
    """Chi-square upper quantile: the ``x`` with ``P(X > x) = p`` (accurate for tiny ``p``,
    where ``chi2_ppf(1 - p)`` would lose the digits of ``p`` to rounding)."""
    out = 2.0 * _special().gammainccinv(np.multiply(0.5, dof), p)
    return float(out) if np.ndim(out) == 0 else out


def _binom_pmf(k: float, n: int, p: float) -> float:
    if p == 0.0 or p == 1.0:
        return float(k == (0 if p == 0.0 else n))
    log_pmf = (
        _special().gammaln(n + 1.0)
        - _special().gammaln(k + 1.0)
        - _special().gammaln(n - k + 1.0)
        + k * math.log(p)
        + (n - k) * math.log1p(-p)
    )
    return math.exp(log_pmf)


def _binom_cdf(k: int, n: int, p: float) -> float:
    """``P(X <= k)`` through the regularized incomplete beta function (as scipy.stats)."""
    if k < 0:
        return 0.0
    return 1.0 if k >= n else float(_special().betainc(n - k, k + 1, 1.0 - p))


def _binom_sf(k: int, n: int, p: float) -> float:
    """``P(X > k)``."""
    if k < 0:
        return 1.0
    return 0.0 if k >= n else float(_special().betainc(k + 1, n - k, p))


def _last_index_at_most(value, bound: float, lo: int, hi: int) -> int:
    """Largest ``i`` in ``[lo - 1, hi]`` with ``value(i) <= bound``, for ``value``
    increasing on ``[lo, hi]`` (a bisection: the pmf is monotone on each side of its mode)."""
    while lo <= hi:
        mid = (lo + hi) // 2
        if value(mid) <= bound:
            lo = mid + 1
        else:
            hi = mid - 1
    return hi


def binomtest_pvalue(k: int, n: int, p: float) -> float:
    """Two-sided p-value of ``k`` successes in ``n`` Bernoulli(``p``) trials.

    The sum of the probabilities of every outcome no more likely than ``k`` (with a relative
    tolerance of 1e-7 for ties), the definition ``scipy.stats.binomtest`` uses: one tail is
    the cdf up to ``k``, the other is found by bisection on the far side of the mode.

    Parameters
    ----------
    k : int
        Successes, ``0 <= k <= n``.
    n : int
        Trials, ``n >= 1``.
    p : float
        Success probability under the null hypothesis, in ``[0, 1]``.

    Returns
    -------
    float
    """
    k, n, p = int(k), int(n), float(p)
    if not 0 <= k <= n or n < 1 or not 0.0 <= p <= 1.0:
        raise ValueError(f"binomtest_pvalue: need 0 <= k <= n, n >= 1, 0 <= p <= 1 ({k}, {n}, {p})")
    if k == p * n:
        return 1.0
    bound = _binom_pmf(k, n, p) * (1.0 + 1e-7)
    if k < p * n:
        # Upper tail: the outcomes above the mode whose pmf is at most ``bound``.
        first = n - _last_index_at_most(
            lambda i: _binom_pmf(n - i, n, p), bound, 0, n - math.ceil(p * n)
        )
        pval = _binom_cdf(k, n, p) + _binom_sf(first - 1, n, p)
    else:
        last = _last_index_at_most(lambda i: _binom_pmf(i, n, p), bound, 0, math.floor(p * n))
        pval = _binom_cdf(last, n, p) + _binom_sf(k - 1, n, p)
    return min(1.0, float(pval))


class _Chi2:
    """``chi2.ppf(q, dof)`` and ``chi2.isf(p, dof)`` under scipy.stats' names, so that a
    module written against ``scipy.stats.chi2`` switches with its import line only."""

    __slots__ = ()
    ppf = staticmethod(chi2_ppf)
    isf = staticmethod(chi2_isf)


#: The chi-square quantiles under ``scipy.stats.chi2``'s method names.
chi2 = _Chi2()
