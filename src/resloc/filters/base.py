"""Filter interface, the filter-kind enum and the factory."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Protocol

import numpy as np

__all__ = ["FilterKind", "GaussianFilter", "Moments", "make_filter"]


class FilterKind(enum.StrEnum):
    """Which Gaussian approximation a robot's filter uses."""

    CKF = "ckf"
    UKF = "ukf"
    EKF = "ekf"


@dataclass(frozen=True)
class Moments:
    """Predicted-measurement moments of relative measurements ``z_ij`` (one row per link).

    Attributes
    ----------
    z_hat : ndarray, shape (E, 2)
        Predicted measurement ``hat z_ij,k|k-1`` (bearing wrapped).
    S : ndarray, shape (E, 2, 2)
        Innovation covariance ``P^zz_ij`` including ``R``.
    Pxz : ndarray, shape (E, 3, 2)
        Cross-covariance ``P^xz_ij`` between ``x_i`` and ``z_ij``.
    H_i : ndarray, shape (E, 2, 3) or None
        Measurement Jacobian w.r.t. ``x_i`` (EKF only: enables the Joseph form).
    R_eff : ndarray, shape (E, 2, 2) or None
        Noise seen by ``x_i``: ``R + H_j P_j H_j^T`` (EKF only).
    """

    z_hat: np.ndarray
    S: np.ndarray
    Pxz: np.ndarray
    H_i: np.ndarray | None = None
    R_eff: np.ndarray | None = None


class GaussianFilter(Protocol):
    """What every filter strategy provides. All arrays carry a leading batch axis."""

    kind: FilterKind

    def predict(
        self, x: np.ndarray, P: np.ndarray, u: np.ndarray, dt: float, Q: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Time update. ``x: (B,3)``, ``P: (B,3,3)``, ``u: (B,2)``, ``Q: (B,3,3)``."""
        ...

    def relative_moments(
        self,
        x_i: np.ndarray,
        P_i: np.ndarray,
        x_j: np.ndarray,
        P_j: np.ndarray,
        R: np.ndarray,
    ) -> Moments:
        """Moments of ``z_ij`` over ``[x_i; x_j] ~ N(., blockdiag(P_i, P_j))``.

        ``x_i, x_j: (E,3)``, ``P_i, P_j: (E,3,3)``, ``R: (2,2)`` or ``(E,2,2)``.
        """
        ...


def make_filter(
    kind: FilterKind | str,
    ukf_alpha: float = 0.5,
    ukf_beta: float = 2.0,
    ukf_kappa: float = 0.0,
) -> GaussianFilter:
    """Build the filter strategy for ``kind``.

    Parameters
    ----------
    kind : FilterKind or {"ckf", "ukf", "ekf"}
    ukf_alpha, ukf_beta, ukf_kappa : float
        Scaled-unscented parameters (UKF only), same definition as FilterPy's
        ``MerweScaledSigmaPoints``.
    """
    from resloc.filters.ekf import ExtendedFilter
    from resloc.filters.sigma_points import SigmaPointFilter, cubature_rule, merwe_scaled_rule

    kind = FilterKind(kind)
    if kind is FilterKind.CKF:
        return SigmaPointFilter(FilterKind.CKF, cubature_rule(3), cubature_rule(6))
    if kind is FilterKind.UKF:
        return SigmaPointFilter(
            FilterKind.UKF,
            merwe_scaled_rule(3, ukf_alpha, ukf_beta, ukf_kappa),
            merwe_scaled_rule(6, ukf_alpha, ukf_beta, ukf_kappa),
        )
    return ExtendedFilter()
