"""Range/bearing relative measurement, eq. (3), and its Jacobians."""

from __future__ import annotations

import numpy as np

from resloc.angles import wrap_angle

__all__ = ["measurement_noise", "range_bearing", "range_bearing_jacobians"]

#: Ranges below this are treated as this (the Jacobian is singular at zero range).
MIN_RANGE = 1e-6


def range_bearing(x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """Noise-free relative measurement of robot j by robot i, eq. (3).

    ``h_ij = [|p_j - p_i|, wrap(atan2(dy, dx) - theta_i)]``.

    Parameters
    ----------
    x_i, x_j : ndarray, shapes broadcastable to (..., 3)
        Poses of the observer i and the observed j.

    Returns
    -------
    ndarray, shape (..., 2)
        ``[range (m), bearing (rad)]`` with bearing in ``[-pi, pi)``.
    """
    dx = x_j[..., 0] - x_i[..., 0]
    dy = x_j[..., 1] - x_i[..., 1]
    out = np.empty((*np.broadcast_shapes(x_i.shape, x_j.shape)[:-1], 2), dtype=float)
    out[..., 0] = np.hypot(dx, dy)
    out[..., 1] = wrap_angle(np.arctan2(dy, dx) - x_i[..., 2])
    return out


def range_bearing_jacobians(x_i: np.ndarray, x_j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of eq. (3) with respect to ``x_i`` and ``x_j``.

    Parameters
    ----------
    x_i, x_j : ndarray, shape (E, 3)

    Returns
    -------
    H_i, H_j : ndarray, shape (E, 2, 3)
    """
    dx = x_j[:, 0] - x_i[:, 0]
    dy = x_j[:, 1] - x_i[:, 1]
    q = np.maximum(dx * dx + dy * dy, MIN_RANGE**2)
    r = np.sqrt(q)
    E = x_i.shape[0]
    H_j = np.zeros((E, 2, 3))
    H_j[:, 0, 0] = dx / r
    H_j[:, 0, 1] = dy / r
    H_j[:, 1, 0] = -dy / q
    H_j[:, 1, 1] = dx / q
    H_i = -H_j
    H_i[:, 1, 2] = -1.0
    return H_i, H_j


def measurement_noise(range_std: float, bearing_std: float) -> np.ndarray:
    """Measurement noise covariance ``R = diag(range_std^2, bearing_std^2)``, shape (2, 2)."""
    return np.diag([range_std**2, bearing_std**2])
