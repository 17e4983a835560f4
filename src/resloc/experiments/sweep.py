"""Parameter sweeps: one scenario parameter varied over a list of values, run over seeds in
parallel worker processes.

A sweep file is a scenario file (same sections, same validation) plus a ``[sweep]`` table::

    [sweep]
    name = "Fig. 5b: detection threshold"
    parameter = "detector.rho"          # a dotted key of the scenario schema
    values = [0.2, 0.3, 0.5, 1.0]
    filters = ["ckf"]                   # optional: run.filters for every point
    metric = "msle_mean"                # optional: the scalar summarized per point
    base = "default"                    # optional: "default" (the embedded scenario) or a
                                        # scenario file relative to this one

    [detector]                          # optional scenario sections, applied over the base
    norm = "euclidean"

Without ``base`` the sections apply over the schema defaults, exactly as in a scenario file
(so a sweep file without ``[[sdz]]``/``[[cdz]]`` has no danger zones). ``parameter`` is any
dotted key of a scenario file (``detector.rho``, ``trigger.alpha``, ``team.robots``,
``attack.links``), or ``zones.<key>`` (every SDZ and CDZ, e.g. ``zones.radius``),
``sdz.<key>`` / ``cdz.<key>`` (every zone of one kind).

Seeds are the Monte Carlo dimension: ``run.trials`` seeds are simulated together in one
batched run per point (trial ``t`` of every point uses the same random streams), and distinct
points run in parallel processes (:func:`run_scenarios`).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import json
import math
import multiprocessing
import os
import queue
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from resloc.errors import ConfigError
from resloc.experiments.config import (
    Scenario,
    _toml_value,
    default_scenario,
    load_scenario,
    parse_scenario,
    read_toml,
    scenario_to_dict,
    set_dotted,
)
from resloc.experiments.runner import DEAD_RECKONING, RunResult, run_scenario
from resloc.experiments.stats import Estimate, mean_ci

__all__ = [
    "METRICS",
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
]

#: Per-seed scalars a sweep can summarize (see ``EstimatorResult.per_trial``).
METRICS = ("msle_mean", "msle_final", "rmse_mean", "rmse_final", "nees_mean", "comm_rate")
_FILTER_ORDER = ("ckf", "ukf", "ekf")
_SWEEP_KEYS = ("name", "parameter", "values", "filters", "metric", "base")
#: Parameters that a sweep may not vary (they are the seeds, or have their own key).
_RESERVED = {
    "run.trials": "seeds are the Monte Carlo dimension; use --seeds",
    "run.seed": "seeds are the Monte Carlo dimension; use --seeds",
    "run.filters": "use sweep.filters",
}

#: Threads per worker process for BLAS/OpenMP (the work is parallel across processes).
_THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "NUMBA_NUM_THREADS",
)

ProgressFn = Callable[[float, float], None]


# --------------------------------------------------------------------------- sweep files
@dataclass(frozen=True)
class SweepSpec:
    """A validated sweep: a base scenario and one parameter varied over values.

    Attributes
    ----------
    name : str
    parameter : str
        Dotted key (see module doc).
    values : tuple
        The values, in order (numbers, strings or booleans).
    base : Scenario
        The scenario every point starts from (``filters`` already applied).
    metric : str
        One of :data:`METRICS`.
    """

    name: str
    parameter: str
    values: tuple
    base: Scenario
    metric: str = "msle_mean"

    def scenario(self, value: Any) -> Scenario:
        """The point ``parameter = value`` (validated)."""
        return apply_parameter(self.base, self.parameter, value)

    def scenarios(self, seeds: int | None = None, steps: int | None = None) -> list[Scenario]:
        """Every point, with ``run.trials = seeds`` and ``run.steps = steps`` when given."""
        spec = self.with_run(seeds, steps)
        return [spec.scenario(v) for v in spec.values]

    def with_run(self, seeds: int | None = None, steps: int | None = None) -> SweepSpec:
        """Copy with the seed count (``run.trials``) and/or ``run.steps`` replaced."""
        changes: dict[str, Any] = {}
        if seeds is not None:
            changes["run.trials"] = int(seeds)
        if steps is not None:
            changes["run.steps"] = int(steps)
        if not changes:
            return self
        return SweepSpec(
            self.name, self.parameter, self.values, self.base.replace(**changes), self.metric
        )

    @property
    def numeric(self) -> bool:
        """True when every value is a number (plots use a numeric axis)."""
        return all(isinstance(v, int | float) and not isinstance(v, bool) for v in self.values)


def apply_parameter(scenario: Scenario, parameter: str, value: Any) -> Scenario:
    """``scenario`` with ``parameter`` set to ``value`` (validated).

    ``zones.<key>`` sets ``key`` in every ``[[sdz]]`` and ``[[cdz]]``; ``sdz.<key>`` and
    ``cdz.<key>`` in every zone of that kind; any other dotted key is a scenario-file key.

    Raises
    ------
    ConfigError
        Unknown key, wrong type or out-of-range value, or zones requested but absent.
    """
    source = f"sweep {parameter} = {value!r}"
    data = scenario_to_dict(scenario)
    head, _, key = parameter.partition(".")
    if head in ("zones", "sdz", "cdz"):
        if not key or "." in key:
            raise ConfigError(
                f"{source}: use zones.<key>, sdz.<key> or cdz.<key> (e.g. zones.radius)"
            )
        kinds = ("sdz", "cdz") if head == "zones" else (head,)
        zones = [z for kind in kinds for z in data.get(kind, [])]
        if not zones:
            raise ConfigError(
                f"{source}: the scenario has no {' or '.join(f'[[{k}]]' for k in kinds)} "
                "zones to change"
            )
        for z in zones:
            z[key] = value
    else:
        set_dotted(data, parameter, value)
    return parse_scenario(data, source=source)


def _merge(base: dict, over: dict) -> dict:
    """Scenario mapping ``over`` applied on ``base`` (tables merged, zone arrays replaced)."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = {**out[k], **v}
        else:
            out[k] = v
    return out


