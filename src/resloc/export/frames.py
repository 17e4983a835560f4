"""Which recorded steps an export keeps, and per-step summaries the viewers share."""

from __future__ import annotations

import numpy as np

from resloc.experiments.metrics import msle

__all__ = ["frame_steps", "msle_series", "position_errors", "step_rows"]


def frame_steps(time: np.ndarray, rate: float | None, max_frames: int | None = None) -> np.ndarray:
    """Indices of the steps to keep: at most ``rate`` per second and ``max_frames`` in all
    (the first and the last step always).

    Parameters
    ----------
    time : ndarray, shape (K,)
    rate : float or None
    max_frames : int or None

    Returns
    -------
    ndarray of int, shape (F,)
    """
    K = len(time)
    stride = 1
    if rate is not None and K > 1:
        dt = float(np.median(np.diff(time)))
        stride = max(1, round(1.0 / (rate * dt)) if dt > 0 else 1)
    if max_frames is not None and K > max_frames:
        stride = max(stride, int(np.ceil((K - 1) / (max_frames - 1))))
    idx = np.arange(0, K, stride)
    if idx[-1] != K - 1:
        idx = np.append(idx, K - 1)
    return idx


def step_rows(step: np.ndarray, after: int, upto: int) -> np.ndarray:
    """Rows of a link log (sorted by ``step``) with ``after < step <= upto``, shape (M',)."""
    lo = np.searchsorted(step, after, side="right")
    return np.arange(lo, np.searchsorted(step, upto, side="right"))


def position_errors(rec, name: str) -> np.ndarray:
    """``|p_est - p_true|`` per step and robot, shape (K, N); ``nan`` where the truth is
    missing."""
    d = rec.estimates[name][..., :2] - rec.truth[..., :2]
    return np.where(rec.valid, np.hypot(d[..., 0], d[..., 1]), np.nan)


def msle_series(rec, name: str) -> np.ndarray:
    """The paper's MSLE per step, shape (K,); ``nan`` where some robot's truth is missing."""
    ok = rec.valid.all(axis=1)
    out = np.full(len(rec.time), np.nan)
    if ok.any():
        out[ok] = msle(rec.truth[ok, :, :2], rec.estimates[name][ok, :, :2])
    return out
