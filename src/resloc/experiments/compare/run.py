"""Running ``resloc compare``: one task per cell (a scenario with all its seeds as trials of
one run), computed on the study executor (:mod:`resloc.experiments.executor`: in this
process, an embedded or an external Dask cluster, with the result store)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from resloc.cl.detection import NORM_GATE
from resloc.experiments.compare.methods import (
    BEST,
    DEFAULT,
    EXTRA_SCENARIOS,
    FUSION_METHODS,
    METHODS,
    NAIVE_REFERENCE,
    PAPER,
    QUICK_TEAM_SIZES,
    ROC_GATES,
    SCENARIOS,
    TEAM_SIZES,
    Method,
    StudyScenario,
    study_scenario,
)
from resloc.experiments.compare.report import CompareResult, compare_result
from resloc.experiments.config import Scenario, default_scenario
from resloc.experiments.config_dump import scenario_to_dict
from resloc.experiments.executor import Study, StudyFailedError, Task
from resloc.experiments.store import cell_key

__all__ = ["run_compare"]


def _cell_metrics(result, name: str) -> dict[str, Any]:
    """Per-trial metrics of one estimator of a run."""
    est = result.estimators[name]
    t = est.totals
    with np.errstate(invalid="ignore", divide="ignore"):
        tpr = t["tp"] / (t["tp"] + t["fn"])
        fpr = t["fp"] / (t["fp"] + t["tn"])
        att_fused = t["attacked_fused"] / t["attacked"]
    return {
        "msle": est.per_trial("msle_mean"),
        "msle_final": est.per_trial("msle_final"),
        "rmse": est.per_trial("rmse_mean"),
        "nees": est.per_trial("nees_mean"),
        "nees_rel": est.per_trial("nees_rel_mean"),
        "comm_rate": est.per_trial("comm_rate"),
        "bytes_per_step": est.bytes_per_step(result.scenario.estimator.fusion),
        "tpr": tpr,
        "fpr": fpr,
        "attacked_fused": att_fused,
        "repairs": int(t["repairs"].sum()),
        "wall_time_s": float(result.wall_time),
    }


def _compute_cell(scenario: Scenario, params, stride: int) -> list[dict]:
    """One cell (picklable, runs on a worker): the metrics of the scenario's filter."""
    from resloc.experiments.runner import run_scenario

    result = run_scenario(scenario, params=params, metric_stride=stride)
    name = scenario.run.filters[0]
    out: dict[str, Any] = {"metrics": _cell_metrics(result, name)}
    out["robots"] = result.meta["robots"]
    if "lambda2" in result.meta:
        out["lambda2"] = {
            k: v for k, v in result.meta["lambda2"].items() if k != "abs_rel_error_series"
        }
        if "abs_rel_error_series" in result.meta["lambda2"]:
            series = np.asarray(result.meta["lambda2"]["abs_rel_error_series"])
            burn = min(len(series) // 10, 100)
            out["lambda2"]["abs_rel_error_after_warmup"] = float(np.nanmean(series[burn:]))
    return [out]


def _cell_task(task: dict) -> Task:
    """The executor task of one comparison cell; its store key is everything that
    determines the result (the scenario with its seeds, per-trial parameters, stride)."""
    scenario: Scenario = task["scenario"]
    params, stride = task.get("params"), task.get("stride", 1)
    key = cell_key(
        "compare", scenario=scenario_to_dict(scenario), params=params, stride=int(stride)
    )
    return Task(
        _compute_cell,
        (scenario, params, stride),
        (key,),
        task["label"],
        {"scenario": scenario_to_dict(scenario), "label": task["label"]},
        float(scenario.world.team.robots * scenario.run.trials * scenario.run.steps),
    )


def _run_cells(tasks: list[dict], study: Study) -> list[dict]:
    """Every cell: from the study's store, or computed on its backend (in task order)."""
    work = [_cell_task(t) for t in tasks]
    looked_up = {w.keys[0]: study.lookup(w.keys[0]) for w in work}
    found = {key: value for key, (hit, value) in looked_up.items() if hit}
    todo = [w for w in work if w.keys[0] not in found]
    found.update(study.run(todo, cells=len(work), from_store=len(found)))
    if study.failures:
        raise StudyFailedError(study.failures, study.stats)
    described = ({k: v for k, v in t.items() if k not in ("scenario", "params")} for t in tasks)
    return [{"task": d, **found[w.keys[0]]} for d, w in zip(described, work, strict=True)]


def _task(study, sc: StudyScenario, me: Method, seeds, steps, filt, quick, robots=None) -> dict:
    return {
        "study": study,
        "scenario_key": sc.key,
        "scenario_label": sc.label,
        "method_key": me.key,
        "method_label": me.label,
        "label": f"{study}: {sc.key} / {me.key}",
        "scenario": study_scenario(sc, me, seeds, steps, filt, quick, robots=robots),
    }


def _roc_tasks(quick: bool, filt: str, steps: int, robots=None) -> list[dict]:
    """Closed-loop ROC runs: gauge fusion, one threshold per group of trials (threshold k on
    trials ``k*seeds .. (k+1)*seeds - 1``, as a per-robot gate threshold)."""
    seeds = 1 if quick else 3
    tasks = []
    for attack in ("sdz_stealthy",) if quick else ("sdz_fixed", "sdz_stealthy"):
        sc = next(s for s in SCENARIOS if s.key == attack)
        for gate in ROC_GATES:
            values = gate.values[::3] if quick else gate.values
            changes = {"estimator.fusion": "gauge", **gate.changes}
            me = Method(f"roc-{gate.key}", f"ROC {gate.key}", changes)
            scenario = study_scenario(
                sc, me, seeds * len(values), steps, filt, quick, robots=robots
            )
            thresholds = [
                NORM_GATE.threshold(dataclasses.replace(scenario.detector, **{gate.option: v}))
                for v in values
            ]
            per_trial = np.repeat(np.asarray(thresholds, float), seeds)
            rho = np.repeat(per_trial, scenario.world.team.robots)
            tasks.append(
                {
                    "study": "roc",
                    "scenario_key": attack,
                    "method_key": gate.key,
                    "label": f"roc: {attack} / {gate.key}",
                    "values": list(values),
                    "threshold_name": gate.threshold_name,
                    "seeds": seeds,
                    "scenario": scenario,
                    "params": dataclasses.replace(scenario.cl_params(), rho=rho),
                    "stride": 10,
                }
            )
    return tasks


def _lambda2_tasks(quick: bool, seeds: int, filt: str, steps: int) -> list[dict]:
    sizes = QUICK_TEAM_SIZES if quick else TEAM_SIZES
    tasks = []
    clean = SCENARIOS[0]
    for n in sizes:
        for mode in ("global", "distributed"):
            me = Method(f"lambda2-{mode}", f"lambda2 {mode}", {"trigger.lambda2": mode})
            scenario = study_scenario(clean, me, seeds, steps, filt, quick).replace(
                **{"team.robots": n}
            )
            tasks.append(
                {
                    "study": "lambda2",
                    "scenario_key": "clean",
                    "method_key": mode,
                    "robots": n,
                    "label": f"lambda2: N={n} / {mode}",
                    "scenario": scenario,
                    "stride": 10,
                }
            )
    return tasks


def run_compare(
    quick: bool = False,
    seeds: int | None = None,
    jobs: int | None = 1,
    filt: str = "ckf",
    progress: Callable[[int, int, str], None] | None = None,
    studies: tuple[str, ...] = ("table", "fusion", "roc", "lambda2"),
    steps: int | None = None,
    robots: int | None = None,
    study: Study | None = None,
) -> CompareResult:
    """Run the comparison of resloc's methods with the paper's (``docs/beyond.md``).

    Parameters
    ----------
    quick : bool
        Smoke-test size: 2 seeds, 200 steps, zones moved onto the team's first 200 steps,
        the paper and the best combination, a reduced ROC and lambda2 study.
    seeds : int, optional
        Seeds (trials) per cell (default 10, quick 2).
    jobs : int, optional
        Worker processes when no ``study`` is given (``None``: the CPUs).
    filt : {"ckf", "ukf", "ekf"}
    progress : callable(done, total, label), optional
        Over cells, when no ``study`` is given.
    studies : tuple of str
        Which studies to run.
    steps, robots : int, optional
        Override the steps per run and the team size (tests; the report's targets assume
        the defaults).
    study : Study, optional
        Backend (embedded or external Dask cluster), result store and progress.

    Returns
    -------
    CompareResult
    """
    t0 = time.perf_counter()
    seeds = int(seeds if seeds is not None else (2 if quick else 10))
    steps = int(steps) if steps is not None else (200 if quick else 1000)
    methods = tuple(m for m in METHODS if m.key in (PAPER, BEST)) if quick else METHODS
    tasks: list[dict] = []
    if "table" in studies:
        for sc in SCENARIOS:
            for me in methods:
                tasks.append(_task("table", sc, me, seeds, steps, filt, quick, robots))
        extra_methods = tuple(m for m in METHODS if m.key in (PAPER, BEST))
        for sc in () if quick else EXTRA_SCENARIOS:
            for me in extra_methods:
                tasks.append(_task("extra", sc, me, seeds, steps, filt, quick, robots))
    if "fusion" in studies:
        fusion_methods = (
            FUSION_METHODS
            if not quick
            else tuple(m for m in FUSION_METHODS if m.key in ("naive", NAIVE_REFERENCE, BEST))
        )
        for me in fusion_methods:
            tasks.append(_task("fusion", DEFAULT, me, seeds, steps, filt, quick, robots))
    if "roc" in studies:
        tasks += _roc_tasks(quick, filt, steps, robots)
    if "lambda2" in studies:
        tasks += _lambda2_tasks(quick, seeds, filt, steps)

    if study is None:
        study = Study(
            jobs=jobs, progress=(lambda d, t: progress(int(d), int(t), "")) if progress else None
        )
    outputs = _run_cells(tasks, study)
    config = {
        "quick": quick,
        "seeds": seeds,
        "steps": steps,
        "filter": filt,
        "jobs": study.stats.workers,
        "study": study.stats.to_dict(),
        "robots": robots or default_scenario().world.team.robots,
        "wall_time_s": time.perf_counter() - t0,
        "cells": len(tasks),
    }
    return compare_result(config, outputs)
