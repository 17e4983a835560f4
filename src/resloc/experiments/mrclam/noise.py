"""Sensor noise of an MRCLAM replay: measured against the ground truth (how the defaults
were chosen, ``--noise auto``), and the range noise that grows with the range, fused in
groups of rows that share one quantized level."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from resloc.angles import wrap_angle
from resloc.cl.params import CLParams
from resloc.datasets.mrclam import MRCLAMDataset
from resloc.errors import ConfigError
from resloc.experiments.mrclam.config import MRCLAMConfig
from resloc.experiments.mrclam.replay import ground_truth_at, step_commands
from resloc.models.measurement import range_bearing

__all__ = [
    "NOISE_TAIL_FACTOR",
    "RANGE_STD_QUANTUM",
    "estimate_noise",
    "level_groups",
    "noise_from_fit",
    "range_noise_level",
    "range_noise_std",
]


def _robust_std(e: np.ndarray) -> float:
    """``1.4826 * MAD``: the standard deviation of the Gaussian core, blind to outliers."""
    return float(1.4826 * np.median(np.abs(e - np.median(e)))) if len(e) else float("nan")


def estimate_noise(
    data: MRCLAMDataset, max_gap: float = 0.25, window: float = 1.0
) -> dict[str, dict[str, float]]:
    """Sensor noise measured against the ground truth (how the defaults were chosen).

    Measurements: measured minus ground-truth-implied range and bearing of every robot and
    landmark sighting whose observer (and observed robot) has ground truth. Odometry: over
    consecutive ``window``-second intervals, the distance along the heading and the heading
    change from the ground truth minus the integral of the commanded ``v`` and ``omega``,
    divided by ``sqrt(window)`` (a noise density, as :class:`MRCLAMConfig` expects).

    Parameters
    ----------
    data : MRCLAMDataset
    max_gap : float
        Ground-truth gap (s) above which a time is not used.
    window : float
        Odometry integration window (s).

    Returns
    -------
    dict
        ``robot`` and ``landmark``: ``n``, ``range_bias``, ``range_std``,
        ``range_std_robust``, ``range_std_rel_robust`` (robust std of the range error divided
        by the true range), ``bearing_bias``, ``bearing_std``, ``bearing_std_robust``.
        ``odometry``: ``n``, ``v_bias``, ``v_density``, ``v_density_robust``,
        ``omega_bias``, ``omega_density``, ``omega_density_robust``.
    """
    lm = dict(zip(data.landmark_subjects.tolist(), data.landmark_xy, strict=True))
    robot_log = {log.subject: log for log in data.robots}
    err: dict[str, list[np.ndarray]] = {"robot": [], "landmark": []}
    odo_err: list[np.ndarray] = []
    for log in data.robots:
        m = log.measurements
        if len(m):
            xi, ok = ground_truth_at(log.groundtruth, m[:, 0], max_gap)
            xj = np.zeros((len(m), 3))
            subject = m[:, 1].astype(int)
            rob = np.isin(subject, list(robot_log))
            for s in np.unique(subject[rob]):
                sel = subject == s
                xj[sel], ok_j = ground_truth_at(robot_log[s].groundtruth, m[sel, 0], max_gap)
                ok[sel] &= ok_j
            for k in np.flatnonzero(~rob):
                xj[k, :2] = lm[subject[k]]
            z_true = range_bearing(xi, xj)
            e = m[:, 2:4] - z_true
            e[:, 1] = wrap_angle(e[:, 1])
            rel = e[:, 0] / np.maximum(z_true[:, 0], 1e-6)
            rows = np.column_stack([e, rel])
            err["robot"].append(rows[ok & rob])
            err["landmark"].append(rows[ok & ~rob])
        g, o = log.groundtruth, log.odometry
        if len(o) < 2 or len(g) < 2:
            continue
        edges = np.arange(max(g[0, 0], o[0, 0]), min(g[-1, 0], o[-1, 0]), window)
        if len(edges) < 2:
            continue
        pose, ok = ground_truth_at(g, edges, max_gap)
        cmd = step_commands(o, edges) * window  # (W, 2): commanded distance, turn
        heading = np.unwrap(pose[:, 2])
        mid = 0.5 * (heading[1:] + heading[:-1])
        dist = np.diff(pose[:, 0]) * np.cos(mid) + np.diff(pose[:, 1]) * np.sin(mid)
        turn = np.diff(heading)
        both = ok[1:] & ok[:-1]
        odo_err.append(np.column_stack([dist - cmd[:, 0], turn - cmd[:, 1]])[both])
    out: dict[str, dict[str, float]] = {}
    for kind, parts in err.items():
        e = np.concatenate(parts) if parts else np.zeros((0, 3))
        out[kind] = {
            "n": len(e),
            "range_bias": float(np.median(e[:, 0])) if len(e) else float("nan"),
            "range_std": float(e[:, 0].std()) if len(e) else float("nan"),
            "range_std_robust": _robust_std(e[:, 0]),
            "range_std_rel_robust": _robust_std(e[:, 2]),
            "bearing_bias": float(np.median(e[:, 1])) if len(e) else float("nan"),
            "bearing_std": float(e[:, 1].std()) if len(e) else float("nan"),
            "bearing_std_robust": _robust_std(e[:, 1]),
        }
    e = np.concatenate(odo_err) if odo_err else np.zeros((0, 2))
    root = math.sqrt(window)
    out["odometry"] = {
        "n": len(e),
        "v_bias": float(e[:, 0].mean() / window) if len(e) else float("nan"),
        "v_density": float(e[:, 0].std() / root) if len(e) else float("nan"),
        "v_density_robust": _robust_std(e[:, 0]) / root,
        "omega_bias": float(e[:, 1].mean() / window) if len(e) else float("nan"),
        "omega_density": float(e[:, 1].std() / root) if len(e) else float("nan"),
        "omega_density_robust": _robust_std(e[:, 1]) / root,
    }
    return out


#: Robust stds of the sightings are multiplied by this for the filter's ``R``: the errors
#: are heavy-tailed and correlated in time (``docs/mrclam.md``, "Sensor noise"); on Dataset
#: 6 it turns the fitted 0.042 / 0.0083 rad into the defaults 0.07 / 0.015 rad.
NOISE_TAIL_FACTOR = 1.8


def noise_from_fit(fit: dict[str, dict[str, float]]) -> dict[str, object]:
    """The :class:`MRCLAMConfig` noise fields from an :func:`estimate_noise` fit.

    Range noise per metre and bearing noise: the larger of the robot and landmark sightings'
    robust stds times :data:`NOISE_TAIL_FACTOR`; the range floor ``range_std`` stays at its
    default (the per-metre term dominates beyond 0.5 m); odometry densities: the plain
    (tail-including) stds of the 1 s windows.

    Raises
    ------
    ConfigError
        When the data give no ground-truth-matched sightings or odometry windows.
    """
    sight = [fit[k] for k in ("robot", "landmark") if fit[k]["n"] > 0]
    odo = fit["odometry"]
    if not sight or odo["n"] < 2:
        raise ConfigError(
            "noise: cannot fit the sensor noise (no sightings or odometry windows with ground "
            "truth); use --noise default"
        )
    rel = max(s["range_std_rel_robust"] for s in sight)
    bearing = max(s["bearing_std_robust"] for s in sight)
    values = {
        "range_std_rel": NOISE_TAIL_FACTOR * rel,
        "bearing_std": NOISE_TAIL_FACTOR * bearing,
        "odometry_density": (odo["v_density"], odo["omega_density"]),
    }
    flat = [values["range_std_rel"], values["bearing_std"], *values["odometry_density"]]
    if not all(np.isfinite(v) and v > 0 for v in flat):
        raise ConfigError(f"noise: the fit gave unusable values {values}; use --noise default")
    return values


#: Range-noise standard deviations are rounded to this (m) so that rows share parameters.
RANGE_STD_QUANTUM = 0.005


def range_noise_std(z_range: np.ndarray, config: MRCLAMConfig) -> np.ndarray:
    """Range noise model ``sigma_r = sqrt(range_std^2 + (range_std_rel * z)^2)``.

    Parameters
    ----------
    z_range : ndarray, shape (M,)
        Measured ranges (m).
    config : MRCLAMConfig

    Returns
    -------
    ndarray, shape (M,)
    """
    return np.hypot(config.range_std, config.range_std_rel * np.asarray(z_range, float))


def range_noise_level(z_range: np.ndarray, config: MRCLAMConfig) -> np.ndarray:
    """:func:`range_noise_std` in units of :data:`RANGE_STD_QUANTUM` (rounded), int (M,)."""
    return np.maximum(np.rint(range_noise_std(z_range, config) / RANGE_STD_QUANTUM), 1).astype(
        np.int64
    )


def level_groups(
    level: np.ndarray, base: CLParams, cache: dict[int, CLParams]
) -> list[tuple[np.ndarray, CLParams]]:
    """Rows ``level: (M,)`` (:func:`range_noise_level`) grouped by level, ascending, each
    with ``base`` at the level's ``range_std`` (memoized in ``cache``): one ``correct`` call
    per level, as ``CLParams`` has one scalar range std. Rows keep their order."""
    groups = []
    for lv in np.unique(level).tolist():
        params = cache.get(lv)
        if params is None:
            params = cache[lv] = dataclasses.replace(base, range_std=lv * RANGE_STD_QUANTUM)
        groups.append((np.flatnonzero(level == lv), params))
    return groups
