"""Innovation-residual attack detector (Algorithm 1, "Attack Detection")."""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from resloc.linalg import solve_spd

__all__ = ["NORM_RULES", "InnovationNorm", "NormRule", "attack_detected", "innovation_norm"]


class InnovationNorm(enum.StrEnum):
    """How the 2-vector ``Lambda = [range error (m), bearing error (rad)]`` becomes a scalar.

    ``euclidean``: the paper's ``||Lambda||`` (adds metres to radians).
    ``scaled``: ``||Lambda / sigma||`` with the measurement noise standard deviations.
    ``nis``: ``sqrt(Lambda^T S^{-1} Lambda)``, the normalized innovation (uses ``P^zz``).
    """

    EUCLIDEAN = "euclidean"
    SCALED = "scaled"
    NIS = "nis"


@dataclass(frozen=True)
class NormRule:
    """One innovation norm.

    Attributes
    ----------
    measure : callable(nu, S, noise_std) -> ndarray
        The norm of innovations ``nu: (E, 2)`` with covariances ``S: (E, 2, 2)`` and the
        noise standard deviations ``noise_std: (2,)``; shape ``(E,)``.
    chi_square : bool
        Its square is the NIS: chi-square with 2 degrees of freedom for honest measurements,
        so a gate can be set by a false-alarm probability.
    """

    measure: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
    chi_square: bool


def _euclidean(nu: np.ndarray, S: np.ndarray, noise_std: np.ndarray) -> np.ndarray:
    return np.hypot(nu[:, 0], nu[:, 1])


def _scaled(nu: np.ndarray, S: np.ndarray, noise_std: np.ndarray) -> np.ndarray:
    s = nu / np.asarray(noise_std, float)
    return np.hypot(s[:, 0], s[:, 1])


def _normalized(nu: np.ndarray, S: np.ndarray, noise_std: np.ndarray) -> np.ndarray:
    w = solve_spd(S, nu[:, :, None])[:, :, 0]
    return np.sqrt(np.maximum(np.einsum("ei,ei->e", nu, w), 0.0))


#: Every innovation norm's rule.
NORM_RULES: dict[InnovationNorm, NormRule] = {
    InnovationNorm.EUCLIDEAN: NormRule(_euclidean, chi_square=False),
    InnovationNorm.SCALED: NormRule(_scaled, chi_square=False),
    InnovationNorm.NIS: NormRule(_normalized, chi_square=True),
}


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
    return NORM_RULES[InnovationNorm(kind)].measure(nu, S, noise_std)


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
