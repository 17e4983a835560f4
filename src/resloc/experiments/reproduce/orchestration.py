"""Running the reproduction (:func:`run_reproduction`: every experiment over several seeds
in parallel worker processes) and writing it (:func:`write_reproduction`: report, results,
figures, scenarios)."""

from __future__ import annotations

import datetime as _dt
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from resloc import __version__
from resloc.experiments.config import Scenario
from resloc.experiments.config_dump import dump_scenario
from resloc.experiments.executor import Study
from resloc.experiments.reproduce.catalogue import (
    FULL_SEEDS,
    QUICK_SEEDS,
    QUICK_STEPS,
    Experiment,
    experiments,
    write_examples,
)
from resloc.experiments.reproduce.claims import Claim, evaluate_claims
from resloc.experiments.reproduce.report import build_report
from resloc.experiments.runner import RunResult
from resloc.experiments.stats import (
    mean_ci,
)
from resloc.experiments.sweep import (
    SweepResult,
    dump_sweep,
    run_scenarios,
)

__all__ = [
    "Reproduction",
    "main",
    "results_dict",
    "run_reproduction",
    "write_reproduction",
]


@dataclass
class Reproduction:
    """Every experiment's result.

    Attributes
    ----------
    experiments : list of Experiment
    results : dict
        ``key -> RunResult`` (single scenarios) or ``SweepResult`` (sweeps).
    seeds, steps : int
    quick : bool
    jobs : int
    wall_time : float
        Seconds for all simulations.
    runs : int
        Distinct simulations (identical scenarios are simulated once).
    """

    experiments: list[Experiment]
    results: dict[str, Any]
    seeds: int
    steps: int
    quick: bool
    jobs: int
    wall_time: float
    runs: int = 0
    started: str = field(default_factory=lambda: _dt.datetime.now().isoformat(timespec="seconds"))

    def run(self, key: str) -> RunResult:
        """A single-scenario experiment's result."""
        res = self.results[key]
        assert isinstance(res, RunResult)
        return res

    def sweep(self, key: str) -> SweepResult:
        """A sweep experiment's result."""
        res = self.results[key]
        assert isinstance(res, SweepResult)
        return res


def run_reproduction(
    seeds: int | None = None,
    steps: int | None = None,
    quick: bool = False,
    jobs: int | None = 1,
    progress: Callable[[float, float], None] | None = None,
    study: Study | None = None,
) -> Reproduction:
    """Run every experiment of :func:`experiments`.

    Parameters
    ----------
    seeds : int, optional
        Seeds per experiment (default 10, or 2 with ``quick``), batched as trials.
    steps : int, optional
        Steps per run (default: the scenario's, or :data:`QUICK_STEPS` with ``quick``).
    quick : bool
    jobs : int, optional
        Worker processes when no ``study`` is given (``None``: the CPUs).
    progress : callable(done, total), optional
        Over cells, when no ``study`` is given.
    study : Study, optional
        The study executor: backend (embedded or external Dask cluster), result store,
        progress.

    Returns
    -------
    Reproduction
    """
    exps = experiments()
    seeds = int(seeds) if seeds is not None else (QUICK_SEEDS if quick else FULL_SEEDS)
    if steps is None and quick:
        steps = QUICK_STEPS
    t0 = time.perf_counter()
    scenarios: list[Scenario] = []
    slices = {}
    for exp in exps:
        sc = exp.scenarios(seeds, steps)
        slices[exp.key] = slice(len(scenarios), len(scenarios) + len(sc))
        scenarios += sc
    study = study if study is not None else Study(jobs=jobs, progress=progress)
    runs = run_scenarios(scenarios, study=study)
    jobs = study.stats.workers
    wall = time.perf_counter() - t0
    results: dict[str, Any] = {}
    for exp in exps:
        part = runs[slices[exp.key]]
        if exp.is_sweep:
            spec = exp.sweep().with_run(seeds, steps)
            results[exp.key] = SweepResult(spec, part, sum(r.wall_time for r in part))
        else:
            results[exp.key] = part[0]
    distinct = len({id(r.truth) for r in runs})
    return Reproduction(
        exps,
        results,
        seeds,
        scenarios[0].run.steps,
        quick,
        jobs,
        wall,
        distinct,
    )


def results_dict(rep: Reproduction, claims: list[Claim]) -> dict:
    """Every number of the report, for ``results.json``."""
    out: dict[str, Any] = {
        "resloc": __version__,
        "started": rep.started,
        "seeds": rep.seeds,
        "steps": rep.steps,
        "quick": rep.quick,
        "jobs": rep.jobs,
        "wall_time_s": rep.wall_time,
        "distinct_runs": rep.runs,
        "claims": [
            {
                "figure": c.figure,
                "claim": c.text,
                "test": c.test,
                "measured": c.measured,
                "verdict": c.verdict.value,
                "note": c.note,
                "data": c.data,
            }
            for c in claims
        ],
        "experiments": {},
    }
    for exp in rep.experiments:
        res = rep.results[exp.key]
        if isinstance(res, SweepResult):
            out["experiments"][exp.key] = res.to_dict()
        else:
            out["experiments"][exp.key] = {
                "name": exp.title,
                "wall_time_s": res.wall_time,
                "estimators": {
                    name: {
                        m: {**mean_ci(e.per_trial(m)).to_dict(), "per_seed": e.per_trial(m)}
                        for m in ("msle_mean", "msle_final", "rmse_mean", "comm_rate")
                    }
                    for name, e in res.estimators.items()
                },
            }
    return out


def write_reproduction(rep: Reproduction, out: Path) -> tuple[list[Claim], dict[str, Path]]:
    """Evaluate the claims and write ``report.md``, ``report.html``, ``results.json``,
    ``figures/*.png`` and ``scenarios/*.toml`` (each experiment as run) into ``out``."""
    from resloc.experiments.report import write_report
    from resloc.experiments.run_files import write_json

    out = Path(out)
    claims = evaluate_claims(rep)
    doc = build_report(rep, claims, out)
    md, page = write_report(doc, out)
    write_json(out / "results.json", results_dict(rep, claims))
    sc_dir = out / "scenarios"
    sc_dir.mkdir(exist_ok=True)
    for exp in rep.experiments:
        res = rep.results[exp.key]
        text = dump_sweep(res.spec) if isinstance(res, SweepResult) else dump_scenario(res.scenario)
        (sc_dir / exp.filename).write_text(text, encoding="utf-8")
    return claims, {"report.md": md, "report.html": page, "results.json": out / "results.json"}


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description="Maintenance: write examples/paper/*.toml")
    ap.add_argument("--write-examples", type=Path, required=True, metavar="DIR")
    args = ap.parse_args(argv)
    for p in write_examples(args.write_examples):
        print(p)
    return 0
