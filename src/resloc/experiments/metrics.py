"""Evaluation metrics: MSLE (the paper's), RMSE, NEES (absolute and relative), its
consistency test and detector rates (communication's messages and bytes:
:mod:`resloc.experiments.traffic`)."""

from __future__ import annotations

import numpy as np

from resloc.angles import wrap_angle
from resloc.distributions import binomtest_pvalue, chi2_ppf
from resloc.linalg import solve_spd

__all__ = [
    "NEES_EXCEED_3DOF",
    "AccuracyRecorder",
    "TruthDistances",
    "align_se2",
    "confusion_counts",
    "detector_rates",
    "detector_scores",
    "msle",
    "msle_of_distances",
    "nees",
    "nees_band",
    "nees_consistency",
    "nees_consistency_counts",
    "pair_distances",
    "position_rmse",
    "rate",
    "relative_nees",
    "remove_team_rigid_motion",
]

#: ``chi2.ppf(0.95, 3)``: a consistent 3-DoF filter's NEES exceeds it 5 % of the time.
NEES_EXCEED_3DOF = 7.814727903251178


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
    return msle_of_distances(pair_distances(p_true), pair_distances(p_est))


def pair_distances(p: np.ndarray) -> np.ndarray:
    """``|p_i - p_j|`` of every pair of robots of every trial, ``(T, N, 2) -> (T, N, N)``.

    ``sqrt(dx^2 + dy^2)``: the value ``np.linalg.norm(..., axis=-1)`` gives for planar
    differences, without its strided reduction over an axis of length 2.
    """
    p = np.asarray(p, float)
    dx = p[:, :, None, 0] - p[:, None, :, 0]
    dy = p[:, :, None, 1] - p[:, None, :, 1]
    return np.sqrt(dx * dx + dy * dy)


def msle_of_distances(d_true: np.ndarray, d_est: np.ndarray) -> np.ndarray:
    """:func:`msle` from the true and estimated :func:`pair_distances` ``(T, N, N)``."""
    n = d_true.shape[1]
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


