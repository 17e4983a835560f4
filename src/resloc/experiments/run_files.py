"""The files of a result set: strict JSON, CSV written column by column, and a run's files
(:func:`save_run`). Where they are written (a temporary that takes the output directory's
place whole) is :mod:`resloc.experiments.output`'s job."""

from __future__ import annotations

import contextlib
import csv
import io
import itertools
import json
import math
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "csv_field",
    "csv_rows",
    "draw_plots",
    "save_run",
    "warn",
    "write_json",
    "write_timeseries",
    "write_trajectories",
]


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, float | np.floating):
        f = float(v)
        return None if math.isnan(f) or math.isinf(f) else f
    return v


def write_json(path: Path, data: Any) -> None:
    """Write JSON with NaN/inf as ``null`` (strict JSON)."""
    path.write_text(json.dumps(_jsonable(data), indent=2) + "\n", encoding="utf-8")


def warn(message: str) -> None:
    """One ``warning: ...`` line on stderr."""
    print(f"warning: {message}", file=sys.stderr)


def draw_plots(draw, *args, what: str = "figures") -> list[Path]:
    """Call a plotting function; if it fails, warn in one line and return no files.

    Figures are a view of data already written: a figure that cannot be drawn (a
    matplotlib error, a missing font, a backend problem) must not cost the data.
    """
    try:
        return list(draw(*args))
    except Exception as exc:  # any plotting failure is only a warning
        detail = str(exc).splitlines()[0] if str(exc) else ""
        warn(f"{what} skipped ({exc.__class__.__name__}: {detail[:160]}); the data are written")
        return []


def save_run(result, out: Path, plots: bool = True) -> list[Path]:
    """Write a :class:`~resloc.experiments.runner.RunResult` into directory ``out``.

    Files: ``scenario.toml`` (resolved, re-runnable), ``summary.json``, ``timeseries.csv``
    (per step and estimator: means over trials), ``transmissions_<filter>.csv`` (robot x
    step raster of trial 0), ``trajectories.csv`` (trial 0, truth and estimates),
    ``recording.npz`` (trial 0 step by step, for ``resloc export``) and, with
    matplotlib, ``trajectories.png``, ``msle.png`` and ``transmissions.png`` (a figure that
    cannot be drawn is skipped with a warning).

    Returns
    -------
    list of Path
        The files written.
    """
    from resloc.experiments.config_dump import dump_scenario

    out = Path(out)
    written = []
    p = out / "scenario.toml"
    p.write_text(dump_scenario(result.scenario), encoding="utf-8")
    written.append(p)
    p = out / "summary.json"
    write_json(
        p,
        {
            "scenario": result.scenario.run.name,
            "seed": result.scenario.run.seed,
            "trials": result.scenario.run.trials,
            "robots": result.meta.get("robots"),
            "steps": result.scenario.run.steps,
            "wall_time_s": result.wall_time,
            "estimators": result.summary(),
            "diverged": {
                name: est.diverged
                for name, est in result.estimators.items()
                if getattr(est, "diverged", None)
            },
        },
    )
    written.append(p)
    p = out / "timeseries.csv"
    write_timeseries(p, result)
    written.append(p)
    for name, est in result.estimators.items():
        if name == "dr":
            continue
        p = out / f"transmissions_{name}.csv"
        np.savetxt(p, est.raster.T, fmt="%d", delimiter=",", header="rows: robots, cols: steps")
        written.append(p)
    p = out / "trajectories.csv"
    write_trajectories(p, result)
    written.append(p)
    from resloc.experiments.recording import RECORDING_FILE, recording_from_run

    written.append(recording_from_run(result).save(out / RECORDING_FILE))
    if plots:
        from resloc.experiments import plots as plotting

        written += draw_plots(plotting.plot_run, result, out)
    return written


#: The line ending of Python's ``csv`` module, which the files have always used.
CSV_LINE_END = "\r\n"


def csv_field(text: str) -> str:
    """One CSV field as :mod:`csv` writes it (quoted when it holds a comma, a quote or a
    line break)."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator=CSV_LINE_END).writerow([text])
    return buf.getvalue().removesuffix(CSV_LINE_END)


def csv_rows(row_format: str, columns: Sequence[Sequence]) -> str:
    """Rows of CSV text from whole columns, formatted by one ``%`` operation.

    The same bytes as ``csv.writer`` writing one row at a time with each value formatted
    by the matching ``%`` code (Python's float formatting is the same under ``%`` and
    ``format``), at a fraction of the cost: no Python call per row or field.

    Parameters
    ----------
    row_format : str
        One row's ``%`` format without the line ending, e.g. ``"%d,%s,%.5f"``; string
        fields must already be CSV fields (:func:`csv_field`).
    columns : sequence of sequences, each of length ``n``
        The fields, column by column (lists of Python numbers format fastest).

    Returns
    -------
    str
        ``n`` rows, each ending in ``\\r\\n``.
    """
    n = len(columns[0]) if columns else 0
    if n == 0:
        return ""
    values = tuple(itertools.chain.from_iterable(zip(*columns, strict=True)))
    return ((row_format + CSV_LINE_END) * n) % values


TIMESERIES_COLUMNS = (
    "step",
    "time_s",
    "estimator",
    "msle",
    "rmse",
    "nees",
    "comm_rate",
    "detected",
)
TRAJECTORY_COLUMNS = ("step", "robot", "source", "x", "y", "theta")


def write_timeseries(path: Path, result) -> None:
    """``timeseries.csv``: per step and estimator, the means over trials."""
    steps = len(result.time)
    step_numbers = list(range(1, steps + 1))
    times = np.asarray(result.time, float).tolist()
    parts = [",".join(TIMESERIES_COLUMNS) + CSV_LINE_END]
    for name, est in result.estimators.items():
        s = est.series
        with np.errstate(invalid="ignore", divide="ignore"), _quiet_empty_means():
            comm_rate = s["triggered"].sum(axis=1) / s["candidates"].sum(axis=1)
            means = [np.nanmean(s[key], axis=1).tolist() for key in ("msle", "rmse", "nees")]
        detected = np.nansum(s["detected"], axis=1).astype(np.int64).tolist()
        columns = [step_numbers, times, [csv_field(name)] * steps, *means]
        columns += [comm_rate.tolist(), detected]
        parts.append(csv_rows("%d,%.4f,%s,%.6g,%.6g,%.6g,%.6g,%d", columns))
    path.write_text("".join(parts), encoding="utf-8", newline="")


def write_trajectories(path: Path, result) -> None:
    """``trajectories.csv``: trial 0's true and estimated poses, step by step."""
    sources = {"truth": result.truth} | {n: e.track for n, e in result.estimators.items()}
    parts = [",".join(TRAJECTORY_COLUMNS) + CSV_LINE_END]
    for source, poses in sources.items():
        steps, robots = poses.shape[:2]
        rows = steps * robots
        flat = np.asarray(poses, float).reshape(rows, 3)
        columns = [
            np.repeat(np.arange(steps), robots).tolist(),
            np.tile(np.arange(robots), steps).tolist(),
            [csv_field(source)] * rows,
            *(flat[:, c].tolist() for c in range(3)),
        ]
        parts.append(csv_rows("%d,%d,%s,%.5f,%.5f,%.5f", columns))
    path.write_text("".join(parts), encoding="utf-8", newline="")


@contextlib.contextmanager
def _quiet_empty_means() -> Iterator[None]:
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Mean of empty slice", RuntimeWarning)
        yield
