"""Writing a finished replay: ``summary.json``, CSV tables, the recording and figures."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from resloc.experiments.mrclam.scoring import MRCLAMResult

__all__ = ["save_mrclam"]


def save_mrclam(
    result: MRCLAMResult, out: str | Path, plots: bool = True, sample_period: float = 0.2
) -> list[Path]:
    """Write a replay's results into directory ``out`` (created if needed).

    Files: ``summary.json`` (configuration, data description, overall and per-robot
    statistics), ``per_robot.csv`` (one row per estimator and robot, plus ``all``),
    ``timeseries.csv`` (per ``sample_period``: time, robot, true and estimated poses and
    errors), ``recording.npz`` (every step, for ``resloc export``) and, with matplotlib,
    ``trajectories.png`` and ``errors.png``.

    Returns
    -------
    list of Path
    """
    from resloc.experiments.run_files import write_json

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    p = out / "summary.json"
    write_json(
        p,
        {
            "config": result.config.to_dict(),
            "info": result.info,
            "wall_time_s": result.wall_time,
            "overall": result.summary(),
            "diverged": {n: e.diverged for n, e in result.estimators.items() if e.diverged},
            "per_robot": {"robots": result.robots.tolist(), **result.per_robot()},
        },
    )
    written.append(p)

    p = out / "per_robot.csv"
    keys = list(next(iter(result.estimators.values())).per_robot)
    with p.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["estimator", "robot", *keys])
        for name, est in result.estimators.items():
            for r, subject in enumerate(result.robots):
                w.writerow([name, int(subject), *(f"{est.per_robot[k][r]:.6g}" for k in keys)])
            w.writerow([name, "all", *(_fmt_overall(est.overall.get(k)) for k in keys)])
    written.append(p)

    p = out / "timeseries.csv"
    stride = max(round(sample_period / result.config.dt), 1)
    idx = np.arange(0, len(result.time), stride)
    names = list(result.estimators)
    with p.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        header = ["time_s", "robot", "valid", "x_true", "y_true", "theta_true"]
        for n in names:
            header += [f"x_{n}", f"y_{n}", f"theta_{n}", f"pos_err_{n}", f"nees_{n}"]
        w.writerow(header)
        for k in idx:
            for r, subject in enumerate(result.robots):
                row = [f"{result.time[k]:.3f}", int(subject), int(result.valid[k, r])]
                row += [f"{v:.4f}" for v in result.truth[k, r]]
                for n in names:
                    e = result.estimators[n]
                    row += [f"{v:.4f}" for v in e.track[k, r]]
                    row += [f"{e.pos_err[k, r]:.4f}", f"{e.nees[k, r]:.4g}"]
                w.writerow(row)
    written.append(p)
    from resloc.experiments.recording import RECORDING_FILE, recording_from_mrclam

    written.append(recording_from_mrclam(result).save(out / RECORDING_FILE))
    if plots:  # a figure that cannot be drawn is skipped with a warning, the data stay
        from resloc.experiments.plots import plot_mrclam_errors, plot_mrclam_trajectories
        from resloc.experiments.run_files import draw_plots

        figures = ((plot_mrclam_trajectories, "trajectories"), (plot_mrclam_errors, "errors"))
        for draw, name in figures:
            written += draw_plots(
                lambda d=draw, n=name: [d(result, out / f"{n}.png")], what=f"{name}.png"
            )
    return written


def _fmt_overall(v) -> str:
    if v is None:
        return ""
    return f"{v:.6g}"