def align_se2(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid planar transform (no scale, no reflection) that best maps ``source`` onto
    ``target`` in least squares (Umeyama / Kabsch in 2-D), for a batch of point sets.

    Parameters
    ----------
    source, target : ndarray, shape (M, 2) or (T, M, 2)
        Paired points (estimated and true positions).

    Returns
    -------
    R : ndarray, shape (2, 2) or (T, 2, 2)
    t : ndarray, shape (2,) or (T, 2)
        ``target ~ source @ R.T + t``.
    """
    src = np.asarray(source, float)
    dst = np.asarray(target, float)
    mu_s, mu_d = src.mean(axis=-2), dst.mean(axis=-2)
    H = np.swapaxes(src - mu_s[..., None, :], -1, -2) @ (dst - mu_d[..., None, :])
    # In 2-D the optimal rotation angle is closed-form: atan2 of the cross and dot terms.
    angle = np.arctan2(H[..., 0, 1] - H[..., 1, 0], H[..., 0, 0] + H[..., 1, 1])
    c, s = np.cos(angle), np.sin(angle)
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    return R, mu_d - (R @ mu_s[..., None])[..., 0]


def remove_team_rigid_motion(x_true: np.ndarray, x_est: np.ndarray) -> np.ndarray:
    """The estimates moved by the team's least-squares rigid-body (SE(2)) error.

    With relative measurements only, a common rotation and translation of the whole team
    (the gauge) is unobservable; what remains after removing the best such motion is the
    relative error, the part the measurements and the detectors act on.

    Parameters
    ----------
    x_true, x_est : ndarray, shape (T, N, 3)
        True and estimated poses of the N robots of T teams.

    Returns
    -------
    ndarray, shape (T, N, 3)
        ``x_est`` rotated and translated (heading rotated by the same angle, wrapped).
    """
    x_est = np.asarray(x_est, float)
    R, t = align_se2(x_est[..., :2], np.asarray(x_true, float)[..., :2])
    out = x_est.copy()
    out[..., :2] = x_est[..., :2] @ np.swapaxes(R, -1, -2) + t[..., None, :]
    out[..., 2] = wrap_angle(x_est[..., 2] + np.arctan2(R[..., 1, 0], R[..., 0, 0])[..., None])
    return out


def relative_nees(x_true: np.ndarray, x_est: np.ndarray, P: np.ndarray) -> np.ndarray:
    """NEES of the relative error: the team's rigid-body error removed first.

    ``e_i^T P_i^{-1} e_i`` with ``e_i`` the error of robot i after
    :func:`remove_team_rigid_motion`, weighed by the same reported covariance ``P_i``.
    Removing 3 of the team's 3N degrees of freedom lowers a consistent filter's mean to
    about ``3 (N - 1) / N``; a covariance that also carries the gauge part (``gauge``
    fusion) lowers it further, so values above 3 are overconfidence in the relative
    part, whatever the gauge.

    Parameters
    ----------
    x_true, x_est : ndarray, shape (T, N, 3)
    P : ndarray, shape (T, N, 3, 3)

    Returns
    -------
    ndarray, shape (T, N)
    """
    x_true = np.asarray(x_true, float)
    T, N = x_true.shape[:2]
    aligned = remove_team_rigid_motion(x_true, x_est)
    flat = nees(x_true.reshape(-1, 3), aligned.reshape(-1, 3), np.asarray(P).reshape(-1, 3, 3))
    return flat.reshape(T, N)


def nees_consistency(samples: np.ndarray, dof: int = 3, level: float = 0.95) -> dict[str, float]:
    """A consistency test with power on NEES samples (see :func:`nees_consistency_counts`).

    Parameters
    ----------
    samples : ndarray, any shape
        Per-robot, per-step NEES samples (``nan`` ignored).
    dof : int
    level : float

    Returns
    -------
    dict
    """
    x = np.asarray(samples, float).ravel()
    x = x[np.isfinite(x)]
    above = int((x > chi2_ppf(level, dof)).sum())
    return nees_consistency_counts(float(x.sum()), x.size, above, dof, level)


def nees_band(dof: int, samples: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided ``level`` chi-square band of an average of ``samples`` independent NEES.

    ``[chi2.ppf((1 - level) / 2, dof M) / M, chi2.ppf((1 + level) / 2, dof M) / M]`` with
    ``M = samples`` (Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4.2).
    """
    m = int(samples)
    alpha = 1.0 - level
    return float(chi2_ppf(alpha / 2, dof * m) / m), float(chi2_ppf(1 - alpha / 2, dof * m) / m)


def nees_consistency_counts(
    total: float, samples: int, exceed: int, dof: int = 3, level: float = 0.95
) -> dict[str, float]:
    """A consistency test with power: every per-robot, per-step NEES sample, not seed means.

    Two statistics of the ``M = samples`` NEES values:

    * the average NEES (ANEES ``= total / M``) with the two-sided chi-square band of a
      consistent filter, ``chi2.ppf((1 -+ level) / 2, dof M) / M`` (exact for independent
      samples; successive steps of one robot are correlated, so this band is narrower than
      the truth: the exceedance test below is the one to read);
    * the share of samples above ``chi2.ppf(level, dof)`` (``exceed`` of them; a consistent
      filter: ``1 - level``) with the binomial two-sided p-value of that share.

    Parameters
    ----------
    total : float
        Sum of the samples.
    samples : int
    exceed : int
        Samples above ``chi2.ppf(level, dof)``.
    dof : int
    level : float

    Returns
    -------
    dict
        ``anees``, ``band_lo``, ``band_hi``, ``in_band`` (1.0 / 0.0), ``samples``,
        ``exceed_share``, ``exceed_expected``, ``exceed_pvalue``.
    """
    m = int(samples)
    alpha = 1.0 - level
    if m == 0:
        nan = float("nan")
        keys = ("anees", "band_lo", "band_hi", "in_band", "exceed_share", "exceed_pvalue")
        return {**dict.fromkeys(keys, nan), "samples": 0, "exceed_expected": alpha}
    lo, hi = nees_band(dof, m, level)
    anees = float(total) / m
    return {
        "anees": anees,
        "band_lo": lo,
        "band_hi": hi,
        "in_band": float(lo <= anees <= hi),
        "samples": m,
        "exceed_share": exceed / m,
        "exceed_expected": alpha,
        "exceed_pvalue": binomtest_pvalue(int(exceed), m, alpha),
    }


class TruthDistances:
    """The true :func:`pair_distances` of the last buffer of steps, kept for the next
    :class:`AccuracyRecorder` that flushes the same steps (the estimators of one run see
    the same truth, and their recorders flush the same rows one after the other)."""

    def __init__(self) -> None:
        self.key: bytes | None = None
        self.value: np.ndarray | None = None

    def distances(self, rows: np.ndarray, p_true: np.ndarray) -> np.ndarray:
        """Pair distances of ``p_true: (C * T, N, 2)``, the truth of steps ``rows``."""
        key = np.asarray(rows, np.int64).tobytes()
        if key != self.key or self.value is None:
            self.key, self.value = key, pair_distances(p_true)
        return self.value


class AccuracyRecorder:
    """The per-step accuracy of one estimator (MSLE, RMSE, NEES, relative NEES), computed in
    bulk over many steps.

    At 17 robots one step's metrics are a few dozen small numpy calls whose fixed cost
    exceeds their arithmetic; :meth:`add` only copies the step's truth, estimate and
    covariance into a buffer, and the metric functions above run once per buffer of steps,
    on the steps stacked into the batch dimension they already have. The buffer holds at
    most :data:`BUFFER_BYTES` (one step at a time when a single step needs more, as with
    the ``O(N^2)`` MSLE of a large team), and is emptied when full, when the series' last
    row is added, and on :meth:`flush`. The values equal the per-step computation exactly.

    Parameters
    ----------
    series : dict of str to ndarray, each shape (steps, T)
        Receives rows ``msle``, ``rmse``, ``nees`` (mean over robots) and ``nees_rel``.
    totals : dict of str to ndarray, each shape (T,)
        Accumulates ``nees_samples``, ``nees_exceed`` and ``nees_rel_exceed`` (samples
        above :data:`NEES_EXCEED_3DOF`).
    trials, robots : int
        ``T`` and ``N``; states arrive as ``(T * N, 3)``, trial-major.
    truth : TruthDistances, optional
        Shared by the recorders of estimators that see the same truth at every step (one
        run), so the true pair distances of a buffer are computed once, not per estimator.
    without : dict of str to ndarray, optional
        ``{name: ids}``: also a row ``msle_<name>``, the MSLE of the team without robots
        ``ids`` (the pairs among the others, normalized by their number): the robots an
        attacker runs left out (:meth:`~resloc.world.attackers.base.Strategy.owned`).
    """

    #: Most bytes the buffered steps and their metric temporaries may take.
    BUFFER_BYTES = 16_000_000
    #: Most steps per bulk evaluation (beyond it the fixed costs are already amortized).
    MAX_ROWS = 256

    def __init__(
        self,
        series: dict,
        totals: dict,
        trials: int,
        robots: int,
        truth: TruthDistances | None = None,
        without: dict[str, np.ndarray] | None = None,
    ) -> None:
        self.series, self.totals = series, totals
        self.truth = truth
        self.kept = {}
        for name, ids in (without or {}).items():
            self.kept[name] = np.setdiff1d(np.arange(robots), np.asarray(ids, int))
            series[f"msle_{name}"] = np.full_like(series["msle"], np.nan)
        self.trials, self.robots = trials, robots
        self.last_row = len(series["msle"]) - 1
        robots_total = trials * robots
        # x, pose (3 each) and P (9) per robot, and the (N, N, 2) pair temporaries of msle.
        per_step = 8 * robots_total * (15 + 8 * robots)
        self.capacity = int(max(1, min(self.MAX_ROWS, self.BUFFER_BYTES // per_step)))
        self.rows = np.zeros(self.capacity, np.int64)
        self.pose = np.zeros((self.capacity, robots_total, 3))
        self.x = np.zeros((self.capacity, robots_total, 3))
        self.P = np.zeros((self.capacity, robots_total, 3, 3))
        self.filled = 0

    def add(self, row: int, pose: np.ndarray, x: np.ndarray, P: np.ndarray) -> None:
        """Record step ``row`` (0-based row of ``series``).

        Parameters
        ----------
        row : int
        pose, x : ndarray, shape (T * N, 3)
            True and estimated poses.
        P : ndarray, shape (T * N, 3, 3)
            The covariances the estimator reports.
        """
        n = self.filled
        self.rows[n] = row
        self.pose[n], self.x[n], self.P[n] = pose, x, P
        self.filled = n + 1
        if self.filled == self.capacity or row == self.last_row:
            self.flush()

    def flush(self) -> None:
        """Compute the metrics of the buffered steps and write them into the series."""
        C, T, N = self.filled, self.trials, self.robots
        if C == 0:
            return
        self.filled = 0
        rows = self.rows[:C]
        pose = self.pose[:C].reshape(C * T, N, 3)
        x = self.x[:C].reshape(C * T, N, 3)
        P = self.P[:C].reshape(C * T, N, 3, 3)
        s, tot = self.series, self.totals
        if self.truth is None:
            d_true = pair_distances(pose[..., :2])
        else:
            d_true = self.truth.distances(rows, pose[..., :2])
        d_est = pair_distances(x[..., :2])
        s["msle"][rows] = msle_of_distances(d_true, d_est).reshape(C, T)
        for name, kept in self.kept.items():
            pairs = np.ix_(np.arange(C * T), kept, kept)
            s[f"msle_{name}"][rows] = msle_of_distances(d_true[pairs], d_est[pairs]).reshape(C, T)
        s["rmse"][rows] = position_rmse(pose[..., :2], x[..., :2]).reshape(C, T)
        per_robot = nees(pose.reshape(-1, 3), x.reshape(-1, 3), P.reshape(-1, 3, 3))
        per_robot = per_robot.reshape(C, T, N)
        rel = relative_nees(pose, x, P).reshape(C, T, N)
        s["nees"][rows] = per_robot.mean(axis=2)
        s["nees_rel"][rows] = rel.mean(axis=2)
        tot["nees_samples"] += N * C
        tot["nees_exceed"] += (per_robot > NEES_EXCEED_3DOF).sum(axis=(0, 2))
        tot["nees_rel_exceed"] += (rel > NEES_EXCEED_3DOF).sum(axis=(0, 2))
