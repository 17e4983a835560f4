"""``run_mrclam``: a dataset through dead reckoning and the configured filters in the one
estimator loop of the simulator (:func:`~resloc.experiments.lockstep.run_lockstep`), scored
against the ground truth.

The replay as a step source (:class:`ReplaySteps`): over step ``(t_{k-1}, t_k]`` every robot
predicts with the step's odometry; then the sightings time-stamped in the step are fused,
sorted by observer and time: first the landmark sightings (fixed neighbours
``x_j = (x_l, y_l, 0)``, ``P_j`` from the landmark ground-truth standard deviations;
detector on, trigger off: a landmark sighting needs no message, and its channel is never
jammed), then the robot-to-robot sightings, whose neighbour estimate is the neighbour's
current estimate, through detector, event trigger and channel; each part in groups of one
range-noise level (:func:`~resloc.experiments.mrclam.noise.level_groups`). The robots share
one wireless network: every robot sees ``lambda2 = N``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from resloc.cl.fusion_methods import fusion_strategy
from resloc.datasets.mrclam import MRCLAMDataset, load_mrclam
from resloc.experiments.lockstep import (
    DEAD_RECKONING,
    Estimation,
    EstimatorState,
    LinkGroup,
    Step,
    divergence,
    run_lockstep,
)
from resloc.experiments.mrclam.config import MRCLAMConfig
from resloc.experiments.mrclam.noise import level_groups, range_noise_level
from resloc.experiments.mrclam.replay import Replay, prepare_replay
from resloc.experiments.mrclam.scoring import (
    LINK_OUTCOMES,
    MRCLAMEstimate,
    MRCLAMResult,
    empty_link_log,
    score_estimate,
)
from resloc.filters.base import FilterKind, make_filter
from resloc.filters.update import covariance_is_pd

__all__ = ["ReplayLog", "ReplaySteps", "landmark_states", "replay_result", "run_mrclam"]


def run_mrclam(
    data: MRCLAMDataset | str | Path,
    config: MRCLAMConfig | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> MRCLAMResult:
    """Replay an MRCLAM dataset through dead reckoning and the configured filters.

    Every estimator steps through the same data in lockstep; a numerical failure stops the
    failing estimator only (its ``diverged`` says where), the others finish.

    Parameters
    ----------
    data : MRCLAMDataset or path
        A loaded dataset, or a folder (loaded up to ``config.duration``).
    config : MRCLAMConfig, optional
    progress : callable(estimator, k, steps), optional

    Returns
    -------
    MRCLAMResult
    """
    t_start = time.perf_counter()
    config = config or MRCLAMConfig()
    if not isinstance(data, MRCLAMDataset):
        data = load_mrclam(data, duration=config.duration, strict=config.strict)
    rp = prepare_replay(data, config)
    params = config.cl_params()
    x0, P0 = rp.initial_estimates(config.init_std)
    names = (DEAD_RECKONING, *config.filters)
    nodes = data.n_robots + len(data.landmark_subjects)  # landmarks are neighbours too
    fusion = fusion_strategy(params.fusion)
    estimators = [
        EstimatorState(name, make_filter(FilterKind(name)), x0, P0, nodes, fusion)
        if name != DEAD_RECKONING
        else EstimatorState(name, make_filter(FilterKind.EKF), x0, P0, nodes)
        for name in names
    ]
    source = ReplaySteps(rp, config, names, x0, P0)
    K, stride = rp.steps, max(rp.steps // 200, 1)

    def tick(k: int) -> None:
        if progress is not None and (k % stride == 0 or k == K):
            for name in names:
                progress(name, k, K)

    run_lockstep(source, estimators, Estimation(params, config.dt, data.n_robots), tick)
    scored = {}
    for est in estimators:
        source.stop_at_invalid_covariance(est, config.dt)
        log = source.logs.pop(est.name)  # its float64 covariances go once scored
        scored[est.name] = score_estimate(
            est.name, rp, log.track, log.cov, log.links, est.wall, est.diverged
        )
    info = {
        "t0_unix": data.t0,
        "data_end_s": data.end,
        "rows_loaded": data.counts(),
        "rows_skipped": dict(data.skipped),
        "rows_skipped_by_file": data.skipped_by_file,
        "attacked": int(rp.attacked.sum()),
        "jammed": int((~rp.channel_ok).sum()),
        "lambda2": float(data.n_robots),
        "cl_params": {
            "odometry_std_per_step": list(params.odometry_std),
            "process_floor_std": list(params.process_floor_std),
        },
    }
    return replay_result(rp, config, scored, time.perf_counter() - t_start, info)


def replay_result(
    rp: Replay,
    config: MRCLAMConfig,
    estimators: dict[str, MRCLAMEstimate],
    wall: float,
    info: dict,
) -> MRCLAMResult:
    """The :class:`MRCLAMResult` of replay ``rp``: its data description (dataset, steps,
    robots, landmarks, sightings replayed, zones) with ``info`` added."""
    data = rp.dataset
    zones = {"sdz": list(rp.sdz.zones), "cdz": list(rp.cdz.zones)}
    info = {
        "dataset": data.name,
        "path": str(data.path),
        "replayed_s": float(rp.time[-1]),
        "steps": rp.steps,
        "robots": data.robot_subjects.tolist(),
        "landmarks": len(data.landmark_subjects),
        "measurements_replayed": {
            "robot": int(rp.is_robot.sum()),
            "landmark": int((~rp.is_robot).sum()),
        },
        **info,
        "zones": {
            kind: [{"center": list(z.center), "radius": z.radius, "peak": z.peak} for z in disc]
            for kind, disc in zones.items()
        },
    }
    truth = (rp.time, rp.truth, rp.valid, data.robot_subjects, data.landmark_xy.copy())
    sightings = {"step": rp.step, "i": rp.obs, "j": rp.target, "attacked": rp.attacked}
    return MRCLAMResult(config, info, *truth, zones, estimators, wall, sightings)


def landmark_states(data: MRCLAMDataset) -> tuple[np.ndarray, np.ndarray]:
    """Landmarks as fixed neighbours: poses ``(L, 3)`` ``(x, y, 0)`` and covariances
    ``(L, 3, 3)`` from the ground-truth standard deviations (floored at 0.1 mm)."""
    L = len(data.landmark_subjects)
    x = np.zeros((L, 3))
    x[:, :2] = data.landmark_xy
    P = np.zeros((L, 3, 3))
    P[:, 0, 0] = np.maximum(data.landmark_std[:, 0], 1e-4) ** 2
    P[:, 1, 1] = np.maximum(data.landmark_std[:, 1], 1e-4) ** 2
    P[:, 2, 2] = 1e-6
    return x, P


@dataclasses.dataclass
class ReplayLog:
    """What one estimator made of a replay.

    Attributes
    ----------
    track : ndarray, shape (K + 1, N, 3)
        Estimates at the step times (``nan`` after a divergence).
    cov : ndarray, shape (K + 1, N, 3, 3)
    links : dict of str to ndarray, each shape (M,)
        Per-sighting outcomes (:func:`~resloc.experiments.mrclam.scoring.empty_link_log`).
    """

    track: np.ndarray
    cov: np.ndarray
    links: dict[str, np.ndarray]


class ReplaySteps:
    """The steps of ``rp`` and the logs of the estimators named ``names``.

    Parameters
    ----------
    rp : Replay
    config : MRCLAMConfig
    names : sequence of str
    x0, P0 : ndarray, shapes (N, 3), (N, 3, 3)
        Initial estimates (the first entries of the tracks).
    """

    def __init__(self, rp: Replay, config: MRCLAMConfig, names, x0, P0) -> None:
        self.rp = rp
        self.robots = rp.dataset.n_robots
        params = config.cl_params()
        # Landmark sightings skip the trigger; each part memoizes its parameters per level.
        self.landmark_params = (dataclasses.replace(params, trigger=False), {})
        self.robot_params = (params, {})
        self.landmarks = landmark_states(rp.dataset)
        self.level = range_noise_level(rp.z[:, 0], config)
        self.lambda2 = np.full(self.robots, float(self.robots))
        K, M = rp.steps, len(rp.step)
        self.logs = {}
        for name in names:
            log = ReplayLog(np.empty((K + 1, *x0.shape)), np.empty((K + 1, *P0.shape)), {})
            log.track[0], log.cov[0], log.links = x0, P0, empty_link_log(M)
            self.logs[name] = log

    def steps(self) -> Iterator[Step]:
        rp = self.rp
        for k in range(1, rp.steps + 1):
            lo, hi = rp.bounds[k], rp.bounds[k + 1]
            groups = []
            if hi > lo:
                n_lm = int(np.count_nonzero(~rp.is_robot[lo:hi]))  # landmark rows come first
                groups += self._groups(np.arange(lo, lo + n_lm), self.landmark_params, True)
                groups += self._groups(np.arange(lo + n_lm, hi), self.robot_params, False)
            yield Step(k - 1, rp.u[k - 1], groups, rp.risk_s[k], rp.risk_c[k], self.lambda2)

    def _groups(self, rows: np.ndarray, part: tuple, landmark: bool) -> list[LinkGroup]:
        """Sightings ``rows`` in one group per range-noise level."""
        rp, (base, cache) = self.rp, part
        groups = []
        for at, params in level_groups(self.level[rows], base, cache):
            sub = rows[at]
            j = rp.target[sub]
            fixed = None
            if landmark:
                x_lm, P_lm = self.landmarks
                fixed = (x_lm[j - self.robots], P_lm[j - self.robots])
            ok = rp.channel_ok[sub]
            groups.append(LinkGroup(rp.obs[sub], j, rp.z[sub], ok, params, fixed, rows=sub))
        return groups

    def record(self, est: EstimatorState, step: Step) -> None:
        log, k = self.logs[est.name], step.k + 1
        if est.diverged is not None:  # stopped: no estimate, no link outcomes from here on
            log.track[k], log.cov[k] = np.nan, np.nan
            return
        log.track[k], log.cov[k] = est.x, est.P
        # Dead reckoning fuses nothing: no outcomes, its sightings stay unused.
        for group, out in zip(step.groups, est.outcomes, strict=False):
            for name in LINK_OUTCOMES:
                log.links[name][group.rows] = getattr(out, name)

    def stop_at_invalid_covariance(self, est: EstimatorState, dt: float) -> None:
        """Stop ``est`` where one of its logged covariances is not positive definite.

        A sigma-point prediction with a negative weight can leave a covariance indefinite
        without any computation failing; its NEES is then undefined. The estimator is
        reported diverged from that step on, as a failure inside its step would be
        (checked once over the whole log: a per-step test would cost more than the step).
        """
        log = self.logs[est.name]
        with np.errstate(invalid="ignore"):  # a stopped estimator's covariances are nan
            pd = covariance_is_pd(log.cov.reshape(-1, 3, 3))
        ok = pd.reshape(log.cov.shape[:2]).all(axis=1)
        k = int(np.argmin(ok))  # the estimate after step k (1-based) is the first invalid one
        if ok[k] or (est.diverged is not None and est.diverged["step"] <= k):
            return  # valid, or blank from where the estimator stopped
        reason = "a covariance is no longer positive definite"
        est.diverged = divergence(k - 1, dt, self.robots, log.cov[k], reason)
        log.track[k:], log.cov[k:] = np.nan, np.nan
        later = self.rp.step >= k
        for name, blank in zip(LINK_OUTCOMES, empty_link_log(1).values(), strict=True):
            log.links[name][later] = blank[0]
