"""The redundancy stage's position fixes (:mod:`resloc.cl.detection_redundancy`): each
link's fix of its observer's position, ``f_ij = p_j - r_ij u(theta_i + b_ij)``, with its
covariance ``C_ij``, and the neighbours' claimed covariances capped at the observer's
median claim (no neighbour weighs more than a typical one: in the test,
:func:`weight_capped_covariance`, and, with ``redundancy_cap_fusion``, in the update,
:func:`capped_claims`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["capped_claims", "position_fix", "weight_capped_covariance"]


def weight_capped_covariance(P_nb: np.ndarray, i: np.ndarray) -> np.ndarray:
    """Neighbours' claimed position covariances, each scaled up to at least the median trace
    among the same observer's neighbours (no neighbour weighs more than a typical one).

    Parameters
    ----------
    P_nb : ndarray, shape (E, 3, 3)
        Claimed covariances of the neighbours' estimates.
    i : ndarray of int, shape (E,)
        Observer of each row.

    Returns
    -------
    ndarray, shape (E, 2, 2)
    """
    P = np.asarray(P_nb, float)
    return P[:, :2, :2] * _claim_scale(P, i)[:, None, None]


def capped_claims(P_nb: np.ndarray, i: np.ndarray) -> np.ndarray:
    """The neighbours' claimed covariances ``(E, 3, 3)``, each scaled by the factor
    :func:`weight_capped_covariance` puts on its position block: what a robot fuses when
    ``redundancy_cap_fusion`` is on, so a neighbour weighs in the update no more than the
    redundancy test credited it (shape (E, 3, 3))."""
    P = np.asarray(P_nb, float)
    return P * _claim_scale(P, i)[:, None, None]


def _claim_scale(P: np.ndarray, i: np.ndarray) -> np.ndarray:
    """Each claim's factor, shape (E,): its position block's trace raised to the median
    trace of its observer's claims (``P: (E, 3, 3)``, ``i: (E,)``); 1 where the trace is
    not positive."""
    trace = P[:, 0, 0] + P[:, 1, 1]
    median = _group_median(trace, np.asarray(i))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(trace > 0.0, np.maximum(median / trace, 1.0), 1.0)


def _group_median(values: np.ndarray, group: np.ndarray) -> np.ndarray:
    """The median of ``values: (E,)`` over the rows of each row's ``group``, shape (E,)."""
    if not len(values):
        return values.copy()
    order = np.lexsort((values, group))
    sorted_group = group[order]
    start = np.flatnonzero(np.r_[True, sorted_group[1:] != sorted_group[:-1]])
    count = np.diff(np.r_[start, len(values)])
    ranked = values[order]
    median = 0.5 * (ranked[start + (count - 1) // 2] + ranked[start + count // 2])
    per_row = np.empty(len(values))
    per_row[order] = np.repeat(median, count)
    return per_row


def position_fix(
    z: np.ndarray,
    x_obs: np.ndarray,
    P_obs: np.ndarray,
    x_nb: np.ndarray,
    P_nb_pos: np.ndarray,
    R: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Observer i's position as link ``(i, j)`` says: ``f = p_j - r u(theta_i + b)``
    (``r`` corrected for the mean shortening the angle's noise causes).

    Parameters
    ----------
    z : ndarray, shape (E, 2)
        Range and bearing of j measured by i.
    x_obs, P_obs : ndarray, shapes (E, 3), (E, 3, 3)
        Observer's estimate (its heading and heading variance are used).
    x_nb : ndarray, shape (E, 3)
        Neighbour's broadcast estimate.
    P_nb_pos : ndarray, shape (E, 2, 2)
        Position covariance credited to the neighbour.
    R : ndarray, shape (2, 2)

    Returns
    -------
    fix : ndarray, shape (E, 2)
    C : ndarray, shape (E, 2, 2)
    """
    r = z[:, 0]
    a = x_obs[:, 2] + z[:, 1]
    c, s = np.cos(a), np.sin(a)
    # A direction read with a zero-mean Gaussian angle error of variance s2 (the bearing
    # noise and the heading's variance) is shortened on average by exp(-s2 / 2): undone,
    # so that honest fixes are unbiased (a sequence test summing residuals over hundreds
    # of steps would otherwise see that bias as a lead).
    r_mean = r * np.exp(0.5 * (R[1, 1] + P_obs[:, 2, 2]))
    fix = x_nb[:, :2] - r_mean[:, None] * np.stack([c, s], axis=1)
    # d fix / d theta_i = d fix / d b = r [sin a, -cos a]; d fix / d r = -[cos a, sin a],
    # taken at the predicted geometry (the estimates' relative position), not at the
    # reading: weights that moved with the reading's own noise would bias the references
    # the fixes are compared with.
    rel = x_nb[:, :2] - x_obs[:, :2]
    r_pred = np.hypot(rel[:, 0], rel[:, 1])
    use = r_pred > 0.0
    c = np.where(use, rel[:, 0] / np.where(use, r_pred, 1.0), c)
    s = np.where(use, rel[:, 1] / np.where(use, r_pred, 1.0), s)
    r = np.where(use, r_pred, r)
    J_a = r[:, None] * np.stack([s, -c], axis=1)
    J_z = np.stack([np.stack([-c, J_a[:, 0]], 1), np.stack([-s, J_a[:, 1]], 1)], 1)
    C = (
        P_nb_pos
        + J_a[:, :, None] * J_a[:, None, :] * P_obs[:, 2, 2][:, None, None]
        + J_z @ R @ np.swapaxes(J_z, -1, -2)
    )
    return fix, 0.5 * (C + np.swapaxes(C, -1, -2))
