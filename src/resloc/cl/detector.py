"""Innovation-residual attack detector (Algorithm 1, "Attack Detection")."""

from __future__ import annotations

import numpy as np

from resloc.innovation_norm import InnovationNorm
from resloc.linalg import solve_spd

__all__ = ["InnovationNorm", "attack_detected", "innovation_norm"]


def innovation_norm(
    nu: np.ndarray, S: np.ndarray, kind: InnovationNorm, noise_std: np.ndarray
) -> np.ndarray:
    """Scalar size of innovations.

    Parameters
    ----------
    nu : ndarray, shape (E, 2)
        Innovations ``Lambda_ij`` (eq. 9).
    S : ndarray, shape (E, 2, 2)
        Innovation covariances (used by ``nis``).
    kind : InnovationNorm
    noise_std : ndarray, shape (2,)
        Range and bearing noise standard deviations (used by ``scaled``).

    Returns
    -------
    ndarray, shape (E,)
    """
    kind = InnovationNorm(kind)  # a plain string would otherwise fall through to "nis"
    if kind is InnovationNorm.EUCLIDEAN:
        return np.hypot(nu[:, 0], nu[:, 1])
    if kind is InnovationNorm.SCALED:
        s = nu / np.asarray(noise_std, float)
        return np.hypot(s[:, 0], s[:, 1])
    w = solve_spd(S, nu[:, :, None])[:, :, 0]
    return np.sqrt(np.maximum(np.einsum("ei,ei->e", nu, w), 0.0))


def attack_detected(norm: np.ndarray, rho: np.ndarray | float) -> np.ndarray:
    """Attack detection of Algorithm 1: discard ``z_ij`` when ``||Lambda_ij|| > rho``.

    Parameters
    ----------
    norm : ndarray, shape (E,)
        Innovation norms.
    rho : float or ndarray, shape (E,)
        Detection threshold per link (``inf`` disables the detector).

    Returns
    -------
    ndarray of bool, shape (E,)
        True where the measurement is flagged and discarded.
    """
    return norm > rho