def parse_sweep(data: dict, source: str = "sweep", base_dir: Path | None = None) -> SweepSpec:
    """Validate a sweep mapping (as read from TOML) into a :class:`SweepSpec`.

    Every value is applied once here, so a bad value fails before any work.

    Raises
    ------
    ConfigError
        One line naming ``source``, the field and the fix.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a TOML document")
    sweep = data.get("sweep")
    if sweep is None:
        raise ConfigError(
            f"{source}: no [sweep] table; a sweep file needs [sweep] with parameter and values "
            "(for a plain scenario use `resloc run`)"
        )
    if not isinstance(sweep, dict):
        raise ConfigError(f"{source}: sweep: expected a table, got {sweep!r}")
    for key in sweep:
        if key not in _SWEEP_KEYS:
            raise ConfigError(
                f"{source}: sweep.{key}: unknown key; known keys here: {', '.join(_SWEEP_KEYS)}"
            )
    parameter = sweep.get("parameter")
    if not isinstance(parameter, str) or not parameter:
        raise ConfigError(
            f'{source}: sweep.parameter: expected a dotted key such as "detector.rho", '
            f"got {parameter!r}"
        )
    if parameter in _RESERVED:
        raise ConfigError(
            f"{source}: sweep.parameter: {parameter} cannot be swept; {_RESERVED[parameter]}"
        )
    values = sweep.get("values")
    if not isinstance(values, list) or not values:
        raise ConfigError(f"{source}: sweep.values: expected a non-empty array, got {values!r}")
    for k, v in enumerate(values):
        if isinstance(v, list | dict):
            raise ConfigError(
                f"{source}: sweep.values[{k}]: expected a number, string or boolean, got {v!r}"
            )
    if len({json.dumps(v) for v in values}) != len(values):
        raise ConfigError(f"{source}: sweep.values: {values!r} lists a value twice")
    metric = sweep.get("metric", "msle_mean")
    if metric not in METRICS:
        raise ConfigError(f"{source}: sweep.metric: {metric!r} is not one of {', '.join(METRICS)}")
    name = sweep.get("name", f"sweep of {parameter}")
    if not isinstance(name, str):
        raise ConfigError(f"{source}: sweep.name: expected a string, got {name!r}")

    sections = {k: v for k, v in data.items() if k != "sweep"}
    base_ref = sweep.get("base")
    if base_ref is None:
        base_data: dict = {}
    elif base_ref == "default":
        base_data = scenario_to_dict(default_scenario())
    elif isinstance(base_ref, str):
        p = Path(base_ref)
        if not p.is_absolute() and base_dir is not None:
            p = base_dir / p
        try:
            base_data = scenario_to_dict(load_scenario(p))
        except ConfigError as exc:
            raise ConfigError(f"{source}: sweep.base: {exc}") from None
    else:
        raise ConfigError(
            f'{source}: sweep.base: expected "default" or a scenario file path, got {base_ref!r}'
        )
    filters = sweep.get("filters")
    if filters is not None:
        if not isinstance(filters, list):
            raise ConfigError(f"{source}: sweep.filters: expected an array, got {filters!r}")
        sections = _merge(sections, {"run": {**sections.get("run", {}), "filters": filters}})
    merged = _merge(base_data, sections)
    try:
        base = parse_scenario(merged, source="scenario")
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    spec = SweepSpec(name, parameter, tuple(values), base, metric)
    for k, v in enumerate(values):
        try:
            spec.scenario(v)
        except ConfigError as exc:
            raise ConfigError(f"{source}: sweep.values[{k}]: {exc}") from None
    return spec


def load_sweep(path: str | Path) -> SweepSpec:
    """Read and validate a sweep TOML file (see module doc).

    Raises
    ------
    ConfigError
        Missing file, TOML syntax error, or invalid content (one line, names the field).
    """
    p = Path(path)
    data = read_toml(p, "sweep")
    return parse_sweep(data, source=str(p), base_dir=p.parent)


def dump_minimal(scenario: Scenario) -> str:
    """TOML of only what differs from the schema defaults (zones in full).

    Loading the text with :func:`~resloc.experiments.config.load_scenario` gives back
    ``scenario``; a short file states exactly what an experiment changes.
    """
    ref = scenario_to_dict(Scenario())
    data = scenario_to_dict(scenario)
    lines: list[str] = []
    for section, values in data.items():
        if section in ("sdz", "cdz"):
            continue
        diff = {k: v for k, v in values.items() if ref[section].get(k) != v}
        if diff:
            lines.append(f"[{section}]")
            lines += [f"{k} = {_toml_value(v)}" for k, v in diff.items()]
            lines.append("")
    zone_ref = scenario_to_dict(Scenario(world=_one_zone_world()))["sdz"][0]
    for section in ("sdz", "cdz"):
        for zone in data.get(section, []):
            lines.append(f"[[{section}]]")
            lines += [
                f"{k} = {_toml_value(v)}"
                for k, v in zone.items()
                if k in ("center", "radius") or zone_ref.get(k) != v
            ]
            lines.append("")
    return "\n".join(lines)


def _one_zone_world():
    from resloc.world.spec import WorldSpec, ZoneSpec

    return WorldSpec(sdz=(ZoneSpec(),))


def dump_sweep(spec: SweepSpec) -> str:
    """A sweep file for ``spec`` (``[sweep]`` plus the base scenario's non-default values);
    :func:`load_sweep` reads it back to an equal spec."""
    head = [
        "[sweep]",
        f"name = {_toml_value(spec.name)}",
        f"parameter = {_toml_value(spec.parameter)}",
        f"values = {_toml_value(list(spec.values))}",
        f"filters = {_toml_value(list(spec.base.run.filters))}",
    ]
    if spec.metric != "msle_mean":
        head.append(f"metric = {_toml_value(spec.metric)}")
    base = spec.base.replace(**{"run.filters": list(Scenario().run.filters)})
    return "\n".join(head) + "\n\n" + dump_minimal(base)


# --------------------------------------------------------------------------- parallel runs
def _dedupe_key(s: Scenario) -> str:
    data = scenario_to_dict(s)
    for k in ("filters", "name", "dead_reckoning"):
        data["run"].pop(k)
    return json.dumps(data, sort_keys=True)


def _cost(s: Scenario) -> float:
    """Relative cost of a run: robots x trials x steps x (filters + world overhead)."""
    r = s.run
    return float(s.world.team.robots * r.trials * r.steps * (len(r.filters) + 0.2))


_WORKER_QUEUE: Any = None


def _init_worker(q) -> None:
    global _WORKER_QUEUE
    _WORKER_QUEUE = q


def _run_job(index: int, scenario: Scenario) -> tuple[int, RunResult]:
    """Worker: run one scenario, reporting progress through the queue every ~2% of steps."""
    every = max(1, scenario.run.steps // 50)
    q = _WORKER_QUEUE

    def progress(k: int, steps: int) -> None:
        if q is not None and (k % every == 0 or k == steps):
            q.put((index, k))

    return index, run_scenario(scenario, progress=progress)


@contextlib.contextmanager
def _single_threaded_children() -> Iterator[None]:
    """Make spawned workers start with one BLAS/OpenMP thread each (restored afterwards)."""
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: "1" for k in _THREAD_VARS})
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def run_scenarios(
    scenarios: list[Scenario], jobs: int = 1, progress: ProgressFn | None = None
) -> list[RunResult]:
    """Run several scenarios, in parallel processes, and return their results in order.

    Scenarios that differ only in ``run.filters`` / ``run.name`` / ``run.dead_reckoning`` are
    simulated once with the union of their filters (the world does not depend on the
    filters, so each filter's result is the same as in a separate run). Runs are handed to
    ``jobs`` worker processes longest first; each worker uses one BLAS thread.

    Parameters
    ----------
    scenarios : list of Scenario
    jobs : int
        Worker processes (``1``: run in this process).
    progress : callable(done, total), optional
        Called as work completes (units: robot-steps weighted by filters).

    Returns
    -------
    list of RunResult
        One per scenario; its ``estimators`` hold exactly the scenario's filters (plus
        ``dr`` when it asks for dead reckoning).
    """
    groups: dict[str, list[int]] = {}
    for k, s in enumerate(scenarios):
        groups.setdefault(_dedupe_key(s), []).append(k)
    unique: list[Scenario] = []
    for members in groups.values():
        wanted = {f for k in members for f in scenarios[k].run.filters}
        filters = [f for f in _FILTER_ORDER if f in wanted]
        dr = any(scenarios[k].run.dead_reckoning for k in members)
        unique.append(
            scenarios[members[0]].replace(**{"run.filters": filters, "run.dead_reckoning": dr})
        )
    costs = [_cost(s) for s in unique]
    total = float(sum(costs))
    done = [0.0] * len(unique)

    def report(index: int, k: int) -> None:
        done[index] = costs[index] * k / unique[index].run.steps
        if progress is not None:
            progress(sum(done), total)

    order = sorted(range(len(unique)), key=lambda i: -costs[i])
    results: list[RunResult | None] = [None] * len(unique)
    jobs = max(1, min(int(jobs), len(unique)))
    if progress is not None:
        progress(0.0, total)
    if jobs == 1:
        for i in order:
            every = max(1, unique[i].run.steps // 200)
            results[i] = run_scenario(
                unique[i],
                progress=lambda k, n, i=i, e=every: report(i, k) if k % e == 0 or k == n else None,
            )
    else:
        _warm_up_kernels()
        ctx = multiprocessing.get_context("spawn")
        with _single_threaded_children():
            q = ctx.Queue()
            pool = cf.ProcessPoolExecutor(
                max_workers=jobs, mp_context=ctx, initializer=_init_worker, initargs=(q,)
            )
            try:
                pending = {pool.submit(_run_job, i, unique[i]) for i in order}
                while pending:
                    finished, pending = cf.wait(
                        pending, timeout=0.25, return_when=cf.FIRST_COMPLETED
                    )
                    _drain(q, report)
                    for fut in finished:
                        i, res = fut.result()
                        results[i] = res
                        report(i, unique[i].run.steps)
            except BaseException:
                pool.shutdown(wait=False, cancel_futures=True)
                for proc in list(getattr(pool, "_processes", {}).values()):
                    proc.terminate()
                raise
            pool.shutdown(wait=True)
            q.close()
    out: list[RunResult] = []
    by_scenario: dict[int, int] = {}
    for u, members in enumerate(groups.values()):
        for k in members:
            by_scenario[k] = u
    for k, s in enumerate(scenarios):
        res = results[by_scenario[k]]
        assert res is not None
        keep = [*s.run.filters, *([DEAD_RECKONING] if s.run.dead_reckoning else [])]
        out.append(
            RunResult(
                s,
                {name: res.estimators[name] for name in keep},
                res.truth,
                res.time,
                res.wall_time,
                dict(res.meta),
            )
        )
    return out


def _warm_up_kernels() -> None:
    """Compile the optional compiled kernels once, here, so that every worker process loads
    them from the on-disk cache instead of compiling them again in parallel."""
    try:
        from resloc.cl import kernels
    except ImportError:  # pragma: no cover - the kernels module is optional
        return
    warm = getattr(kernels, "warm_up", None)
    if warm is not None:
        warm()


def _drain(q, report: Callable[[int, int], None]) -> None:
    while True:
        try:
            index, k = q.get_nowait()
        except queue.Empty:
            return
        report(index, k)


# --------------------------------------------------------------------------- results
@dataclass
class SweepResult:
    """A finished sweep: one :class:`RunResult` per value, all with the same seeds.

    Attributes
    ----------
    spec : SweepSpec
        As run (``run.trials`` = seeds, ``run.steps``).
    runs : list of RunResult
        ``runs[k]`` is the point ``spec.values[k]``.
    wall_time : float
        Seconds: elapsed for :func:`run_sweep`; within a reproduction, the sum of the
        simulation times of its points (shared points count in every experiment using them).
    """

    spec: SweepSpec
    runs: list[RunResult]
    wall_time: float = 0.0
    meta: dict = field(default_factory=dict)

    @property
    def filters(self) -> list[str]:
        """The filters every point ran."""
        return list(self.spec.base.run.filters)

    @property
    def seeds(self) -> int:
        """Seeds (Monte Carlo trials) per point."""
        return self.spec.base.run.trials

    def per_trial(self, estimator: str, metric: str | None = None) -> np.ndarray:
        """Per-seed values, shape ``(len(values), seeds)``."""
        metric = metric or self.spec.metric
        return np.stack([r.estimators[estimator].per_trial(metric) for r in self.runs])

    def estimates(self, estimator: str, metric: str | None = None) -> list[Estimate]:
        """Mean and 95% CI over seeds at every value."""
        return [mean_ci(row) for row in self.per_trial(estimator, metric)]

    def to_dict(self) -> dict:
        """Plain mapping for JSON: every point, filter and metric (mean, CI, per seed)."""
        points = []
        for v, run in zip(self.spec.values, self.runs, strict=True):
            est = {}
            for name, e in run.estimators.items():
                est[name] = {
                    m: {**mean_ci(e.per_trial(m)).to_dict(), "per_seed": e.per_trial(m)}
                    for m in METRICS
                    if not (name == DEAD_RECKONING and m == "comm_rate")
                }
            points.append({"value": v, "estimators": est})
        return {
            "name": self.spec.name,
            "parameter": self.spec.parameter,
            "values": list(self.spec.values),
            "metric": self.spec.metric,
            "seeds": self.seeds,
            "base_seed": self.spec.base.run.seed,
            "steps": self.spec.base.run.steps,
            "filters": self.filters,
            "wall_time_s": self.wall_time,
            "points": points,
        }


def run_sweep(
    spec: SweepSpec,
    seeds: int | None = None,
    steps: int | None = None,
    jobs: int = 1,
    progress: ProgressFn | None = None,
) -> SweepResult:
    """Run every point of ``spec`` over ``seeds`` seeds (batched as trials), in parallel.

    Parameters
    ----------
    spec : SweepSpec
    seeds : int, optional
        Override ``run.trials`` (seeds ``run.seed``'s trials ``0 .. seeds - 1``).
    steps : int, optional
        Override ``run.steps``.
    jobs : int
        Worker processes.
    progress : callable(done, total), optional

    Returns
    -------
    SweepResult
    """
    t0 = time.perf_counter()
    spec = spec.with_run(seeds, steps)
    runs = run_scenarios(spec.scenarios(), jobs=jobs, progress=progress)
    return SweepResult(spec, runs, time.perf_counter() - t0, {"jobs": jobs})


def _fmt_value(v: Any) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def save_sweep(result: SweepResult, out: Path, plots: bool = True) -> list[Path]:
    """Write a :class:`SweepResult` into directory ``out``.

    Files: ``sweep.toml`` (re-runnable), ``summary.json`` (every point, filter and metric:
    mean, 95% CI, per-seed values), ``sweep.csv`` (one row per point and filter) and, with
    plots, ``sweep.png`` (metric against the value, 95% CI bars), ``msle_time.png`` (MSLE
    over time per value, 95% bands) and ``transmissions_<k>.png`` (robot x time raster of
    seed 0 per value, titled with the average communication rate).
    """
    from resloc.experiments.output import write_json

    out = Path(out)
    spec = result.spec
    written = []
    p = out / "sweep.toml"
    p.write_text(dump_sweep(spec), encoding="utf-8")
    written.append(p)
    p = out / "summary.json"
    write_json(p, result.to_dict())
    written.append(p)
    p = out / "sweep.csv"
    rows = ["value,estimator," + ",".join(f"{m},{m}_ci95" for m in METRICS)]
    for v, run in zip(spec.values, result.runs, strict=True):
        for name, e in run.estimators.items():
            cells = []
            for m in METRICS:
                est = mean_ci(e.per_trial(m))
                cells += [f"{est.mean:.6g}", f"{est.half:.6g}"]
            rows.append(f"{_fmt_value(v)},{name}," + ",".join(cells))
    p.write_text("\n".join(rows) + "\n", encoding="utf-8")
    written.append(p)
    if plots:
        from resloc.experiments import report as figures

        label = spec.parameter
        written.append(
            figures.errorbar_figure(
                out / "sweep.png",
                list(spec.values),
                {f: result.estimates(f) for f in result.filters},
                xlabel=label,
                ylabel=figures.METRIC_LABELS.get(spec.metric, spec.metric),
                title=f"{spec.name}\n({result.seeds} seeds, mean and 95% CI)",
                logy=spec.metric.startswith("msle"),
            )
        )
        first = result.filters[0] if result.filters else DEAD_RECKONING
        curves = [
            figures.Curve(
                f"{label} = {_fmt_value(v)}", run.time, run.estimators[first].series["msle"]
            )
            for v, run in zip(spec.values, result.runs, strict=True)
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
                e = run.estimators[first]
                cr = mean_ci(e.per_trial("comm_rate"))
                written.append(
                    figures.raster_figure(
                        out / f"transmissions_{k}.png",
                        e.raster,
                        run.time,
                        f"{first.upper()} transmissions, {label} = {_fmt_value(v)}\n"
                        f"(average communication rate = {_rate_text(cr)})",
                        e.links,
                    )
                )
    return written


def _rate_text(est: Estimate) -> str:
    if not math.isfinite(est.mean):
        return "-"
    return est.format(".3f")
