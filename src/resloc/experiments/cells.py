"""Simulation cells: one estimator on one seed (trial) of one resolved scenario.

``resloc reproduce`` and ``resloc sweep`` are lists of scenarios, each with ``run.trials``
seeds and ``run.filters`` (+ dead reckoning). :func:`run_scenarios` splits them into cells
``(scenario, trial, estimator)``, reads the cells the store already has, groups the others
into tasks (the contiguous missing trials of one scenario and the union of their
estimators are simulated together, batched: trial ``t`` is identical whichever trials are
batched with it, and the world does not depend on the estimators), runs the tasks on a
:class:`~resloc.experiments.executor.Study`, and assembles one
:class:`~resloc.experiments.runner.RunResult` per scenario from its cells.

The store key of a cell (:func:`sim_key`) is the scenario without ``run.trials``,
``run.filters``, ``run.name`` and ``run.dead_reckoning`` (they select cells, they do not
change one), the trial index, the estimator, the package version and its source fingerprint.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from resloc.experiments.config import Scenario
from resloc.experiments.config_dump import scenario_to_dict
from resloc.experiments.executor import (
    Study,
    StudyFailedError,
    Task,
    default_jobs,
)
from resloc.experiments.runner import DEAD_RECKONING, EstimatorResult, RunResult, run_scenario
from resloc.experiments.store import canonical_json, cell_key

__all__ = [
    "SimCell",
    "StudyFailedError",
    "contiguous_runs",
    "group_data",
    "run_scenarios",
    "sim_key",
    "simulate_cells",
]

#: Order of estimators within a task (the world does not depend on it).
_ESTIMATOR_ORDER = ("ckf", "ukf", "ekf", DEAD_RECKONING)
#: Seeds batched in one task at most (bounds a task's memory and the work lost to a kill).
MAX_BATCH = 16


@dataclass
class SimCell:
    """One estimator on one trial.

    Attributes
    ----------
    estimator : str
        ``ckf``, ``ukf``, ``ekf`` or ``dr``.
    trial : int
    series : dict of str to ndarray, each shape (steps,)
    totals : dict of str to int
    wall_time : float
        This trial's share of the estimator's time in its task.
    raster : ndarray of int8, shape (steps, N), or None
        Trial 0 only (as in :class:`~resloc.experiments.runner.EstimatorResult`).
    track : ndarray, shape (steps + 1, N, 3), or None
        Trial 0 only.
    truth : ndarray, shape (steps + 1, N, 3), or None
        True poses, trial 0 only.
    time : ndarray, shape (steps,), or None
        Trial 0 only.
    cov : ndarray of float32, shape (steps + 1, N, 3, 3), or None
        Reported covariances, trial 0 only.
    links : LinkLog or None
        Every sensed link of trial 0 with this estimator's outcomes (trial 0 only).
    """

    estimator: str
    trial: int
    series: dict
    totals: dict
    wall_time: float
    raster: np.ndarray | None = None
    track: np.ndarray | None = None
    truth: np.ndarray | None = None
    time: np.ndarray | None = None
    cov: np.ndarray | None = None
    links: Any = None


def group_data(scenario: Scenario) -> dict:
    """The scenario as a mapping without the keys that only select cells."""
    data = scenario_to_dict(scenario)
    for k in ("trials", "filters", "name", "dead_reckoning"):
        data["run"].pop(k)
    return data


def sim_key(group: str, trial: int, estimator: str) -> str:
    """Store key of a simulation cell; ``group`` is the SHA-256 of the canonical JSON of
    :func:`group_data` (see module doc), computed once per scenario."""
    return cell_key("sim", scenario=group, trial=int(trial), estimator=estimator)


def _digest(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _estimators(scenario: Scenario) -> list[str]:
    return [*scenario.run.filters, *([DEAD_RECKONING] if scenario.run.dead_reckoning else [])]


def simulate_cells(
    scenario: Scenario,
    first_trial: int,
    trials: int,
    estimators: tuple[str, ...],
    wanted: tuple[tuple[int, str], ...] | None = None,
) -> list[SimCell]:
    """Simulate trials ``first_trial .. first_trial + trials - 1`` with ``estimators``.

    Parameters
    ----------
    scenario : Scenario
    first_trial, trials : int
    estimators : tuple of str
        Run together (filters and ``dr``).
    wanted : tuple of (trial, estimator), optional
        The cells to return, in this order (default: every trial and estimator).

    Returns
    -------
    list of SimCell
        ``wanted`` order, or trial-major with estimators in the given order.
    """
    filters = [e for e in estimators if e != DEAD_RECKONING]
    run = scenario.replace(
        **{
            "run.trials": int(trials),
            "run.filters": filters,
            "run.dead_reckoning": DEAD_RECKONING in estimators,
        }
    )
    res = run_scenario(run, first_trial=first_trial)
    if wanted is None:
        wanted = tuple((first_trial + t, name) for t in range(trials) for name in estimators)
    cells = []
    for trial, name in wanted:
        t = trial - first_trial
        est = res.estimators[name]
        first = trial == 0
        cells.append(
            SimCell(
                name,
                trial,
                {k: v[:, t].copy() for k, v in est.series.items()},
                {k: int(v[t]) for k, v in est.totals.items()},
                est.wall_time / trials,
                est.raster if first else None,
                est.track if first else None,
                res.truth if first else None,
                res.time if first else None,
                est.cov if first else None,
                est.links if first else None,
            )
        )
    return cells


def _cost(scenario: Scenario, trials: int, estimators: int) -> float:
    """Relative cost of a task: robots x trials x steps x (estimators + world overhead)."""
    return float(scenario.world.team.robots * trials * scenario.run.steps * (estimators + 0.2))


def contiguous_runs(trials: list[int], size: int) -> list[list[int]]:
    """Contiguous runs of ``trials`` (sorted), each at most ``size`` long."""
    out: list[list[int]] = []
    for t in trials:
        if out and t == out[-1][-1] + 1 and len(out[-1]) < size:
            out[-1].append(t)
        else:
            out.append([t])
    return out


def _assemble(
    scenario: Scenario, cells: dict[tuple[int, str], SimCell], truth_cache: dict, group: str
) -> RunResult:
    """One RunResult from its cells (trials stacked along the last axis)."""
    T = scenario.run.trials
    estimators = {}
    for name in _estimators(scenario):
        per = [cells[(t, name)] for t in range(T)]
        estimators[name] = EstimatorResult(
            name,
            {k: np.stack([c.series[k] for c in per], axis=1) for k in per[0].series},
            {k: np.array([c.totals[k] for c in per], dtype=np.int64) for k in per[0].totals},
            per[0].raster,
            per[0].track,
            float(sum(c.wall_time for c in per)),
            per[0].cov,
            per[0].links,
        )
    first = cells[(0, _estimators(scenario)[0])]
    # One truth object per distinct simulation (callers count distinct runs by identity).
    truth, time = truth_cache.setdefault(group, (first.truth, first.time))
    wall = float(sum(e.wall_time for e in estimators.values()))
    meta = {"robots": scenario.world.team.robots, "trials": T}
    return RunResult(scenario, estimators, truth, time, wall, meta)


def run_scenarios(
    scenarios: list[Scenario],
    jobs: int | None = 1,
    progress=None,
    study: Study | None = None,
    allow_failures: bool = False,
) -> list[RunResult | None]:
    """Run several scenarios (cells from the store, the rest on the study's backend).

    Parameters
    ----------
    scenarios : list of Scenario
    jobs : int, optional
        Worker processes when no ``study`` is given (``1``: this process).
    progress : callable(done, total), optional
        Over cells; used when no ``study`` is given.
    study : Study, optional
        Backend, store and progress (default: ``Study(jobs, progress=progress)``, no store).
    allow_failures : bool
        ``True``: a scenario with a failed cell gives ``None`` (the failures are in
        ``study.failures``); ``False``: raise :class:`StudyFailedError` after the others finished.

    Returns
    -------
    list of RunResult or None
        One per scenario; its ``estimators`` hold exactly the scenario's filters (plus
        ``dr`` when it asks for dead reckoning).
    """
    study = study if study is not None else Study(jobs=jobs, progress=progress)
    groups: dict[str, tuple[Scenario, dict, str]] = {}
    needed: dict[str, dict[int, set[str]]] = {}
    gids = []
    for s in scenarios:
        data = group_data(s)
        gid = canonical_json(data)
        gids.append(gid)
        groups.setdefault(gid, (s, data, _digest(gid)))
        per = needed.setdefault(gid, {})
        for t in range(s.run.trials):
            per.setdefault(t, set()).update(_estimators(s))

    got: dict[str, dict[tuple[int, str], SimCell]] = {gid: {} for gid in groups}
    missing: dict[str, dict[int, set[str]]] = {}
    hits = 0
    for gid, per in needed.items():
        digest = groups[gid][2]
        for t, names in per.items():
            for name in names:
                found, value = study.lookup(sim_key(digest, t, name))
                if found:
                    got[gid][(t, name)] = value
                    hits += 1
                else:
                    missing.setdefault(gid, {}).setdefault(t, set()).add(name)

    # Enough tasks to keep every worker busy to the end, as few as that allows (batching
    # seeds is up to ~2x faster); the numbers do not depend on the batching.
    parallel = 8 if study.scheduler else (study.jobs or default_jobs())
    n_missing = sum(len(per) for per in missing.values())
    batch = max(1, min(MAX_BATCH, math.ceil(n_missing / max(1, 4 * parallel))))
    tasks: list[Task] = []
    index: dict[str, tuple[str, int, str]] = {}
    for gid, per in missing.items():
        base, data, digest = groups[gid]
        for chunk in contiguous_runs(sorted(per), batch):
            wanted = set().union(*(per[t] for t in chunk))
            names = tuple(e for e in _ESTIMATOR_ORDER if e in wanted)
            # Only the missing cells are returned (a stored cell is never rewritten).
            cells = tuple((t, name) for t in chunk for name in names if name in per[t])
            keys = []
            for t, name in cells:
                key = sim_key(digest, t, name)
                keys.append(key)
                index[key] = (gid, t, name)
            tasks.append(
                Task(
                    simulate_cells,
                    (base, chunk[0], len(chunk), names, cells),
                    tuple(keys),
                    f"{base.run.name} seeds {chunk[0]}..{chunk[-1]}",
                    {"scenario": data, "trials": [chunk[0], chunk[-1]], "estimators": names},
                    _cost(base, len(chunk), len(names)),
                )
            )
    computed_cells = sum(len(t.keys) for t in tasks)
    results = study.run(tasks, cells=hits + computed_cells, from_store=hits)
    for key, value in results.items():
        gid, t, name = index[key]
        got[gid][(t, name)] = value

    truth_cache: dict = {}
    out: list[RunResult | None] = []
    for s, gid in zip(scenarios, gids, strict=True):
        cells = got[gid]
        complete = all((t, e) in cells for t in range(s.run.trials) for e in _estimators(s))
        out.append(_assemble(s, cells, truth_cache, gid) if complete else None)
    if study.failures and not allow_failures:
        raise StudyFailedError(study.failures, study.stats)
    return out
