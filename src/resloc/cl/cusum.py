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

The NIS squares the innovation, so a bias of ``delta`` standard deviations raises its mean by
only ``delta^2``: an attacker can keep a 1-sigma bias under ``k = 3``. A bias has a sign,
though. The **mean-shift CUSUM** runs Page's two-sided test on each component of the
whitened innovation ``w = L^{-1} Lambda`` (``S = L L^T``, honest ``w ~ N(0, I)``),

``g+_c <- min(max(0, g+_c + w_c - k), cap)``, ``g-_c <- min(max(0, g-_c - w_c - k), cap)``,

the optimal test for a shift of ``2k`` sigmas (Basseville & Nikiforov 1993, sec. 2.2); with
``k = 0.5``, ``h = 8`` an honest link raises a false alarm about every 19,000 measurements per
statistic (Siegmund's approximation) and a 1-sigma bias is caught within about 16. Only
measurements that pass the gate update it, and while a component's statistic alarms the
link's measurements with ``|w_c| > k`` are discarded (on both sides: one-sided discarding
biased the filter into a lock-out).
"""

from __future__ import annotations

import numpy as np

from resloc.distributions import chi2
from resloc.linalg import cholesky_jitter, solve_spd

__all__ = [
    "chi2_gate",
    "cusum_alarm",
    "cusum_update",
    "link_cusum",
    "link_mean_cusum",
    "nis",
    "whiten",
]


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


def whiten(nu: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Whitened innovations ``w = L^{-1} Lambda`` with ``S = L L^T`` (honest: ``N(0, I)``).

    Parameters
    ----------
    nu : ndarray, shape (E, 2)
    S : ndarray, shape (E, 2, 2)

    Returns
    -------
    ndarray, shape (E, 2)
        ``w_0 = Lambda_r / sqrt(S_rr)`` (range), ``w_1`` the bearing given the range.
    """
    L = cholesky_jitter(S)
    w0 = nu[:, 0] / L[:, 0, 0]
    w1 = (nu[:, 1] - L[:, 1, 0] * w0) / L[:, 1, 1]
    return np.stack([w0, w1], axis=1)


def link_mean_cusum(
    store,
    i: np.ndarray,
    j: np.ndarray,
    w: np.ndarray,
    k: float | np.ndarray,
    h: float | np.ndarray,
    passed: np.ndarray | None = None,
) -> np.ndarray:
    """Update the per-link signed CUSUMs of the whitened innovation; return what to discard.

    Parameters
    ----------
    store : LinkStatistic
        Per-link statistics of width 4 (``LinkMemory.mean_cusum``): ``g+_r, g-_r, g+_b,
        g-_b``, updated in place, capped at ``2 h``.
    i, j : ndarray of int, shape (E,)
        Links (distinct within one call).
    w : ndarray, shape (E, 2)
        Whitened innovations (:func:`whiten`).
    k, h : float or ndarray, shape (E,)
        Reference (half the shift to detect, in sigmas) and alarm threshold.
    passed : ndarray of bool, shape (E,), optional
        Which measurements passed the per-measurement gate: only those update the
        statistics (a gross outlier the gate already rejects would drive them to the cap).

    Returns
    -------
    ndarray of bool, shape (E,)
        Measurements to discard: while a component's statistic alarms (either sign), those
        with ``|w_c| > k``. Symmetric on purpose: discarding only the side the alarm points
        to truncates the innovations on one side, biases the filter and feeds the alarm
        (measured: a lock-out, MSLE x700 under a fixed bias); closing the whole link lost
        the honest measurements of intermittently attacked links (MSLE x2 against a
        gate-only attacker).
    """
    k = np.asarray(k, dtype=float).reshape(-1, 1)
    h = np.asarray(h, dtype=float).reshape(-1, 1)
    signed = np.stack([w[:, 0], -w[:, 0], w[:, 1], -w[:, 1]], axis=1)  # (E, 4)
    g_old = store.get(i, j)
    g = cusum_update(g_old, signed, k, 2.0 * h)
    if passed is not None:
        g = np.where(np.asarray(passed, bool)[:, None], g, g_old)
    store.set(i, j, g)
    alarm = cusum_alarm(g, h).reshape(-1, 2, 2).any(axis=2)  # per component (E, 2)
    return (alarm & (np.abs(w) > k)).any(axis=1)
