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

A claimed difference that the data show to be absent is established with an equivalence test
(:func:`tost`, two one-sided tests): the difference lies within ``(low, high)`` at level
``level`` when its ``1 - 2 (1 - level)`` interval (90% for 95%) lies inside the margins. An
interval that merely contains 0 shows nothing (absence of evidence); an equivalence test has
to be passed. Trends over a grid are checked step by step (:func:`monotone_steps`) and an
interior minimum against both ends (:func:`interior_minimum`); both are intersection-union
tests (every part must pass at ``level``, which keeps the whole at ``level`` with no
correction).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Equivalence",
    "Estimate",
    "InteriorMinimum",
    "Monotonicity",
    "Verdict",
    "combine_verdicts",
    "interior_minimum",
    "mean_ci",
    "mean_ci_series",
    "monotone_steps",
    "paired_difference",
    "per_seed_slopes",
    "ratio",
    "slopes",
    "tost",
    "verdict_above",
    "verdict_below",
    "verdict_directional",
]

#: Confidence level of every interval in the reports.
LEVEL = 0.95


class Verdict(enum.StrEnum):
    """Outcome of checking one claim of the paper against the measurements."""

    #: The interval lies on the claimed side (and the effect is not negligible).
    HOLDS = "holds"
    #: The interval lies on the other side, beyond the equivalence margin.
    DOES_NOT_HOLD = "does not hold"
    #: The claimed effect is absent: an equivalence test puts it within the margin.
    NOT_REPRODUCED = "not reproduced"
    #: The interval is too wide to decide either way.
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
    from scipy import stats as _sps  # 0.37 s to import: only when a study needs it

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


def per_seed_slopes(x, y) -> np.ndarray:
    """Least-squares slope of ``y`` against ``x`` fitted separately for every seed.

    Parameters
    ----------
    x : array-like, shape (m,) or (m, n)
        The swept values (shared by all seeds), or one column of x values per seed (for
        instance the measured communication rate of each seed).
    y : array-like, shape (m, n)
        The measured value at each of the ``m`` points for each of ``n`` seeds.

    Returns
    -------
    ndarray, shape (n,)
        Units of ``y`` per unit of ``x``; ``nan`` for a seed with a non-finite value or no
        spread in ``x`` (so two sweeps over the same seeds stay paired).
    """
    y = np.asarray(y, dtype=float)
    if y.ndim != 2:
        raise ValueError(f"slopes: y must have shape (m, n), got {y.shape}")
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        x = np.repeat(x[:, None], y.shape[1], axis=1)
    if x.shape != y.shape:
        raise ValueError(f"slopes: x has shape {x.shape}, y has shape {y.shape}")
    out = np.full(y.shape[1], np.nan)
    ok = np.isfinite(y).all(axis=0) & np.isfinite(x).all(axis=0)
    xc = x[:, ok] - x[:, ok].mean(axis=0)
    yc = y[:, ok] - y[:, ok].mean(axis=0)
    denom = (xc**2).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        fitted = np.where(denom > 0, (xc * yc).sum(axis=0) / denom, np.nan)
    out[ok] = fitted
    return out


def slopes(x, y, level: float = LEVEL) -> Estimate:
    """Mean and interval of :func:`per_seed_slopes` (seeds without a slope left out)."""
    return mean_ci(per_seed_slopes(x, y), level)


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
    """A claim made of several parts that must all hold: *holds* when every part holds;
    otherwise the most decisive failure: *does not hold* when any part does not hold, else
    *not reproduced* when any part's effect is shown absent, else *inconclusive*."""
    for outcome in (Verdict.DOES_NOT_HOLD, Verdict.NOT_REPRODUCED):
        if any(v is outcome for v in verdicts):
            return outcome
    if verdicts and all(v is Verdict.HOLDS for v in verdicts):
        return Verdict.HOLDS
    return Verdict.INCONCLUSIVE


@dataclass(frozen=True)
class Equivalence:
    """Result of an equivalence test (TOST) of a mean against the margins ``(low, high)``.

    Attributes
    ----------
    estimate : Estimate
        The mean with its ``1 - 2 (1 - level)`` interval (90% for ``level = 0.95``): the
        interval whose inclusion in ``(low, high)`` is the TOST decision.
    low, high : float
        The equivalence margins (``low < 0 < high`` for a difference).
    p_value : float
        The larger of the two one-sided p-values; equivalent when below ``1 - level``.
    level : float
    """

    estimate: Estimate
    low: float
    high: float
    p_value: float
    level: float = LEVEL

    @property
    def equivalent(self) -> bool:
        """True when both one-sided tests reject at ``1 - level``."""
        return math.isfinite(self.p_value) and self.p_value < 1.0 - self.level

    @property
    def smallest_margin(self) -> float:
        """The smallest symmetric margin ``m`` for which ``(-m, m)`` would show equivalence:
        the largest absolute end of the TOST interval (``nan`` when undefined)."""
        e = self.estimate
        return max(abs(e.lo), abs(e.hi)) if e.defined else float("nan")

    def to_dict(self) -> dict[str, float | bool]:
        """Plain mapping for JSON."""
        return {
            "tost_interval": self.estimate.to_dict(),
            "margin_low": self.low,
            "margin_high": self.high,
            "p_value": self.p_value,
            "equivalent": self.equivalent,
            "smallest_symmetric_margin": self.smallest_margin,
        }


