"""Unit-aware attack detection: the NIS chi-square gate and a CUSUM test on the NIS.

The paper's detector thresholds ``||Lambda||``, which adds metres to radians. The normalized
innovation squared ``NIS = Lambda^T S^{-1} Lambda`` (``S = P^zz``) is dimensionless and, for a
consistent filter and an honest measurement, chi-square distributed with 2 degrees of
freedom, so a gate ``NIS > chi2.ppf(1 - p_fa, 2)`` has false-alarm probability ``p_fa``
(Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4; the detector norm ``nis`` compares
``sqrt(NIS)`` with ``rho = sqrt(chi2.ppf(1 - p_fa, 2))``).

A per-measurement gate cannot see a small *persistent* bias that stays under its threshold.
Page's CUSUM (Page 1954; Basseville & Nikiforov 1993, sec. 2.2) accumulates the excess of the
NIS over a reference ``k`` per link,

``g_k = min(max(0, g_{k-1} + NIS_k - k), cap)``,

and raises an alarm while ``g_k > h``. Under no attack ``E[NIS] = 2 < k`` and ``g`` stays near
0; a bias that lifts the mean NIS above ``k`` drives ``g`` over ``h`` in about
``h / (E[NIS] - k)`` measurements. The cap bounds the statistic so that a link is released
about ``(cap - h) / (k - 2)`` honest measurements after an attack ends.

While a link alarms, the CL step (:func:`resloc.cl.step.correct`) discards its measurements
whose own NIS exceeds ``k``: the gate tightens from ``chi2.ppf(1 - p_fa, 2)`` to ``k`` instead of
closing the link, so the honest measurements of an intermittently attacked link (an SDZ
falsifies each with probability ``Ds(i)``) keep the robot localized.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from resloc.linalg import solve_spd

__all__ = ["chi2_gate", "cusum_alarm", "cusum_update", "link_cusum", "nis"]


def nis(nu: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Normalized innovation squared ``Lambda^T S^{-1} Lambda`` (by a Cholesky solve).

    Parameters
    ----------
    nu : ndarray, shape (E, 2)
    S : ndarray, shape (E, 2, 2)

    Returns
    -------
    ndarray, shape (E,)
    """
    w = solve_spd(S, nu[:, :, None])[:, :, 0]
    return np.maximum(np.einsum("ei,ei->e", nu, w), 0.0)


def chi2_gate(p_fa: float | np.ndarray, dof: int = 2) -> float | np.ndarray:
    """NIS threshold with false-alarm probability ``p_fa``: ``chi2.ppf(1 - p_fa, dof)``.

    Parameters
    ----------
    p_fa : float or ndarray
        In ``(0, 1)``.
    dof : int
        Measurement dimension (2 for range/bearing).

    Returns
    -------
    float or ndarray
        Threshold on ``NIS`` (the ``nis`` detector norm compares with its square root).
    """
    out = chi2.isf(np.asarray(p_fa, dtype=float), dof)
    return float(out) if np.ndim(out) == 0 else out


def cusum_update(
    g: np.ndarray,
    stat: np.ndarray,
    k: float | np.ndarray,
    cap: float | np.ndarray,
) -> np.ndarray:
    """One CUSUM step ``min(max(0, g + stat - k), cap)``.

    Parameters
    ----------
    g : ndarray, shape (E,)
        Previous statistics (0 for a link never seen).
    stat : ndarray, shape (E,)
        This step's NIS of each link.
    k : float or ndarray, shape (E,)
        Reference (drift) value.
    cap : float or ndarray, shape (E,)
        Upper bound of the statistic.

    Returns
    -------
    ndarray, shape (E,)
    """
    return np.minimum(np.maximum(g + stat - k, 0.0), cap)


def cusum_alarm(g: np.ndarray, h: float | np.ndarray) -> np.ndarray:
    """Alarm while ``g > h``.

    Parameters
    ----------
    g : ndarray, shape (E,)
    h : float or ndarray, shape (E,)

    Returns
    -------
    ndarray of bool, shape (E,)
    """
    return g > h


def link_cusum(
    store,
    i: np.ndarray,
    j: np.ndarray,
    stat: np.ndarray,
    k: float | np.ndarray,
    h: float | np.ndarray,
    cap: float | np.ndarray | None = None,
) -> np.ndarray:
    """Update the per-link CUSUM in ``store`` with this step's NIS and return the alarms.

    Parameters
    ----------
    store : LinkStatistic
        Per-link statistics (``LinkMemory.cusum``), updated in place.
    i, j : ndarray of int, shape (E,)
        Links (distinct within one call).
    stat : ndarray, shape (E,)
        NIS of each link.
    k, h : float or ndarray, shape (E,)
        Reference and alarm threshold.
    cap : float or ndarray, shape (E,), optional
        Upper bound of the statistic (default ``2 h``).

    Returns
    -------
    ndarray of bool, shape (E,)
    """
    cap = 2.0 * np.asarray(h, dtype=float) if cap is None else cap
    g = cusum_update(store.get(i, j), stat, k, cap)
    store.set(i, j, g)
    return cusum_alarm(g, h)
