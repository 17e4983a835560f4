"""``run_mrclam``: a dataset through dead reckoning and the configured filters, in the one
estimator loop of the simulator (:func:`~resloc.experiments.lockstep.run_lockstep`), scored
against the ground truth."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from resloc.cl.fusion_methods import fusion_strategy
from resloc.datasets.mrclam import MRCLAMDataset, load_mrclam
from resloc.experiments.lockstep import DEAD_RECKONING, Estimation, EstimatorState, run_lockstep
from resloc.experiments.mrclam.config import MRCLAMConfig
from resloc.experiments.mrclam.replay import Replay, prepare_replay
from resloc.experiments.mrclam.scoring import MRCLAMEstimate, MRCLAMResult, score_estimate
from resloc.experiments.mrclam.steps import ReplaySteps
from resloc.filters.base import FilterKind, make_filter

__all__ = ["replay_result", "run_mrclam"]


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
    return MRCLAMResult(
        config,
        info,
        rp.time,
        rp.truth,
        rp.valid,
        data.robot_subjects,
        data.landmark_xy.copy(),
        zones,
        estimators,
        wall,
        {"step": rp.step, "i": rp.obs, "j": rp.target, "attacked": rp.attacked},
    )
