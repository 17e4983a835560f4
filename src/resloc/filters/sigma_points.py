"""Sigma-point rules and the sigma-point (CKF / UKF) filter strategy.

The CKF and the UKF differ *only* in their points and weights: the third-degree
spherical-radial cubature rule is the scaled unscented rule with ``alpha=1, beta=0,
kappa=0`` (the centre point then has weight 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from resloc.angles import circular_mean, wrap_angle
from resloc.filters.base import FilterKind, Moments
from resloc.linalg import cholesky_jitter, symmetrize
from resloc.models.measurement import range_bearing
from resloc.models.motion import unicycle_step

__all__ = ["SigmaPointFilter", "SigmaPointRule", "cubature_rule", "merwe_scaled_rule"]


@dataclass(frozen=True, eq=False)
class SigmaPointRule:
    """Unit sigma points ``xi`` and weights of a deterministic-sampling rule.

    Points of ``N(x, P)`` are ``x + L xi_m`` with ``L = chol(P)`` (lower).

    Attributes
    ----------
    unit : ndarray, shape (m, n)
        Unit points ``xi_m``.
    Wm, Wc : ndarray, shape (m,)
        Mean and covariance weights.
    """

    name: str
    unit: np.ndarray
    Wm: np.ndarray
    Wc: np.ndarray

    @property
    def n(self) -> int:
        """State dimension."""
        return self.unit.shape[1]

    def points(self, x: np.ndarray, L: np.ndarray) -> np.ndarray:
        """Sigma points ``X = x + L xi`` (Algorithm 1, "generate cubature points").

        Parameters
        ----------
        x : ndarray, shape (B, n)
        L : ndarray, shape (B, n, n)
            Lower Cholesky factors of the covariances.

        Returns
        -------
        ndarray, shape (B, m, n)
        """
        return x[:, None, :] + np.einsum("bij,mj->bmi", L, self.unit)


def cubature_rule(n: int) -> SigmaPointRule:
    """Third-degree spherical-radial cubature rule.

    ``2n`` points ``+-sqrt(n) e_k`` with equal weights ``1/(2n)`` (Arasaratnam & Haykin).
    """
    unit = np.sqrt(n) * np.vstack([np.eye(n), -np.eye(n)])
    w = np.full(2 * n, 1.0 / (2 * n))
    return SigmaPointRule("cubature", unit, w, w.copy())


def merwe_scaled_rule(n: int, alpha: float, beta: float, kappa: float) -> SigmaPointRule:
    """Scaled unscented rule (van der Merwe), the definition FilterPy's
    ``MerweScaledSigmaPoints`` uses: ``lambda = alpha^2 (n + kappa) - n``, points
    ``x, x +- sqrt(n + lambda) e_k``, ``Wm_0 = lambda/(n+lambda)``,
    ``Wc_0 = Wm_0 + 1 - alpha^2 + beta``, other weights ``1/(2(n+lambda))``.
    """
    lam = alpha**2 * (n + kappa) - n
    if n + lam <= 0:
        raise ValueError(f"UKF parameters give n + lambda = {n + lam:g} <= 0; raise alpha or kappa")
    c = np.sqrt(n + lam)
    unit = np.vstack([np.zeros((1, n)), c * np.eye(n), -c * np.eye(n)])
    Wm = np.full(2 * n + 1, 1.0 / (2 * (n + lam)))
    Wc = Wm.copy()
    Wm[0] = lam / (n + lam)
    Wc[0] = Wm[0] + 1.0 - alpha**2 + beta
    return SigmaPointRule("merwe", unit, Wm, Wc)


def _pose_mean(X: np.ndarray, Wm: np.ndarray, circular: bool) -> np.ndarray:
    """Weighted mean of poses ``X: (B, m, 3)``; the heading by circular mean."""
    mean = np.einsum("bmi,m->bi", X[..., :2], Wm)
    th = circular_mean(X[..., 2], Wm) if circular else wrap_angle(X[..., 2] @ Wm)
    return np.concatenate([mean, th[:, None]], axis=1)


@dataclass(frozen=True, eq=False)
class SigmaPointFilter:
    """CKF or UKF: Algorithm 1 with a pluggable point rule.

    Attributes
    ----------
    kind : FilterKind
    rule3 : SigmaPointRule
        Rule on the 3-D pose (prediction).
    rule6 : SigmaPointRule
        Rule on the joint 6-D ``[x_i; x_j]`` (relative update).
    circular : bool
        Average headings and bearings on the circle (default). ``False`` reproduces
        FilterPy's arithmetic averaging (then wrapped); only for cross-checks.
    """

    kind: FilterKind
    rule3: SigmaPointRule
    rule6: SigmaPointRule
    circular: bool = True

    def predict(
        self, x: np.ndarray, P: np.ndarray, u: np.ndarray, dt: float, Q: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Time update (Algorithm 1, "Prediction").

        Parameters
        ----------
        x : ndarray, shape (B, 3)
        P : ndarray, shape (B, 3, 3)
        u : ndarray, shape (B, 2)
            Measured odometry ``(v, omega)``.
        dt : float
        Q : ndarray, shape (B, 3, 3)

        Returns
        -------
        x, P : ndarray, shapes (B, 3), (B, 3, 3)
        """
        rule = self.rule3
        X = rule.points(x, cholesky_jitter(P))
        Xf = unicycle_step(X, u[:, None, :], dt)
        x_new = _pose_mean(Xf, rule.Wm, self.circular)
        d = Xf - x_new[:, None, :]
        d[..., 2] = wrap_angle(d[..., 2])
        P_new = np.einsum("bmi,m,bmj->bij", d, rule.Wc, d) + Q
        return x_new, symmetrize(P_new)

    def relative_moments(
        self,
        x_i: np.ndarray,
        P_i: np.ndarray,
        x_j: np.ndarray,
        P_j: np.ndarray,
        R: np.ndarray,
    ) -> Moments:
        """Moments of ``z_ij = h(x_i, x_j) + v`` by points over the joint ``[x_i; x_j]``.

        The joint covariance is ``blockdiag(P_i, P_j)`` (the paper's filters keep no
        cross-correlation), so its Cholesky factor is ``blockdiag(L_i, L_j)``.

        Parameters
        ----------
        x_i, x_j : ndarray, shape (E, 3)
        P_i, P_j : ndarray, shape (E, 3, 3)
        R : ndarray, shape (2, 2) or (E, 2, 2)

        Returns
        -------
        Moments
        """
        rule = self.rule6
        E = x_i.shape[0]
        L = np.zeros((E, 6, 6))
        L[:, :3, :3] = cholesky_jitter(P_i)
        L[:, 3:, 3:] = cholesky_jitter(P_j)
        offsets = np.einsum("bij,mj->bmi", L, rule.unit)  # (E, m, 6)
        Xi = x_i[:, None, :] + offsets[..., :3]
        Xj = x_j[:, None, :] + offsets[..., 3:]
        Z = range_bearing(Xi, Xj)  # (E, m, 2)
        z_hat = np.empty((E, 2))
        z_hat[:, 0] = Z[..., 0] @ rule.Wm
        z_hat[:, 1] = (
            circular_mean(Z[..., 1], rule.Wm) if self.circular else wrap_angle(Z[..., 1] @ rule.Wm)
        )
        dZ = Z - z_hat[:, None, :]
        dZ[..., 1] = wrap_angle(dZ[..., 1])
        # Deviations of x_i about its mean are the offsets (sum_m Wm xi_m = 0 for both rules).
        dX = offsets[..., :3] - np.einsum("bmi,m->bi", offsets[..., :3], rule.Wm)[:, None, :]
        S = np.einsum("bmi,m,bmj->bij", dZ, rule.Wc, dZ) + R
        Pxz = np.einsum("bmi,m,bmj->bij", dX, rule.Wc, dZ)
        return Moments(z_hat, symmetrize(S), Pxz)
