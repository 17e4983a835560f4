"""Adaptive event-triggered communication, eqs. (10) and (11)."""

from __future__ import annotations

import numpy as np

__all__ = ["event_threshold", "event_triggered"]


def event_threshold(
    alpha: np.ndarray | float,
    lambda2: np.ndarray,
    gamma: np.ndarray | float,
    innovation_size: np.ndarray,
    zeta_s: np.ndarray | float,
    risk_s: np.ndarray,
    zeta_c: np.ndarray | float,
    risk_c: np.ndarray,
    risk_factor_floor: float = 0.0,
) -> np.ndarray:
    """Adaptive threshold, eq. (11).

    ``delta_ij = alpha / lambda2(G) * (1 + gamma ||Lambda_ij||)
    * (1 - zeta_s Ds(i) - zeta_c Dc(i))``.

    Conventions (``docs/algorithm.md``): ``lambda2 = 0`` (robot i's graph disconnected)
    gives ``delta = inf`` (no transmission); the risk factor is clipped below at
    ``risk_factor_floor`` (default 0: in the most dangerous spots every innovation triggers).

    Parameters
    ----------
    alpha, gamma, zeta_s, zeta_c : float or ndarray, shape (E,)
    lambda2 : ndarray, shape (E,)
        Algebraic connectivity seen by the transmitting link's robot i.
    innovation_size : ndarray, shape (E,)
        ``||Lambda_ij||`` used inside the threshold.
    risk_s, risk_c : ndarray, shape (E,)
        ``Ds(i)`` and ``Dc(i)`` in ``[0, 1]``.
    risk_factor_floor : float

    Returns
    -------
    ndarray, shape (E,)
    """
    risk = np.maximum(1.0 - zeta_s * risk_s - zeta_c * risk_c, risk_factor_floor)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(lambda2 > 0.0, alpha / np.where(lambda2 > 0.0, lambda2, 1.0), np.inf)
        out = scale * (1.0 + gamma * innovation_size) * risk
    # inf * 0 (disconnected and risk factor 0) is resolved as "no transmission".
    return np.where(np.isnan(out), np.inf, out)


def event_triggered(innovation_size: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Event condition, eq. (10): transmit when ``||Lambda_ij|| > delta_ij(G)``.

    Parameters
    ----------
    innovation_size, delta : ndarray, shape (E,)

    Returns
    -------
    ndarray of bool, shape (E,)
    """
    return innovation_size > delta
