"""Danger zones and their risk fields (the paper's SDZ / CDZ, eqs. (4) and (7))."""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["RiskProfile", "Zone", "ZoneField", "risk_profile"]


class RiskProfile(enum.StrEnum):
    """Shape of a zone's risk as a function of normalized distance ``s = d / radius``.

    ``linear``: ``peak (1 - s)``; ``quadratic``: ``peak (1 - s^2)``;
    ``gaussian``: ``peak exp(-s^2 / (2 * 0.5^2))``; ``constant``: ``peak``;
    ``staircase``: five equal-width rings with ``peak * (1.0, 0.8, 0.6, 0.4, 0.2)`` from the
    centre out (the banded field of the first author's public scripts).
    All are highest at the centre and 0 for ``s > 1``.
    """

    LINEAR = "linear"
    QUADRATIC = "quadratic"
    GAUSSIAN = "gaussian"
    CONSTANT = "constant"
    STAIRCASE = "staircase"


def risk_profile(s: np.ndarray, profile: RiskProfile) -> np.ndarray:
    """Unit-peak risk at normalized distance ``s >= 0`` (0 outside ``s > 1``).

    Parameters
    ----------
    s : ndarray, any shape
    profile : RiskProfile

    Returns
    -------
    ndarray, same shape as ``s``, values in ``[0, 1]``
    """
    s = np.asarray(s, float)
    if profile is RiskProfile.LINEAR:
        g = 1.0 - s
    elif profile is RiskProfile.QUADRATIC:
        g = 1.0 - s * s
    elif profile is RiskProfile.GAUSSIAN:
        g = np.exp(-0.5 * (s / 0.5) ** 2)
    elif profile is RiskProfile.STAIRCASE:
        g = 1.0 - 0.2 * np.floor(np.minimum(s, 0.999999) * 5.0)
    else:
        g = np.ones_like(s)
    # np.clip's value, without its Python-level dispatch (a third of a small call's time)
    return np.where(s <= 1.0, np.minimum(np.maximum(g, 0.0), 1.0), 0.0)


@dataclass(frozen=True)
class Zone:
    """One danger zone: a disc with a risk field peaking at its centre.

    Attributes
    ----------
    center : tuple of float
        ``(x, y)`` in metres.
    radius : float
        Metres; the risk is 0 beyond it.
    peak : float
        Risk (attack / failure probability) at the centre, in ``[0, 1]``.
    profile : RiskProfile
    tau : float
        Zone threshold ``tau`` of eqs. (4)/(7): where the risk is below it, it counts as 0.
    """

    center: tuple[float, float]
    radius: float
    peak: float = 1.0
    profile: RiskProfile = RiskProfile.LINEAR
    tau: float = 0.0


class ZoneField:
    """The combined risk field ``R(p)`` of several zones of one kind (sensing or comms).

    Overlapping zones act independently: ``R = 1 - prod_z (1 - R_z)``.

    Parameters
    ----------
    zones : sequence of Zone
    """

    def __init__(self, zones: Sequence[Zone]) -> None:
        self.zones = tuple(zones)

    def __bool__(self) -> bool:
        return bool(self.zones)

    def risk(self, p: np.ndarray) -> np.ndarray:
        """Risk ``D(i) = R(p_i)`` at positions ``p``.

        Parameters
        ----------
        p : ndarray, shape (B, 2)

        Returns
        -------
        ndarray, shape (B,), in ``[0, 1]``
        """
        p = np.asarray(p, float)
        safe = np.ones(p.shape[0])
        for z in self.zones:
            d = np.hypot(p[:, 0] - z.center[0], p[:, 1] - z.center[1])
            r = z.peak * risk_profile(d / z.radius, z.profile)
            r = np.where(r >= z.tau, r, 0.0)
            safe *= 1.0 - r
        return 1.0 - safe

    def inside(self, p: np.ndarray) -> np.ndarray:
        """Whether positions ``p: (B, 2)`` lie in the zone set ``{R(p) >= tau, R > 0}``, (B,)."""
        return self.risk(p) > 0.0
