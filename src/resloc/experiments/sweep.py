"""Parameter sweeps: points (one or several parameters, grid or zip) x seeds x filters, run
as cells on the study executor, summarized per point and written as one tidy table.

The sweep file format is in :mod:`resloc.experiments.sweepfile`. Seeds are the Monte Carlo
dimension: point ``p``, seed ``t`` is trial ``t`` of ``run.seed`` (every point uses the same
random streams for the same seed). Every ``(point, seed, filter)`` is a cell of the result
store (:mod:`resloc.experiments.cells`), so a repeated or interrupted sweep computes only
the cells it does not have.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from resloc.experiments.cells import group_data, run_scenarios
from resloc.experiments.executor import CellFailure, Study
from resloc.experiments.runner import DEAD_RECKONING, RunResult
from resloc.experiments.stats import Estimate, mean_ci
from resloc.experiments.store import canonical_json
from resloc.experiments.sweepfile import (
    METRICS,
    SweepSpec,
    apply_parameter,
    dump_minimal,
    dump_sweep,
    load_sweep,
    parse_sweep,
)

__all__ = [
    "METRICS",
    "TIDY_COLUMNS",
    "SweepResult",
    "SweepSpec",
    "apply_parameter",
    "dump_minimal",
    "dump_sweep",
    "load_sweep",
    "parse_sweep",
    "run_scenarios",
    "run_sweep",
    "save_sweep",
    "tidy_rows",
]

ProgressFn = Any
#: Columns of the tidy table after the point index and the parameters.
TIDY_COLUMNS = ("seed", "trial", "estimator", "status", *METRICS, "error")


@dataclass
class SweepResult:
    """A finished sweep: one :class:`RunResult` per point, all with the same seeds.

    Attributes
    ----------
    spec : SweepSpec
        As run (``run.trials`` = seeds, ``run.steps``).
    runs : list of RunResult or None
        ``runs[k]`` is the point ``spec.values[k]``; ``None`` when one of its cells failed.
    wall_time : float
        Seconds: elapsed for :func:`run_sweep`; within a reproduction, the sum of the
        simulation times of its points (shared points count in every experiment using them).
    meta : dict
        ``jobs`` and the study's statistics (cells from the store, computed, failed).
    failures : list of CellFailure
        Each failed cell with its scenario and traceback.
    """

    spec: SweepSpec
    runs: list[RunResult | None]
    wall_time: float = 0.0
    meta: dict = field(default_factory=dict)
    failures: list[CellFailure] = field(default_factory=list)

    @property
    def filters(self) -> list[str]:
        """The filters every point ran."""
        return list(self.spec.base.run.filters)

    @property
    def seeds(self) -> int:
        """Seeds (Monte Carlo trials) per point."""
        return self.spec.base.run.trials

    def per_trial(self, estimator: str, metric: str | None = None) -> np.ndarray:
        """Per-seed values, shape ``(len(values), seeds)`` (``nan`` rows for failed points)."""
        metric = metric or self.spec.metric
        return np.stack(
            [
                r.estimators[estimator].per_trial(metric)
                if r is not None
                else np.full(self.seeds, np.nan)
                for r in self.runs
            ]
        )

    def estimates(self, estimator: str, metric: str | None = None) -> list[Estimate]:
        """Mean and 95% CI over seeds at every value."""
        return [mean_ci(row) for row in self.per_trial(estimator, metric)]

    def to_dict(self) -> dict:
        """Plain mapping for JSON: every point, filter and metric (mean, CI, per seed)."""
        points = []
        for v, run in zip(self.spec.values, self.runs, strict=True):
            value = list(v) if isinstance(v, tuple) else v
            if run is None:
                points.append({"value": value, "failed": True})
                continue
            est = {}
            for name, e in run.estimators.items():
                est[name] = {
                    m: {**mean_ci(e.per_trial(m)).to_dict(), "per_seed": e.per_trial(m)}
                    for m in METRICS
                    if not (name == DEAD_RECKONING and m == "comm_rate")
                }
            points.append({"value": value, "estimators": est})
        return {
            "name": self.spec.name,
            "parameter": self.spec.parameter
            if isinstance(self.spec.parameter, str)
            else list(self.spec.parameter),
            "values": [list(v) if isinstance(v, tuple) else v for v in self.spec.values],
            "metric": self.spec.metric,
            "seeds": self.seeds,
            "base_seed": self.spec.base.run.seed,
            "steps": self.spec.base.run.steps,
            "filters": self.filters,
            "wall_time_s": self.wall_time,
            "study": self.meta.get("study", {}),
            "failed_cells": len(self.failures),
            "points": points,
        }


def run_sweep(
    spec: SweepSpec,
    seeds: int | None = None,
    steps: int | None = None,
    jobs: int | None = 1,
    progress: ProgressFn | None = None,
    study: Study | None = None,
) -> SweepResult:
    """Run every point of ``spec`` over ``seeds`` seeds and its filters.

    Parameters
    ----------
    spec : SweepSpec
    seeds : int, optional
        Override ``run.trials`` (seeds ``run.seed``'s trials ``0 .. seeds - 1``).
    steps : int, optional
        Override ``run.steps``.
    jobs : int, optional
        Worker processes when no ``study`` is given.
    progress : callable(done, total), optional
        Over cells, when no ``study`` is given.
    study : Study, optional
        Backend (embedded or external Dask cluster), result store and progress.

    Returns
    -------
    SweepResult
        A failed cell does not stop the sweep: its point's run is ``None`` and the failure
        (scenario, traceback) is in ``failures``.
    """
    t0 = time.perf_counter()
    spec = spec.with_run(seeds, steps)
    scenarios = spec.scenarios()  # every point validated before any work
    study = study if study is not None else Study(jobs=jobs, progress=progress)
    runs = run_scenarios(scenarios, study=study, allow_failures=True)
    meta = {"jobs": study.stats.workers, "study": study.stats.to_dict()}
    return SweepResult(spec, runs, time.perf_counter() - t0, meta, list(study.failures))


def tidy_rows(result: SweepResult) -> tuple[list[str], list[list[Any]]]:
    """One row per (point, seed, estimator): the point's parameters, the seed, the status
    and every per-seed metric (``nan`` for dead reckoning's communication rate).

    Returns
    -------
    columns : list of str
        ``point``, each parameter, then :data:`TIDY_COLUMNS`.
    rows : list of list
    """
    spec = result.spec
    columns = ["point", *spec.parameters, *TIDY_COLUMNS]
    names = [*result.filters, *([DEAD_RECKONING] if spec.base.run.dead_reckoning else [])]
    failed = _failed_points(result)
    rows: list[list[Any]] = []
    for k, (v, run) in enumerate(zip(spec.values, result.runs, strict=True)):
        params = list(spec.assignments(v).values())
        for name in names:
            per = {m: run.estimators[name].per_trial(m) for m in METRICS} if run else None
            for t in range(result.seeds):
                head = [k, *params, spec.base.run.seed, t, name]
                if per is None:
                    rows.append([*head, "failed", *([math.nan] * len(METRICS)), failed.get(k)])
                    continue
                values = [
                    math.nan if name == DEAD_RECKONING and m == "comm_rate" else float(per[m][t])
                    for m in METRICS
                ]
                rows.append([*head, "ok", *values, ""])
    return columns, rows


def _failed_points(result: SweepResult) -> dict[int, str]:
    """Point index -> the first error among its failed cells."""
    errors: dict[str, str] = {}
    for f in result.failures:
        errors.setdefault(canonical_json(f.context.get("scenario")), f.error)
    scenarios = result.spec.scenarios()
    return {
        k: errors.get(canonical_json(group_data(scenarios[k])), "failed")
        for k, run in enumerate(result.runs)
        if run is None
    }


def _write_tidy(result: SweepResult, out: Path) -> list[Path]:
    """``cells.csv`` always, ``cells.parquet`` when pyarrow is installed."""
    import csv

    columns, rows = tidy_rows(result)
    written = []
    p = out / "cells.csv"
    with p.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(columns)
        for row in rows:
            w.writerow(["" if isinstance(x, float) and math.isnan(x) else x for x in row])
    written.append(p)
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return written
    table = pa.table(
        {c: [_parquet_value(r[j]) for r in rows] for j, c in enumerate(columns)}
        if rows
        else {c: pa.array([], pa.string()) for c in columns}
    )
    p = out / "cells.parquet"
    pq.write_table(table, p)
    written.append(p)
    return written


def _parquet_value(v: Any) -> Any:
    return None if isinstance(v, float) and math.isnan(v) else v


def save_sweep(result: SweepResult, out: Path, plots: bool = True) -> list[Path]:
    """Write a :class:`SweepResult` into directory ``out``.

    Files: ``sweep.toml`` (re-runnable), ``summary.json`` (every point, filter and metric:
    mean, 95% CI, per-seed values), ``cells.csv`` / ``cells.parquet`` (the tidy table: one
    row per point, seed and estimator, see :func:`tidy_rows`), ``sweep.csv`` (one row per
    point and filter: mean and CI), ``failures.json`` (failed cells: scenario, error,
    traceback; only when some failed) and, with plots, ``sweep.png`` (metric against the
    point, 95% CI bars), ``msle_time.png`` (MSLE over time per point, 95% bands) and
    ``transmissions_<k>.png`` (robot x time raster of seed 0 per point, titled with the
    average communication rate).
    """
    from resloc.experiments.run_files import write_json

    out = Path(out)
    spec = result.spec
    written = []
    p = out / "sweep.toml"
    p.write_text(dump_sweep(spec), encoding="utf-8")
    written.append(p)
    p = out / "summary.json"
    write_json(p, result.to_dict())
    written.append(p)
    written += _write_tidy(result, out)
    p = out / "sweep.csv"
    rows = ["value,estimator," + ",".join(f"{m},{m}_ci95" for m in METRICS)]
    for v, run in zip(spec.values, result.runs, strict=True):
        if run is None:
            continue
        for name, e in run.estimators.items():
            cells = []
            for m in METRICS:
                est = mean_ci(e.per_trial(m))
                cells += [f"{est.mean:.6g}", f"{est.half:.6g}"]
            label = spec.label(v)
            label = f'"{label}"' if "," in label else label
            rows.append(f"{label},{name}," + ",".join(cells))
    p.write_text("\n".join(rows) + "\n", encoding="utf-8")
    written.append(p)
    if result.failures:
        p = out / "failures.json"
        write_json(p, [f.to_dict() for f in result.failures])
        written.append(p)
    if plots:
        written += _plots(result, out)
    return written


def _plots(result: SweepResult, out: Path) -> list[Path]:
    from resloc.experiments import report as figures

    spec = result.spec
    label = spec.axis_label
    x = list(spec.values) if spec.numeric else [spec.label(v) for v in spec.values]
    written = [
        figures.errorbar_figure(
            out / "sweep.png",
            x,
            {f: result.estimates(f) for f in result.filters},
            xlabel=label,
            ylabel=figures.METRIC_LABELS.get(spec.metric, spec.metric),
            title=f"{spec.name}\n({result.seeds} seeds, mean and 95% CI)",
            logy=spec.metric.startswith("msle"),
        )
    ]
    first = result.filters[0] if result.filters else DEAD_RECKONING
    done = [(v, run) for v, run in zip(spec.values, result.runs, strict=True) if run is not None]
    if not done:
        return written
    curves = [
        figures.Curve(
            spec.label(v) if not isinstance(spec.parameter, str) else f"{label} = {spec.label(v)}",
            run.time,
            run.estimators[first].series["msle"],
        )
        for v, run in done
    ]
    written.append(
        figures.band_figure(
            out / "msle_time.png",
            curves,
            title=f"{spec.name}: {first.upper()} MSLE\n(mean and 95% CI, {result.seeds} seeds)",
        )
    )
    if result.filters:
        for k, (v, run) in enumerate(zip(spec.values, result.runs, strict=True)):
            if run is None:
                continue
            e = run.estimators[first]
            cr = mean_ci(e.per_trial("comm_rate"))
            written.append(
                figures.raster_figure(
                    out / f"transmissions_{k}.png",
                    e.raster,
                    run.time,
                    f"{first.upper()} transmissions, {label} = {spec.label(v)}\n"
                    f"(average communication rate = {_rate_text(cr)})",
                    e.links,
                )
            )
    return written


def _rate_text(est: Estimate) -> str:
    if not math.isfinite(est.mean):
        return "-"
    return est.format(".3f")
