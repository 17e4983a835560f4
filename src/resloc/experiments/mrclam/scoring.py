"""Scoring a replay against the motion-capture ground truth, and the result types.

Metrics at every step where the robot's ground truth exists (no gap longer than
``gt_max_gap``): position RMSE, heading RMSE, NEES; MSLE (the paper's) where every robot has
ground truth; communication rate = transmissions / robot-to-robot measurements.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from resloc.angles import wrap_angle
from resloc.experiments.lockstep import DEAD_RECKONING
from resloc.experiments.metrics import detector_scores, msle, nees, rate
from resloc.experiments.mrclam.config import MRCLAMConfig
from resloc.experiments.mrclam.replay import Replay
from resloc.world.zones import Zone

__all__ = [
    "ERROR_STATISTICS",
    "LINK_OUTCOMES",
    "MRCLAMEstimate",
    "MRCLAMResult",
    "empty_link_log",
    "score_estimate",
]


@dataclass
class MRCLAMEstimate:
    """One estimator's replay.

    Attributes
    ----------
    name : str
        ``ckf``, ``ukf``, ``ekf`` or ``dr``.
    track : ndarray, shape (K + 1, N, 3)
        Estimated poses at the step times.
    pos_err : ndarray, shape (K + 1, N)
        ``|p_est - p_true|`` (m), ``nan`` where the ground truth is invalid.
    heading_err : ndarray, shape (K + 1, N)
        Wrapped heading error (rad), ``nan`` where invalid.
    nees : ndarray, shape (K + 1, N)
        ``nan`` where invalid.
    msle : ndarray, shape (K + 1,)
        ``nan`` where some robot has no valid ground truth.
    links : dict of str to ndarray, each shape (M,)
        Per-measurement outcome: ``norm``, ``detected``, ``triggered``, ``delivered``,
        ``fused`` (all False for dead reckoning).
    per_robot : dict of str to ndarray, each shape (N,)
    overall : dict of str to float
    wall_time : float
    cov : ndarray of float32, shape (K + 1, N, 3, 3), optional
        Covariances at the step times (for exports).
    diverged : dict or None
        If the estimator diverged (:func:`~resloc.experiments.lockstep.divergence`): its
        track, covariances and errors are ``nan`` from that step on, its link outcomes
        false, and its overall error statistics ``nan`` (with ``diverged_step``): an
        average over the steps before the failure would look like a result.
    """

    name: str
    track: np.ndarray
    pos_err: np.ndarray
    heading_err: np.ndarray
    nees: np.ndarray
    msle: np.ndarray
    links: dict[str, np.ndarray]
    per_robot: dict[str, np.ndarray] = field(default_factory=dict)
    overall: dict[str, float] = field(default_factory=dict)
    wall_time: float = 0.0
    cov: np.ndarray | None = None
    diverged: dict | None = None


@dataclass
class MRCLAMResult:
    """A finished replay: configuration, data description, truth and every estimator.

    Attributes
    ----------
    config : MRCLAMConfig
    info : dict
        Dataset name and path, start time, steps, rows loaded/skipped, zones, noise.
    time : ndarray, shape (K + 1,)
    truth : ndarray, shape (K + 1, N, 3)
    valid : ndarray of bool, shape (K + 1, N)
    robots : ndarray of int, shape (N,)
        Subject numbers.
    landmark_xy : ndarray, shape (L, 2)
    zones : dict of str to list of Zone
    estimators : dict of str to MRCLAMEstimate
    wall_time : float
    measurements : dict of str to ndarray, each shape (M,)
        The replayed measurements (for exports): ``step``, observer ``i``, target ``j``
        (robot index, or ``N + landmark index``), ``attacked``; the estimators' ``links``
        give each one's outcome, row for row.
    """

    config: MRCLAMConfig
    info: dict
    time: np.ndarray
    truth: np.ndarray
    valid: np.ndarray
    robots: np.ndarray
    landmark_xy: np.ndarray
    zones: dict[str, list[Zone]]
    estimators: dict[str, MRCLAMEstimate]
    wall_time: float = 0.0
    measurements: dict[str, np.ndarray] = field(default_factory=dict)

    def summary(self) -> dict[str, dict[str, float]]:
        """``{estimator: overall stats}``."""
        return {name: dict(e.overall) for name, e in self.estimators.items()}

    def per_robot(self) -> dict[str, dict[str, list[float]]]:
        """``{estimator: {stat: [value per robot]}}``."""
        return {
            name: {k: v.tolist() for k, v in e.per_robot.items()}
            for name, e in self.estimators.items()
        }


#: Per-sighting outcomes a replay keeps (fields of :class:`~resloc.cl.links.LinkOutcome`).
LINK_OUTCOMES = ("norm", "detected", "triggered", "delivered", "fused")

#: Overall statistics that are blank (``nan``) for an estimator that diverged.
ERROR_STATISTICS = (
    "position_rmse",
    "position_error_final",
    "heading_rmse",
    "heading_rmse_deg",
    "nees_mean",
    "nees_median",
    "msle_mean",
)


def empty_link_log(M: int) -> dict[str, np.ndarray]:
    """Per-sighting outcomes of a replay, shape (M,) each, before any step ran: trigger
    norm (nan) and the detected / triggered / delivered / fused flags (False)."""
    return {
        "norm": np.full(M, np.nan),
        **{flag: np.zeros(M, bool) for flag in LINK_OUTCOMES[1:]},
    }


def score_estimate(
    name: str,
    rp: Replay,
    track: np.ndarray,
    cov: np.ndarray,
    links: dict[str, np.ndarray],
    wall: float,
    diverged: dict | None = None,
) -> MRCLAMEstimate:
    """One estimator's replay scored against the ground truth of ``rp``: ``track: (K + 1,
    N, 3)``, ``cov: (K + 1, N, 3, 3)``, per-sighting ``links`` (:func:`empty_link_log`),
    ``wall`` seconds; error statistics ``nan`` if ``diverged``."""
    N = rp.dataset.n_robots
    valid = rp.valid
    d = track[..., :2] - rp.truth[..., :2]
    pos_err = np.where(valid, np.hypot(d[..., 0], d[..., 1]), np.nan)
    heading_err = np.where(valid, wrap_angle(track[..., 2] - rp.truth[..., 2]), np.nan)
    # A stopped estimator's track and covariances are nan from where it stopped.
    estimated = np.isfinite(cov).all(axis=(-2, -1))
    nees_v = np.full(valid.shape, np.nan)
    nees_v[estimated] = nees(rp.truth[estimated], track[estimated], cov[estimated])
    nees_v[~valid] = np.nan
    all_valid = valid.all(axis=1)
    msle_v = np.full(len(rp.time), np.nan)
    if all_valid.any():
        msle_v[all_valid] = msle(rp.truth[all_valid, :, :2], track[all_valid, :, :2])

    rob = rp.is_robot
    obs = rp.obs
    cand = np.bincount(obs[rob], minlength=N)
    trig = np.bincount(obs[rob], weights=links["triggered"][rob], minlength=N)
    fused_r = np.bincount(obs[rob], weights=links["fused"][rob], minlength=N)
    lm = ~rob
    n_lm = np.bincount(obs[lm], minlength=N)
    fused_lm = np.bincount(obs[lm], weights=links["fused"][lm], minlength=N)
    with np.errstate(invalid="ignore", divide="ignore"), _quiet_nan_warnings():
        per_robot = {
            "position_rmse": np.sqrt(np.nanmean(pos_err**2, axis=0)),
            "position_error_final": _last_valid(pos_err),
            "position_error_max": np.nanmax(np.where(valid, pos_err, -np.inf), axis=0),
            "heading_rmse": np.sqrt(np.nanmean(heading_err**2, axis=0)),
            "nees_mean": np.nanmean(nees_v, axis=0),
            "nees_median": np.nanmedian(nees_v, axis=0),
            "robot_measurements": cand.astype(float),
            "comm_rate": np.where(cand > 0, trig / np.maximum(cand, 1), np.nan),
            "robot_fused": fused_r,
            "landmark_measurements": n_lm.astype(float),
            "landmark_fused": fused_lm,
            "scored_fraction": valid.mean(axis=0),
        }
    det = detector_scores(links["detected"][rob], rp.attacked[rob])
    if name == DEAD_RECKONING:  # no detector: its scores are undefined, not zero
        det = {k: (0 if k in ("tp", "fp", "fn", "tn") else float("nan")) for k in det}
    overall = {
        "position_rmse": float(np.sqrt(np.nanmean(pos_err**2))),
        "position_error_final": float(np.nanmean(per_robot["position_error_final"])),
        "heading_rmse": float(np.sqrt(np.nanmean(heading_err**2))),
        "heading_rmse_deg": float(np.degrees(np.sqrt(np.nanmean(heading_err**2)))),
        "nees_mean": float(np.nanmean(nees_v)),
        "nees_median": float(np.nanmedian(nees_v)),
        "msle_mean": float(np.nanmean(msle_v)) if all_valid.any() else float("nan"),
        "msle_scored_fraction": float(all_valid.mean()),
        "comm_rate": rate(links["triggered"][rob].sum(), rob.sum()),
        "delivery_rate": rate(links["delivered"][rob].sum(), links["triggered"][rob].sum()),
        "robot_measurements": int(rob.sum()),
        "robot_fused": int(links["fused"][rob].sum()),
        "landmark_measurements": int(lm.sum()),
        "landmark_fused": int(links["fused"][lm].sum()),
        "landmark_detected": int(links["detected"][lm].sum()),
        "attacked": int(rp.attacked.sum()),
        "attacked_fused": int((links["fused"] & rp.attacked).sum()),
        "detector_tp": det["tp"],
        "detector_fp": det["fp"],
        "detector_fn": det["fn"],
        "detector_tn": det["tn"],
        "detector_precision": det["precision"],
        "detector_recall": det["recall"],
        "detector_false_alarm": det["false_alarm_rate"],
        "wall_time_s": wall,
    }
    if diverged:
        overall.update(dict.fromkeys(ERROR_STATISTICS, float("nan")))
        overall["diverged_step"] = diverged["step"]
    errors = (pos_err, heading_err, nees_v, msle_v)
    cov32 = cov.astype(np.float32)
    return MRCLAMEstimate(name, track, *errors, links, per_robot, overall, wall, cov32, diverged)


@contextlib.contextmanager
def _quiet_nan_warnings() -> Iterator[None]:
    """Silence numpy's "mean of empty slice" warnings (all-nan columns give nan on purpose)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def _last_valid(err: np.ndarray) -> np.ndarray:
    """Last non-nan value per column of ``err: (K, N)``, shape (N,)."""
    ok = ~np.isnan(err)
    idx = np.where(ok.any(axis=0), err.shape[0] - 1 - np.argmax(ok[::-1], axis=0), 0)
    out = err[idx, np.arange(err.shape[1])]
    return np.where(ok.any(axis=0), out, np.nan)
