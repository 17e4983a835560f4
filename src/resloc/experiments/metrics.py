"""Evaluation metrics: MSLE (the paper's), RMSE, NEES, communication and detector rates."""

from __future__ import annotations

import numpy as np

from resloc.angles import wrap_angle
from resloc.linalg import solve_spd

__all__ = [
    "confusion_counts",
    "detector_rates",
    "detector_scores",
    "msle",
    "nees",
    "position_rmse",
    "rate",
]


def msle(p_true: np.ndarray, p_est: np.ndarray) -> np.ndarray:
    """Mean Square Localization Error, exactly as the paper's Experiments section defines it.

    ``MSLE = 1/N sum_i sum_{j != i} (|x_i - x_j| - |hat x_i - hat x_j|)^2`` over positions.
    Note the normalization by ``N`` (not by the ``N (N - 1)`` ordered pairs it sums).

    Parameters
    ----------
    p_true, p_est : ndarray, shape (T, N, 2)
        True and estimated positions of the N robots of T trials.

    Returns
    -------
    ndarray, shape (T,)
    """
    p_true = np.asarray(p_true, float)
    p_est = np.asarray(p_est, float)
    n = p_true.shape[1]
    d_true = np.linalg.norm(p_true[:, :, None, :] - p_true[:, None, :, :], axis=-1)
    d_est = np.linalg.norm(p_est[:, :, None, :] - p_est[:, None, :, :], axis=-1)
    # The diagonal is 0 - 0, so summing over all (i, j) equals summing over j != i.
    return ((d_true - d_est) ** 2).sum(axis=(1, 2)) / n


def position_rmse(p_true: np.ndarray, p_est: np.ndarray) -> np.ndarray:
    """Absolute position RMSE over robots, ``sqrt(mean_i |p_i - hat p_i|^2)``.

    Parameters
    ----------
    p_true, p_est : ndarray, shape (T, N, 2)

    Returns
    -------
    ndarray, shape (T,)
    """
    e = np.asarray(p_true, float) - np.asarray(p_est, float)
    return np.sqrt((e**2).sum(axis=-1).mean(axis=-1))


def nees(x_true: np.ndarray, x_est: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Normalized estimation error squared per robot, ``e^T P^{-1} e`` (heading wrapped).

    A consistent 3-DoF filter averages 3.

    Parameters
    ----------
    x_true, x_est : ndarray, shape (B, 3)
    P : ndarray, shape (B, 3, 3)

    Returns
    -------
    ndarray, shape (B,)
    """
    e = np.asarray(x_true, float) - np.asarray(x_est, float)
    e[:, 2] = wrap_angle(e[:, 2])
    w = solve_spd(P, e[:, :, None])[:, :, 0]
    return np.einsum("bi,bi->b", e, w)


def rate(numerator: float, denominator: float) -> float:
    """``numerator / denominator``, ``nan`` when the denominator is 0."""
    return float(numerator) / float(denominator) if denominator else float("nan")


def confusion_counts(
    detected: np.ndarray,
    attacked: np.ndarray,
    group: np.ndarray | None = None,
    groups: int = 1,
) -> dict[str, np.ndarray]:
    """The detector's confusion counts, per group (e.g. per trial).

    Parameters
    ----------
    detected : ndarray of bool, shape (E,)
        The detector discarded the measurement.
    attacked : ndarray of bool, shape (E,)
        The simulator falsified the measurement (ground truth).
    group : ndarray of int, shape (E,), optional
        Group of every measurement in ``[0, groups)`` (None: one group).
    groups : int

    Returns
    -------
    dict of str to ndarray of int64, each shape (groups,)
        ``tp, fp, fn, tn``.
    """
    detected = np.asarray(detected, bool)
    attacked = np.asarray(attacked, bool)
    group = np.zeros(len(detected), np.int64) if group is None else np.asarray(group)
    cells = {
        "tp": detected & attacked,
        "fp": detected & ~attacked,
        "fn": ~detected & attacked,
        "tn": ~detected & ~attacked,
    }
    return {k: np.bincount(group[m], minlength=groups).astype(np.int64) for k, m in cells.items()}


def detector_rates(tp: float, fp: float, fn: float, tn: float) -> dict[str, float]:
    """``precision``, ``recall`` (true-positive rate) and ``false_alarm_rate`` from counts
    (``nan`` where undefined)."""
    return {
        "precision": rate(tp, tp + fp),
        "recall": rate(tp, tp + fn),
        "false_alarm_rate": rate(fp, fp + tn),
    }


def detector_scores(detected: np.ndarray, attacked: np.ndarray) -> dict[str, float]:
    """Detector precision, recall and false-alarm rate from per-measurement flags.

    Parameters
    ----------
    detected : ndarray of bool, shape (E,)
        The detector discarded the measurement.
    attacked : ndarray of bool, shape (E,)
        The simulator falsified the measurement (ground truth).

    Returns
    -------
    dict
        ``tp, fp, fn, tn`` counts and ``precision``, ``recall`` (true-positive rate),
        ``false_alarm_rate`` (``nan`` where undefined).
    """
    counts = {k: int(v[0]) for k, v in confusion_counts(detected, attacked).items()}
    return {**counts, **detector_rates(**counts)}
