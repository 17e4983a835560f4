"""What a simulated run returns: every estimator's per-step series, per-trial totals and
trial-0 records (:class:`EstimatorResult`), and the run (:class:`RunResult`)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from resloc.experiments.config import Scenario
from resloc.experiments.metrics import detector_rates, nees_consistency_counts, rate
from resloc.experiments.recording import LinkLog
from resloc.experiments.traffic import communication, uncounted_traffic

__all__ = ["SERIES", "TOTALS", "EstimatorResult", "RunResult"]

#: Per-step series recorded for every estimator, each of shape (steps, T).
SERIES = (
    "msle",
    "rmse",
    "nees",
    "nees_rel",
    "candidates",
    "triggered",
    "delivered",
    "detected",
    "attacked",
)
#: Per-trial totals, each of shape (T,).
TOTALS = (
    "candidates",
    "triggered",
    "delivered",
    "failed",
    "detected",
    "fused",
    "attacked",
    "tp",
    "fp",
    "fn",
    "tn",
    "attacked_fused",
    "repairs",
    "nees_samples",
    "nees_exceed",
    "nees_rel_exceed",
    "ack_links",
    "ack_frames",
    "consensus_messages",
    "readings",
    "delivery_ack_links",
    "delivery_ack_frames",
    "independent_parts",
    "factors",
    "pair_ack_links",
    "pair_ack_frames",
    "pair_messages",
    "pair_frames",
    "connectivity_messages",
    "witness_frames",
    "witness_notes",
)


@dataclass
class EstimatorResult:
    """Everything recorded for one estimator over a run.

    Attributes
    ----------
    name : str
        ``ckf``, ``ukf``, ``ekf`` or ``dr``.
    series : dict of str to ndarray, each shape (steps, T)
        Per-step metrics (``msle``, ``rmse``, ``nees``) and link counts.
    totals : dict of str to ndarray, each shape (T,)
        Per-trial counts over the run.
    raster : ndarray of int8, shape (steps, N)
        Transmissions attempted by each robot of trial 0 at each step.
    track : ndarray, shape (steps + 1, N, 3)
        Estimated poses of trial 0.
    wall_time : float
        Seconds spent in this estimator's predict/correct.
    cov : ndarray of float32, shape (steps + 1, N, 3, 3), optional
        Covariances of trial 0 (as reported: with gauge fusion ``D_i + J_i G J_i^T``).
    links : LinkLog, optional
        Every sensed link of trial 0 over the run, each shape (M,): ``step`` (1-based),
        ``i``, ``j``, ``attacked`` (shared by the estimators) and this estimator's
        ``detected``, ``triggered``, ``delivered``, ``fused`` (for exports and figures).
    diverged : dict or None
        If the estimator diverged: ``step`` (1-based), ``time_s``, ``trial``, ``robot`` and
        ``reason`` (see :func:`divergence`). Its series, track and covariances are ``nan``
        from that step on (its link outcomes all false) and its summary's error statistics
        are ``nan``: an average over the steps before the failure would look like a result.
    """

    name: str
    series: dict[str, np.ndarray]
    totals: dict[str, np.ndarray]
    raster: np.ndarray
    track: np.ndarray
    wall_time: float = 0.0
    cov: np.ndarray | None = None
    links: LinkLog | None = None
    diverged: dict | None = None

    def summary(self) -> dict[str, float]:
        """Scalar summary: means over steps and trials, final values, rates, detector scores
        (error statistics ``nan`` and ``diverged_step`` set if the estimator diverged)."""
        with warnings.catch_warnings():  # a diverged estimator has all-NaN final steps
            warnings.filterwarnings("ignore", "Mean of empty slice", RuntimeWarning)
            warnings.filterwarnings("ignore", "All-NaN slice", RuntimeWarning)
            out = self._summary()
        if self.diverged:
            for key in ("msle_mean", "msle_final", "rmse_mean", "rmse_final"):
                out[key] = float("nan")
            out["nees_mean"] = out["nees_median"] = float("nan")
            out["diverged_step"] = self.diverged["step"]
        return out

    def _summary(self) -> dict[str, float]:
        s, t = self.series, self.totals
        steps = s["msle"].shape[0]
        out = {
            "msle_mean": float(np.nanmean(s["msle"])),
            "msle_final": float(np.nanmean(s["msle"][-1])),
            "rmse_mean": float(np.nanmean(s["rmse"])),
            "rmse_final": float(np.nanmean(s["rmse"][-1])),
            "nees_mean": float(np.nanmean(s["nees"])),
            "nees_median": float(np.nanmedian(s["nees"])),
            "comm_rate": rate(t["triggered"].sum(), t["candidates"].sum()),
            "delivery_rate": rate(t["delivered"].sum(), t["triggered"].sum()),
            "fused_rate": rate(t["fused"].sum(), t["candidates"].sum()),
            "attacked_rate": rate(t["attacked"].sum(), t["candidates"].sum()),
            "attacked_fused": int(t["attacked_fused"].sum()),
            "candidates": int(t["candidates"].sum()),
            "transmissions": int(t["triggered"].sum()),
            "delivered": int(t["delivered"].sum()),
            "failed": int(t["failed"].sum()),
            "discarded": int(t["detected"].sum()),
            "repairs": int(t["repairs"].sum()),
            "wall_time_s": self.wall_time,
            "steps": steps,
        }
        scores = detector_rates(*(int(t[k].sum()) for k in ("tp", "fp", "fn", "tn")))
        out["detector_precision"] = scores["precision"]
        out["detector_recall"] = scores["recall"]
        out["detector_false_alarm"] = scores["false_alarm_rate"]
        out.update(self._honest_summary())
        return out

    def _honest_summary(self) -> dict[str, float]:
        """Relative NEES, the consistency tests on every per-robot, per-step sample, and the
        messages and bytes of every kind (``WIRE_BYTES``)."""
        s, t = self.series, self.totals
        n = int(t["nees_samples"].sum())
        out = {"nees_rel_mean": float(np.nanmean(s["nees_rel"]))}
        for key, series in (("nees", s["nees"]), ("nees_rel", s["nees_rel"])):
            test = nees_consistency_counts(
                float(np.nanmean(series)) * n, n, int(t[f"{key}_exceed"].sum())
            )
            out[f"{key}_band_lo"], out[f"{key}_band_hi"] = test["band_lo"], test["band_hi"]
            out[f"{key}_exceed_share"] = test["exceed_share"]
            out[f"{key}_exceed_pvalue"] = test["exceed_pvalue"]
        for kind, (messages, wire) in communication(t).items():
            out[f"messages_{kind}"] = int(messages.sum())
            out[f"bytes_{kind}"] = int(wire.sum())
        return out

    def bytes_per_trial(self) -> np.ndarray:
        """Robot-to-robot bytes of every kind per trial, shape (T,) (``communication``)."""
        return communication(self.totals)["total"][1]

    def bytes_per_step(self, fusion) -> np.ndarray:
        """Robot-to-robot bytes per step and trial, shape (T,); ``nan`` for a fusion method
        whose traffic is not counted (:func:`~resloc.experiments.traffic.uncounted_traffic`:
        the centralized ``tracked``)."""
        per_step = self.bytes_per_trial() / self.series["msle"].shape[0]
        return np.full(per_step.shape, np.nan) if uncounted_traffic(fusion) else per_step

    def per_trial(self, metric: str) -> np.ndarray:
        """A per-trial scalar, shape (T,): ``msle_mean``, ``msle_final``, ``rmse_mean``,
        ``nees_mean`` or ``comm_rate``."""
        s, t = self.series, self.totals
        if metric == "comm_rate":
            with np.errstate(invalid="ignore", divide="ignore"):
                return t["triggered"] / t["candidates"]
        key, how = metric.rsplit("_", 1)
        return np.nanmean(s[key], axis=0) if how == "mean" else s[key][-1]


@dataclass
class RunResult:
    """A finished run: the resolved scenario, the truth of trial 0, and every estimator."""

    scenario: Scenario
    estimators: dict[str, EstimatorResult]
    truth: np.ndarray  # (steps + 1, N, 3) true poses of trial 0
    time: np.ndarray  # (steps,) seconds
    wall_time: float = 0.0
    meta: dict = field(default_factory=dict)

    def summary(self) -> dict[str, dict[str, float]]:
        """``{estimator: summary}``."""
        return {name: est.summary() for name, est in self.estimators.items()}
