"""Extended Kalman filter strategy: first-order linearization of eqs. (2) and (3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from resloc.filters.base import FilterKind, Moments
from resloc.linalg import symmetrize
from resloc.models.measurement import range_bearing, range_bearing_jacobians
from resloc.models.motion import unicycle_state_jacobian, unicycle_step

__all__ = ["ExtendedFilter"]


@dataclass(frozen=True, eq=False)
class ExtendedFilter:
    """EKF: same interface as :class:`~resloc.filters.sigma_points.SigmaPointFilter`."""

    kind: FilterKind = FilterKind.EKF

    def predict(
        self, x: np.ndarray, P: np.ndarray, u: np.ndarray, dt: float, Q: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``x = f(x, u)``, ``P = F P F^T + Q``. Shapes as in ``SigmaPointFilter.predict``."""
        F = unicycle_state_jacobian(x, u, dt)
        x_new = unicycle_step(x, u, dt)
        P_new = F @ P @ np.swapaxes(F, -1, -2) + Q
        return x_new, symmetrize(P_new)

    def relative_moments(
        self,
        x_i: np.ndarray,
        P_i: np.ndarray,
        x_j: np.ndarray,
        P_j: np.ndarray,
        R: np.ndarray,
    ) -> Moments:
        """Linearized moments of eq. (3).

        ``z_hat = h(x_i, x_j)``, ``S = H_i P_i H_i^T + H_j P_j H_j^T + R``,
        ``Pxz = P_i H_i^T``. Shapes as in ``SigmaPointFilter.relative_moments``.
        """
        H_i, H_j = range_bearing_jacobians(x_i, x_j)
        z_hat = range_bearing(x_i, x_j)
        R_eff = H_j @ P_j @ np.swapaxes(H_j, -1, -2) + R
        S = H_i @ P_i @ np.swapaxes(H_i, -1, -2) + R_eff
        Pxz = P_i @ np.swapaxes(H_i, -1, -2)
        return Moments(z_hat, symmetrize(S), Pxz, H_i=H_i, R_eff=symmetrize(R_eff))
