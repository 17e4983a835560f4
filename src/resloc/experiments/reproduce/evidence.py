"""Quantities with units and the tests that decide a claim (used by
:mod:`~resloc.experiments.reproduce.claims`).

A per-seed quantity carries its unit (:class:`Samples`), and so does a number the paper
states (:class:`PaperValue`): comparing them across units raises :class:`UnitMismatchError`.
A claimed effect (a paired difference, a change over a grid) is decided by its 95% interval
and an equivalence test against :data:`EQUIVALENCE_MARGIN` (:func:`directional`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from resloc.experiments.stats import (
    Equivalence,
    Estimate,
    Verdict,
    mean_ci,
    tost,
    verdict_above,
    verdict_below,
    verdict_directional,
)

__all__ = [
    "EQUIVALENCE_MARGIN",
    "METRIC_UNITS",
    "Directional",
    "PaperValue",
    "Samples",
    "UnitMismatchError",
    "check_unit",
    "compare_with_paper",
    "directional",
    "format_with_unit",
]


class UnitMismatchError(ValueError):
    """Two quantities in different units were compared."""


@dataclass(frozen=True)
class PaperValue:
    """A number the paper states, in the unit it states it in.

    Attributes
    ----------
    value : float
    unit : str
        ``"m"``, ``"m^2"`` or ``"1"`` (a fraction).
    source : str
        Where the paper says it.
    """

    value: float
    unit: str
    source: str


#: Units of the per-seed metrics of :meth:`~resloc.experiments.runner.EstimatorResult.per_trial`.
METRIC_UNITS = {
    "msle_mean": "m^2",
    "msle_final": "m^2",
    "rmse_mean": "m",
    "rmse_final": "m",
    "nees_mean": "1",
    "comm_rate": "1",
}
#: Relative equivalence margin: a difference or trend smaller than 5% of the reference level
#: counts as absent. The paper calls the CKF's advantage "significant" and "consistently"
#: better and draws its curves visibly apart; 5% of MSLE is 2.5% of the root-mean-square
#: distance error, below what its figures could show as a separated curve and far below the
#: changes it attributes to the zones (2-3x). The claims table also gives, for each test, the
#: smallest margin at which equivalence would be shown, so another margin can be read off.
EQUIVALENCE_MARGIN = 0.05
#: The unit of each quantity's rendering in the "measured" column.
_UNIT_TEXT = {"m": " m", "m^2": " m^2", "1": ""}


@dataclass(frozen=True)
class Samples:
    """Per-seed values of one quantity with its unit.

    Attributes
    ----------
    values : ndarray, shape (n,)
    unit : str
    """

    values: np.ndarray
    unit: str

    def estimate(self) -> Estimate:
        """Mean and 95% interval over seeds."""
        return mean_ci(self.values)

    def sqrt(self) -> Samples:
        """The per-seed root (``m^2`` becomes ``m``)."""
        roots = {"m^2": "m", "1": "1"}
        if self.unit not in roots:
            raise UnitMismatchError(f"no square root defined for unit {self.unit!r}")
        return Samples(np.sqrt(np.asarray(self.values, float)), roots[self.unit])


def check_unit(unit: str, other: str, what: str) -> None:
    if unit != other:
        raise UnitMismatchError(f"{what}: a quantity in {unit} compared with one in {other}")


def compare_with_paper(samples: Samples, paper: PaperValue, side: str) -> Verdict:
    """Claim "the quantity is ``side`` (below/above) the paper's value"; the units must agree."""
    check_unit(samples.unit, paper.unit, f"comparison with the paper's {paper.source}")
    check = verdict_below if side == "below" else verdict_above
    return check(samples.estimate(), paper.value)


@dataclass(frozen=True)
class Directional:
    """A claimed effect (``side`` of 0) tested with its interval and an equivalence test.

    Attributes
    ----------
    estimate : Estimate
        Of the per-seed effect (a paired difference or a slope), 95%.
    equivalence : Equivalence
        TOST against ``(-margin, margin)``.
    reference : float
        The level the margin is relative to (same unit as the effect).
    verdict : Verdict
    """

    estimate: Estimate
    equivalence: Equivalence
    reference: float
    verdict: Verdict

    @property
    def relative(self) -> float:
        """The effect relative to the reference level."""
        return self.estimate.mean / self.reference if self.reference else float("nan")

    @property
    def smallest_relative_margin(self) -> float:
        """The smallest relative margin at which equivalence would be shown."""
        m = self.equivalence.smallest_margin
        return m / abs(self.reference) if self.reference else float("nan")

    def format(self, spec: str = ".3g") -> str:
        """``"mean ± half (+x%); equivalent within ±5%: yes (from ±y%)"``."""
        eq = "yes" if self.equivalence.equivalent else "no"
        return (
            f"{self.estimate.format(spec)} ({_percent(self.relative)}); equivalent within "
            f"±{EQUIVALENCE_MARGIN:.0%}: {eq} (shown from ±"
            f"{_percent(self.smallest_relative_margin, signed=False)})"
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain mapping for JSON."""
        return {
            **self.estimate.to_dict(),
            "relative": self.relative,
            "reference": self.reference,
            "equivalence": self.equivalence.to_dict(),
            "verdict": self.verdict.value,
        }


def _percent(x: float, signed: bool = True) -> str:
    """A relative value in percent, keeping one significant digit below 0.01%."""
    sign = "+" if signed else ""
    if not math.isfinite(x):
        return "-"
    if x == 0 or abs(x) >= 1e-4:
        return f"{x:{sign}.2%}"
    return f"{x * 100:{sign}.1g}%"


def directional(effect, reference: float, side: str) -> Directional:
    """Test a claimed effect from its per-seed values.

    Parameters
    ----------
    effect : array-like, shape (n,)
        Per-seed effect (a paired difference ``a - b``, or a per-seed slope times the grid's
        range so that it is a change in the measured unit).
    reference : float
        The level the effect is judged against (the comparator's mean); the equivalence
        margin is ``EQUIVALENCE_MARGIN * |reference|``.
    side : str
        ``"below"`` (the claim is a negative effect) or ``"above"``.
    """
    effect = np.asarray(effect, float)
    margin = EQUIVALENCE_MARGIN * abs(reference)
    est = mean_ci(effect)
    if margin > 0 and math.isfinite(margin):
        eq = tost(effect, -margin, margin)
    else:
        eq = Equivalence(est, -margin, margin, float("nan"))
    return Directional(est, eq, float(reference), verdict_directional(est, eq, side))


def format_with_unit(est: Estimate, unit: str, spec: str = ".3g") -> str:
    """``"mean ± half unit"``."""
    return est.format(spec) + _UNIT_TEXT[unit]
