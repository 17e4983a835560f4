"""Angle helpers: the one place where angles are wrapped and averaged."""

from __future__ import annotations

import numpy as np

__all__ = ["circular_mean", "wrap_angle"]


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Wrap angles to ``[-pi, pi)``.

    Parameters
    ----------
    a : array-like, any shape
        Angles in radians (any magnitude).

    Returns
    -------
    ndarray, same shape as ``a``
        ``a`` mapped into ``[-pi, pi)``; ``+pi`` maps to ``-pi``.
    """
    a = np.asarray(a, dtype=float)
    return np.mod(a + np.pi, 2.0 * np.pi) - np.pi


def circular_mean(a: np.ndarray, weights: np.ndarray, axis: int = -1) -> np.ndarray:
    """Weighted circular mean ``atan2(sum w sin a, sum w cos a)``.

    Parameters
    ----------
    a : ndarray, shape (..., m, ...)
        Angles; ``axis`` indexes the ``m`` samples.
    weights : ndarray, shape (m,)
        Sample weights (may be negative, as for scaled sigma points; they need not sum to 1).
    axis : int
        The sample axis of ``a``.

    Returns
    -------
    ndarray
        ``a`` with ``axis`` removed, wrapped to ``[-pi, pi)``.
    """
    a = np.moveaxis(np.asarray(a, dtype=float), axis, -1)
    s = np.sin(a) @ weights
    c = np.cos(a) @ weights
    return wrap_angle(np.arctan2(s, c))
