"""Writing results: an output directory appears complete or not at all."""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from resloc.errors import ConfigError

__all__ = ["atomic_output_dir", "check_output_dir", "save_run", "write_json"]


def check_output_dir(out: Path, overwrite: bool = False) -> None:
    """Refuse an existing, non-empty output directory unless ``overwrite`` (before any work)."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: exists and is not a directory; choose another path")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise ConfigError(
            f"--out {out}: directory exists and is not empty; choose another or pass --overwrite"
        )


@contextlib.contextmanager
def atomic_output_dir(out: Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling directory; on success it replaces ``out`` in one rename.

    On any exception the temporary directory is removed and ``out`` is left untouched, so
    nothing half-written is ever visible at ``out``.
    """
    out = Path(out)
    check_output_dir(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    umask = os.umask(0)
    os.umask(umask)
    tmp.chmod(0o777 & ~umask)  # mkdtemp creates 0700; give the usual directory mode
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        out.rename(old)
    tmp.rename(out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


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


def save_run(result, out: Path, plots: bool = True) -> list[Path]:
    """Write a :class:`~resloc.experiments.runner.RunResult` into directory ``out``.

    Files: ``scenario.toml`` (resolved, re-runnable), ``summary.json``, ``timeseries.csv``
    (per step and estimator: means over trials), ``transmissions_<filter>.csv`` (robot x
    step raster of trial 0), ``trajectories.csv`` (trial 0, truth and estimates),
    ``recording.npz`` (trial 0 step by step, for ``resloc export``) and, with
    matplotlib, ``trajectories.png``, ``msle.png`` and ``transmissions.png``.

    Returns
    -------
    list of Path
        The files written.
    """
    from resloc.experiments.config import dump_scenario

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
        },
    )
    written.append(p)
    p = out / "timeseries.csv"
    with p.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["step", "time_s", "estimator", "msle", "rmse", "nees", "comm_rate", "detected"])
        for name, est in result.estimators.items():
            s = est.series
            with np.errstate(invalid="ignore", divide="ignore"):
                cr = s["triggered"].sum(axis=1) / s["candidates"].sum(axis=1)
            for k in range(len(result.time)):
                w.writerow(
                    [
                        k + 1,
                        f"{result.time[k]:.4f}",
                        name,
                        f"{np.nanmean(s['msle'][k]):.6g}",
                        f"{np.nanmean(s['rmse'][k]):.6g}",
                        f"{np.nanmean(s['nees'][k]):.6g}",
                        f"{cr[k]:.6g}",
                        int(np.nansum(s["detected"][k])),
                    ]
                )
    written.append(p)
    for name, est in result.estimators.items():
        if name == "dr":
            continue
        p = out / f"transmissions_{name}.csv"
        np.savetxt(p, est.raster.T, fmt="%d", delimiter=",", header="rows: robots, cols: steps")
        written.append(p)
    p = out / "trajectories.csv"
    with p.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["step", "robot", "source", "x", "y", "theta"])
        sources = {"truth": result.truth} | {n: e.track for n, e in result.estimators.items()}
        for src, arr in sources.items():
            for k in range(arr.shape[0]):
                for r in range(arr.shape[1]):
                    x, y, th = arr[k, r]
                    w.writerow([k, r, src, f"{x:.5f}", f"{y:.5f}", f"{th:.5f}"])
    written.append(p)
    from resloc.experiments.recording import RECORDING_FILE, recording_from_run

    written.append(recording_from_run(result).save(out / RECORDING_FILE))
    if plots:
        from resloc.experiments import plots as plotting

        written += plotting.plot_run(result, out)
    return written
