"""The Kalman correction shared by every filter, and covariance safeguards."""

from __future__ import annotations

import numpy as np

from resloc.angles import wrap_angle
from resloc.filters.base import Moments
from resloc.linalg import solve_spd, symmetrize

__all__ = ["covariance_is_pd", "innovation", "kalman_gain", "kalman_update", "repair_covariance"]


def innovation(z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
    """Innovation ``Lambda_ij = z_ij - hat z_ij,k|k-1``, eq. (9), bearing wrapped.

    Parameters
    ----------
    z, z_hat : ndarray, shape (E, 2)

    Returns
    -------
    ndarray, shape (E, 2)
    """
    nu = z - z_hat
    nu[:, 1] = wrap_angle(nu[:, 1])
    return nu


def kalman_gain(S: np.ndarray, Pxz: np.ndarray) -> np.ndarray:
    """Kalman gain ``K = P^xz (P^zz)^{-1}`` by a Cholesky solve.

    Parameters
    ----------
    S : ndarray, shape (E, 2, 2)
        Innovation covariances ``P^zz``.
    Pxz : ndarray, shape (E, 3, 2)
        State-measurement cross-covariances.

    Returns
    -------
    ndarray, shape (E, 3, 2)
    """
    return np.swapaxes(solve_spd(S, np.swapaxes(Pxz, -1, -2)), -1, -2)


def kalman_update(
    x: np.ndarray, P: np.ndarray, nu: np.ndarray, m: Moments
) -> tuple[np.ndarray, np.ndarray]:
    """Kalman correction of ``x_i`` from one innovation per row (Algorithm 1, "Correction").

    ``K = P^xz (P^zz)^{-1}`` (by a Cholesky solve), ``x <- x + K Lambda``. The covariance
    uses the Joseph form ``(I - K H) P (I - K H)^T + K R_eff K^T`` when the strategy provides
    a Jacobian (EKF), else ``P - K P^zz K^T`` (the Schur complement of the joint point
    covariance, positive semi-definite by construction for non-negative weights).

    Parameters
    ----------
    x : ndarray, shape (E, 3)
    P : ndarray, shape (E, 3, 3)
    nu : ndarray, shape (E, 2)
        Innovations (bearing wrapped).
    m : Moments
        Measurement moments for the same rows.

    Returns
    -------
    x, P : ndarray, shapes (E, 3), (E, 3, 3)
    """
    K = kalman_gain(m.S, m.Pxz)
    x_new = x + np.einsum("eij,ej->ei", K, nu)
    x_new[:, 2] = wrap_angle(x_new[:, 2])
    if m.H_i is not None and m.R_eff is not None:
        A = np.eye(3) - K @ m.H_i
        P_new = A @ P @ np.swapaxes(A, -1, -2) + K @ m.R_eff @ np.swapaxes(K, -1, -2)
    else:
        P_new = P - K @ m.S @ np.swapaxes(K, -1, -2)
    return x_new, symmetrize(P_new)


def covariance_is_pd(P: np.ndarray) -> np.ndarray:
    """Sylvester's criterion for 3x3 matrices: all leading principal minors > 0.

    Parameters
    ----------
    P : ndarray, shape (B, 3, 3)

    Returns
    -------
    ndarray of bool, shape (B,)
    """
    a = P[:, 0, 0]
    m2 = P[:, 0, 0] * P[:, 1, 1] - P[:, 0, 1] * P[:, 1, 0]
    det = np.linalg.det(P)
    return (a > 0) & (m2 > 0) & (det > 0) & np.isfinite(det)


def repair_covariance(P: np.ndarray, rel_floor: float = 1e-12) -> np.ndarray:
    """Project symmetric matrices onto the positive definite cone by eigenvalue clipping.

    Used only where :func:`covariance_is_pd` fails; callers count every repair.

    Parameters
    ----------
    P : ndarray, shape (B, n, n)
    rel_floor : float
        Eigenvalues are floored at ``rel_floor * max(trace, 1e-300)``.

    Returns
    -------
    ndarray, shape (B, n, n)
    """
    w, V = np.linalg.eigh(symmetrize(P))
    floor = rel_floor * np.maximum(np.abs(np.trace(P, axis1=-2, axis2=-1)), 1e-300)
    w = np.maximum(w, floor[:, None])
    return symmetrize(np.einsum("bij,bj,bkj->bik", V, w, V))
