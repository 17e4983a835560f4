"""Unicycle motion model, eq. (2), its Jacobians, and odometry-driven process noise."""

from __future__ import annotations

import numpy as np

from resloc.angles import wrap_angle

__all__ = [
    "process_noise",
    "unicycle_input_jacobian",
    "unicycle_state_jacobian",
    "unicycle_step",
]


def unicycle_step(x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """Discrete unicycle model, eq. (2): ``x_{k+1} = f(x_k, u_k)``.

    ``p += v [cos th, sin th] dt``, ``th += omega dt`` (heading wrapped).

    Parameters
    ----------
    x : ndarray, shape (..., 3)
        Poses ``[x, y, theta]``; e.g. ``(B, 3)`` or sigma points ``(B, m, 3)``.
    u : ndarray, shape broadcastable to (..., 2)
        Inputs ``[v, omega]``; for sigma points pass ``(B, 1, 2)``.
    dt : float
        Time step in seconds.

    Returns
    -------
    ndarray, shape (..., 3)
    """
    th = x[..., 2]
    v = u[..., 0]
    w = u[..., 1]
    out = np.empty(np.broadcast_shapes(x.shape, (*u.shape[:-1], 3)), dtype=float)
    out[..., 0] = x[..., 0] + v * np.cos(th) * dt
    out[..., 1] = x[..., 1] + v * np.sin(th) * dt
    out[..., 2] = wrap_angle(th + w * dt)
    return out


def unicycle_state_jacobian(x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """``F = df/dx`` of eq. (2).

    Parameters
    ----------
    x : ndarray, shape (B, 3)
    u : ndarray, shape (B, 2)
    dt : float

    Returns
    -------
    ndarray, shape (B, 3, 3)
    """
    B = x.shape[0]
    F = np.zeros((B, 3, 3))
    F[:, 0, 0] = F[:, 1, 1] = F[:, 2, 2] = 1.0
    F[:, 0, 2] = -u[:, 0] * np.sin(x[:, 2]) * dt
    F[:, 1, 2] = u[:, 0] * np.cos(x[:, 2]) * dt
    return F


def unicycle_input_jacobian(x: np.ndarray, dt: float) -> np.ndarray:
    """``G = df/du`` of eq. (2).

    Parameters
    ----------
    x : ndarray, shape (B, 3)
    dt : float

    Returns
    -------
    ndarray, shape (B, 3, 2)
    """
    B = x.shape[0]
    G = np.zeros((B, 3, 2))
    G[:, 0, 0] = np.cos(x[:, 2]) * dt
    G[:, 1, 0] = np.sin(x[:, 2]) * dt
    G[:, 2, 1] = dt
    return G


def process_noise(
    x: np.ndarray, dt: float, odometry_std: np.ndarray, floor_std: np.ndarray
) -> np.ndarray:
    """Process noise ``Q = G M G^T + diag(floor_std^2 dt)``.

    Odometry ``u = (v, omega)`` is measured with independent noise
    ``M = diag(odometry_std^2)``; ``G`` maps it into the state at the estimate ``x``.
    A small floor keeps ``Q`` positive definite when ``v = 0`` (``G M G^T`` has rank 2).

    Parameters
    ----------
    x : ndarray, shape (B, 3)
    dt : float
    odometry_std : ndarray, shape (2,) or (B, 2)
        Standard deviations of the measured ``v`` (m/s) and ``omega`` (rad/s).
    floor_std : ndarray, shape (3,)
        Additive random-walk standard deviations per sqrt(second) for ``x, y, theta``.

    Returns
    -------
    ndarray, shape (B, 3, 3)
    """
    G = unicycle_input_jacobian(x, dt)
    m = np.broadcast_to(np.asarray(odometry_std, float) ** 2, (x.shape[0], 2))
    Q = np.einsum("bik,bk,bjk->bij", G, m, G)
    Q += np.diag(np.asarray(floor_std, float) ** 2 * dt)
    return Q