def tost(samples, low: float, high: float, level: float = LEVEL) -> Equivalence:
    """Two one-sided t-tests: is the mean of ``samples`` inside ``(low, high)``?

    Parameters
    ----------
    samples : array-like, shape (n,)
        One value per seed (for a paired comparison: the per-seed differences ``a - b``;
        for a trend: the per-seed slopes). Non-finite entries are left out.
    low, high : float
        Equivalence margins, ``low < high``.
    level : float
        ``1 - level`` is the size of each one-sided test.

    Returns
    -------
    Equivalence
        ``p = max(P(T >= (mean - low) / se), P(T <= (mean - high) / se))`` with ``T`` Student-t
        with ``n - 1`` degrees of freedom. Samples with no spread are equivalent exactly when
        their mean lies strictly inside the margins.
    """
    if not low < high:
        raise ValueError(f"tost: margins must satisfy low < high, got ({low}, {high})")
    x = np.asarray(samples, dtype=float).ravel()
    x = x[np.isfinite(x)]
    inner = mean_ci(x, 2.0 * level - 1.0)
    if x.size < 2:
        return Equivalence(inner, low, high, float("nan"), level)
    mean, se = float(x.mean()), float(x.std(ddof=1) / math.sqrt(x.size))
    if se == 0.0:
        p = 0.0 if low < mean < high else 1.0
    else:
        from scipy import stats as _sps

        dof = x.size - 1
        p_low = float(_sps.t.sf((mean - low) / se, dof))
        p_high = float(_sps.t.cdf((mean - high) / se, dof))
        p = max(p_low, p_high)
    return Equivalence(inner, low, high, p, level)


def verdict_directional(est: Estimate, equivalence: Equivalence, side: str) -> Verdict:
    """Claim "the quantity is below 0" (``side = "below"``) or "above 0" (``"above"``),
    with an equivalence test for "there is no such effect".

    *not reproduced* when ``equivalence`` shows the quantity within its margins (the claimed
    effect is absent, or too small to matter, even if its interval excludes 0); otherwise
    :func:`verdict_below` / :func:`verdict_above` on ``est`` (*inconclusive* then means the
    interval is too wide to decide either way).
    """
    if side not in ("below", "above"):
        raise ValueError(f"side must be 'below' or 'above', got {side!r}")
    if equivalence.equivalent:
        return Verdict.NOT_REPRODUCED
    return verdict_below(est) if side == "below" else verdict_above(est)


@dataclass(frozen=True)
class Monotonicity:
    """Step-by-step trend over an ordered grid.

    Attributes
    ----------
    steps : tuple of Estimate
        Paired per-seed differences ``y[k + 1] - y[k]``, ``m - 1`` of them.
    direction : int
        ``+1`` when every step's interval lies above 0 (increasing over the whole grid),
        ``-1`` when every one lies below 0, ``0`` otherwise (not shown monotone).
    """

    steps: tuple[Estimate, ...]
    direction: int

    @property
    def significant_steps(self) -> int:
        """How many steps have an interval that excludes 0."""
        return sum(s.defined and (s.lo > 0 or s.hi < 0) for s in self.steps)


def monotone_steps(y, level: float = LEVEL) -> Monotonicity:
    """Whether ``y`` changes in one direction at every step of its grid.

    Parameters
    ----------
    y : array-like, shape (m, n)
        The measured value at each of ``m`` ordered grid points for each of ``n`` seeds.

    Returns
    -------
    Monotonicity
        An intersection-union test: monotone at ``level`` only when every step is.
    """
    y = np.asarray(y, dtype=float)
    if y.ndim != 2 or y.shape[0] < 2:
        raise ValueError(f"monotone_steps: y must have shape (m >= 2, n), got {y.shape}")
    steps = tuple(paired_difference(y[k + 1], y[k], level) for k in range(y.shape[0] - 1))
    if all(s.defined and s.lo > 0 for s in steps):
        direction = 1
    elif all(s.defined and s.hi < 0 for s in steps):
        direction = -1
    else:
        direction = 0
    return Monotonicity(steps, direction)


@dataclass(frozen=True)
class InteriorMinimum:
    """Whether the minimum over a grid lies strictly inside it.

    Attributes
    ----------
    index : int
        Grid index of the smallest mean.
    to_first, to_last : Estimate
        Paired per-seed differences ``y[index] - y[0]`` and ``y[index] - y[-1]``.
    confirmed : bool
        ``index`` is interior and both intervals lie below 0.
    """

    index: int
    to_first: Estimate
    to_last: Estimate
    confirmed: bool


def interior_minimum(y, level: float = LEVEL) -> InteriorMinimum:
    """Locate the smallest mean of ``y`` over its grid and test it against both ends.

    Parameters
    ----------
    y : array-like, shape (m, n)
        ``m`` grid points, ``n`` seeds.
    """
    y = np.asarray(y, dtype=float)
    if y.ndim != 2 or y.shape[0] < 3:
        raise ValueError(f"interior_minimum: y must have shape (m >= 3, n), got {y.shape}")
    means = np.array([mean_ci(row, level).mean for row in y])
    k = int(np.nanargmin(means))
    first = paired_difference(y[k], y[0], level)
    last = paired_difference(y[k], y[-1], level)
    ok = 0 < k < y.shape[0] - 1 and first.defined and last.defined
    return InteriorMinimum(k, first, last, bool(ok and first.hi < 0 and last.hi < 0))
