"""Planar geometry shared by the exports: quaternions, covariance ellipses, SE(2) alignment.

Pure numpy on batched arrays; no optional dependency.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from resloc.experiments.metrics import align_se2

__all__ = [
    "AlignedError",
    "align_se2",
    "aligned_errors",
    "covariance_ellipse",
    "yaw_quaternion",
]

#: ``chi2.ppf(0.95, 2)``: the 95 % confidence ellipse of a 2-D Gaussian is ``sqrt(5.991)`` sigma.
CHI2_95_2D = 5.991464547107979


def yaw_quaternion(theta: np.ndarray) -> np.ndarray:
    """Quaternions ``(qx, qy, qz, qw)`` (w last, as TUM and ROS order them) of yaws.

    Parameters
    ----------
    theta : ndarray, shape (...)

    Returns
    -------
    ndarray, shape (..., 4)
    """
    half = 0.5 * np.asarray(theta, float)
    q = np.zeros((*half.shape, 4))
    q[..., 2] = np.sin(half)
    q[..., 3] = np.cos(half)
    return q


def covariance_ellipse(P: np.ndarray, chi2: float = CHI2_95_2D) -> np.ndarray:
    """Semi-axes and orientation of the position confidence ellipses.

    Parameters
    ----------
    P : ndarray, shape (..., 3, 3) or (..., 2, 2)
        Pose (or position) covariances; the ``(x, y)`` block is used.
    chi2 : float
        Squared Mahalanobis radius (default: 95 % for 2-D).

    Returns
    -------
    ndarray, shape (..., 3)
        ``(a, b, angle)``: major and minor semi-axes (m) and the major axis angle (rad).
    """
    C = np.asarray(P, float)[..., :2, :2]
    sxx, syy, sxy = C[..., 0, 0], C[..., 1, 1], C[..., 0, 1]
    mid = 0.5 * (sxx + syy)
    rad = np.sqrt(np.maximum(0.25 * (sxx - syy) ** 2 + sxy**2, 0.0))
    major = np.maximum(mid + rad, 0.0)
    minor = np.maximum(mid - rad, 0.0)
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    return np.stack([np.sqrt(chi2 * major), np.sqrt(chi2 * minor), angle], axis=-1)


@dataclass(frozen=True)
class AlignedError:
    """Position errors of one estimator under three alignments.

    Attributes
    ----------
    raw : ndarray, shape (N,)
        Position RMSE per robot, no alignment (the absolute error; with relative
        measurements only its team-common part is unobservable).
    team : ndarray, shape (N,)
        After ONE rigid SE(2) transform fitted over every robot and step: removes only the
        team's common rigid-body error, so it keeps every error between robots.
    per_robot : ndarray, shape (N,)
        After one SE(2) transform per robot (what ``evo_ape -a`` computes on one file):
        hides errors between robots, so it flatters a team estimate.
    team_transform : tuple of float
        ``(tx, ty, angle)`` of the team alignment.
    """

    raw: np.ndarray
    team: np.ndarray
    per_robot: np.ndarray
    team_transform: tuple[float, float, float]

    def overall(self) -> dict[str, float]:
        """RMSE over every robot and step for each alignment (robots weighted by samples)."""
        return {
            "raw": float(np.sqrt(np.nanmean(self.raw**2))),
            "team": float(np.sqrt(np.nanmean(self.team**2))),
            "per_robot": float(np.sqrt(np.nanmean(self.per_robot**2))),
        }


def aligned_errors(truth: np.ndarray, estimate: np.ndarray, valid: np.ndarray) -> AlignedError:
    """Position RMSE per robot: unaligned, team-aligned (one shared SE(2)) and per-robot aligned.

    Parameters
    ----------
    truth, estimate : ndarray, shape (K, N, 3) or (K, N, 2)
    valid : ndarray of bool, shape (K, N)
        Samples to use (where the truth exists).

    Returns
    -------
    AlignedError
    """
    p_true = np.asarray(truth, float)[..., :2]
    p_est = np.asarray(estimate, float)[..., :2]
    valid = np.asarray(valid, bool) & np.isfinite(p_est).all(-1) & np.isfinite(p_true).all(-1)
    N = p_true.shape[1]

    def rmse(err2: np.ndarray, mask: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.sqrt(np.where(mask, err2, 0.0).sum(0) / mask.sum(0))

    raw = rmse(((p_est - p_true) ** 2).sum(-1), valid)
    R, t = align_se2(p_est[valid], p_true[valid])
    team_err2 = ((p_est @ R.T + t - p_true) ** 2).sum(-1)
    team = rmse(team_err2, valid)
    per = np.full(N, np.nan)
    for r in range(N):
        ok = valid[:, r]
        if ok.sum() >= 2:
            Rr, tr = align_se2(p_est[ok, r], p_true[ok, r])
            per[r] = np.sqrt(((p_est[ok, r] @ Rr.T + tr - p_true[ok, r]) ** 2).sum(-1).mean())
    angle = float(np.arctan2(R[1, 0], R[0, 0]))
    return AlignedError(raw, team, per, (float(t[0]), float(t[1]), angle))
