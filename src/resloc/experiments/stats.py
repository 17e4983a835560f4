"""Statistics over seeds: means with Student-t confidence intervals, paired differences,
per-seed trends, and the verdict rules of the reproduction report.

Every experiment is run over ``n`` seeds (Monte Carlo trials). A per-seed scalar (for
instance the time-averaged MSLE of one filter) gives ``n`` independent samples; their mean is
reported with the two-sided ``level`` confidence interval

``mean +- t_{(1 + level) / 2, n - 1} * s / sqrt(n)``,

``s`` the sample standard deviation (``ddof = 1``). Within one seed every filter sees exactly
the same truth, odometry, measurements, attacks and channel outcomes (common random numbers,
see :mod:`resloc.experiments.runner`), so a comparison of two filters is a *paired* one: the
interval is computed on the per-seed differences, which removes the seed-to-seed variation
both filters share.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
from scipy import stats as _sps

__all__ = [
    "Estimate",
    "Verdict",
    "combine_verdicts",
    "mean_ci",
    "mean_ci_series",
    "paired_difference",
    "ratio",
    "slopes",
    "verdict_above",
    "verdict_below",
]

#: Confidence level of every interval in the reports.
LEVEL = 0.95


class Verdict(enum.StrEnum):
    """Outcome of checking one claim of the paper against the measurements."""

    HOLDS = "holds"
    DOES_NOT_HOLD = "does not hold"
    INCONCLUSIVE = "inconclusive"


@dataclass(frozen=True)
class Estimate:
    """A mean over seeds with its confidence interval.

    Attributes
    ----------
    mean : float
    half : float
        Half-width of the interval (``nan`` with fewer than two finite samples).
    n : int
        Number of finite samples.
    level : float
    """

    mean: float
    half: float
    n: int
    level: float = LEVEL

    @property
    def lo(self) -> float:
        """Lower end of the interval."""
        return self.mean - self.half

    @property
    def hi(self) -> float:
        """Upper end of the interval."""
        return self.mean + self.half

    @property
    def defined(self) -> bool:
        """True when the interval is finite (``n >= 2`` and finite values)."""
        return math.isfinite(self.mean) and math.isfinite(self.half)

    def format(self, spec: str = ".3g") -> str:
        """``"mean ± half"`` (``"mean (n=1)"`` without an interval, ``"-"`` when undefined)."""
        if not math.isfinite(self.mean):
            return "-"
        if not math.isfinite(self.half):
            return f"{self.mean:{spec}} (n={self.n})"
        return f"{self.mean:{spec}} ± {self.half:{spec}}"

    def to_dict(self) -> dict[str, float]:
        """Plain mapping for JSON."""
        return {
            "mean": self.mean,
            "ci_half": self.half,
            "ci_lo": self.lo,
            "ci_hi": self.hi,
            "n": self.n,
            "level": self.level,
        }


def _t_quantile(n: int | np.ndarray, level: float) -> float | np.ndarray:
    """Two-sided Student-t quantile ``t_{(1 + level) / 2, n - 1}`` (``nan`` for ``n < 2``)."""
    n = np.asarray(n)
    with np.errstate(invalid="ignore"):
        q = _sps.t.ppf(0.5 + level / 2.0, np.where(n >= 2, n - 1, 1))
    return np.where(n >= 2, q, np.nan)


def mean_ci(samples, level: float = LEVEL) -> Estimate:
    """Mean of the finite per-seed samples and its Student-t confidence interval.

    Parameters
    ----------
    samples : array-like, shape (n,)
        One value per seed; ``nan``/``inf`` entries are left out.
    level : float
        Confidence level in (0, 1).

    Returns
    -------
    Estimate
        ``half = t_{(1+level)/2, n-1} * std(ddof=1) / sqrt(n)``; ``nan`` when ``n < 2``.
    """
    x = np.asarray(samples, dtype=float).ravel()
    x = x[np.isfinite(x)]
    n = x.size
    if n == 0:
        return Estimate(float("nan"), float("nan"), 0, level)
    mean = float(x.mean())
    if n < 2:
        return Estimate(mean, float("nan"), 1, level)
    half = float(_t_quantile(n, level) * x.std(ddof=1) / math.sqrt(n))
    return Estimate(mean, half, n, level)


def mean_ci_series(samples: np.ndarray, level: float = LEVEL) -> tuple[np.ndarray, np.ndarray]:
    """Mean and CI half-width along the last axis (seeds), ignoring ``nan``.

    Parameters
    ----------
    samples : ndarray, shape (..., n)
        For example an MSLE series ``(steps, T)``.

    Returns
    -------
    mean, half : ndarray, shape (...)
        ``half`` is ``nan`` where fewer than two finite samples exist.
    """
    x = np.asarray(samples, dtype=float)
    ok = np.isfinite(x)
    n = ok.sum(axis=-1)
    xz = np.where(ok, x, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = xz.sum(axis=-1) / n
        dev = np.where(ok, x - mean[..., None], 0.0)
        var = (dev**2).sum(axis=-1) / (n - 1)
        half = _t_quantile(n, level) * np.sqrt(var) / np.sqrt(n)
    mean = np.where(n > 0, mean, np.nan)
    half = np.where(n >= 2, half, np.nan)
    return mean, half


def paired_difference(a, b, level: float = LEVEL) -> Estimate:
    """Mean of the per-seed differences ``a - b`` with its confidence interval.

    Valid as a paired comparison because ``a[t]`` and ``b[t]`` come from the same seed
    (identical data). Seeds where either value is not finite are left out.

    Parameters
    ----------
    a, b : array-like, shape (n,)
    """
    a = np.asarray(a, dtype=float).ravel()
    b = np.asarray(b, dtype=float).ravel()
    if a.shape != b.shape:
        raise ValueError(f"paired samples differ in length: {a.shape} vs {b.shape}")
    return mean_ci(a - b, level)


def ratio(a, b, level: float = LEVEL) -> Estimate:
    """Mean of the per-seed ratios ``a / b`` with its confidence interval."""
    a = np.asarray(a, dtype=float).ravel()
    b = np.asarray(b, dtype=float).ravel()
    with np.errstate(invalid="ignore", divide="ignore"):
        return mean_ci(a / b, level)


def slopes(x, y, level: float = LEVEL) -> Estimate:
    """Least-squares slope of ``y`` against ``x`` fitted per seed, then averaged over seeds.

    Parameters
    ----------
    x : array-like, shape (m,) or (m, n)
        The swept values (shared by all seeds), or one column of x values per seed (for
        instance the measured communication rate of each seed).
    y : array-like, shape (m, n)
        The measured value at each of the ``m`` points for each of ``n`` seeds.

    Returns
    -------
    Estimate
        Of the per-seed slopes (units of ``y`` per unit of ``x``); seeds with a non-finite
        value or no spread in ``x`` are left out.
    """
    y = np.asarray(y, dtype=float)
    if y.ndim != 2:
        raise ValueError(f"slopes: y must have shape (m, n), got {y.shape}")
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        x = np.repeat(x[:, None], y.shape[1], axis=1)
    if x.shape != y.shape:
        raise ValueError(f"slopes: x has shape {x.shape}, y has shape {y.shape}")
    ok = np.isfinite(y).all(axis=0) & np.isfinite(x).all(axis=0)
    xc = x[:, ok] - x[:, ok].mean(axis=0)
    yc = y[:, ok] - y[:, ok].mean(axis=0)
    denom = (xc**2).sum(axis=0)
    good = denom > 0
    per_seed = (xc[:, good] * yc[:, good]).sum(axis=0) / denom[good]
    return mean_ci(per_seed, level)


def verdict_below(est: Estimate, bound: float = 0.0) -> Verdict:
    """Claim "the quantity is below ``bound``": holds when the whole interval is below,
    does not hold when the whole interval is above, inconclusive otherwise."""
    if not est.defined:
        return Verdict.INCONCLUSIVE
    if est.hi < bound:
        return Verdict.HOLDS
    if est.lo > bound:
        return Verdict.DOES_NOT_HOLD
    return Verdict.INCONCLUSIVE


def verdict_above(est: Estimate, bound: float = 0.0) -> Verdict:
    """Claim "the quantity is above ``bound``" (mirror of :func:`verdict_below`)."""
    if not est.defined:
        return Verdict.INCONCLUSIVE
    if est.lo > bound:
        return Verdict.HOLDS
    if est.hi < bound:
        return Verdict.DOES_NOT_HOLD
    return Verdict.INCONCLUSIVE


def combine_verdicts(*verdicts: Verdict) -> Verdict:
    """A claim made of several parts: holds when every part holds, does not hold when any part
    does not hold, inconclusive otherwise."""
    if any(v is Verdict.DOES_NOT_HOLD for v in verdicts):
        return Verdict.DOES_NOT_HOLD
    if verdicts and all(v is Verdict.HOLDS for v in verdicts):
        return Verdict.HOLDS
    return Verdict.INCONCLUSIVE
