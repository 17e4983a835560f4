"""Issue 6: resloc's fixes measured against the paper's method (``resloc compare``).

Four studies, each over seeds (Monte Carlo trials batched in one run per cell, common
random numbers across methods):

* **main table**: method x scenario (clean, SDZ fixed bias, SDZ stealthy, CDZ jamming) ->
  MSLE, RMSE, NEES, communication rate, detection TPR / FPR, means with 95% Student-t
  intervals over seeds; plus extra attacks (replay, a stealthy attacker that only knows the
  per-measurement gate);
* **fusion consistency** on the default scenario: naive, CI, split CI, factorized, tracked,
  gauge, with the NEES chi-square band;
* **detector ROC** (closed loop): raw-norm and NIS gates swept over their thresholds
  (one threshold per trial of one run, the attacker adapting to each) under fixed and
  stealthy attacks;
* **lambda2 with N**: the distributed estimate's error against the true algebraic
  connectivity, and the trigger's communication rate with the global and the distributed
  value, for growing teams.

Every cell is an independent :func:`~resloc.experiments.runner.run_scenario` call, so cells
run as cells of the study executor (:mod:`resloc.experiments.executor`: embedded or external
Dask cluster, result store). ``docs/beyond.md`` describes the methods.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from resloc.cl.cusum import chi2_gate
from resloc.distributions import chi2
from resloc.experiments.config import Scenario, default_scenario, scenario_to_dict
from resloc.experiments.executor import Study, StudyFailedError, Task
from resloc.experiments.stats import mean_ci, ratio
from resloc.experiments.store import cell_key

__all__ = [
    "FUSION_METHODS",
    "METHODS",
    "SCENARIOS",
    "CompareResult",
    "Method",
    "StudyScenario",
    "nees_band",
    "run_compare",
    "save_compare",
    "study_scenario",
]


@dataclass(frozen=True)
class Method:
    """An estimator configuration: dotted scenario changes on top of the paper's."""

    key: str
    label: str
    changes: dict = field(default_factory=dict)


_NIS = {"detector.norm": "nis", "detector.false_alarm": 0.01}

_NIS_CUSUM = {**_NIS, "detector.cusum": True}
_MEAN = {"detector.mean_cusum": True}

#: The main table's methods (the paper first).
METHODS: tuple[Method, ...] = (
    Method("paper", "paper: naive fusion, raw-norm gate", {}),
    Method("ci", "CI fusion, raw-norm gate", {"estimator.fusion": "ci"}),
    Method(
        "tracked+nis+cusum",
        "tracked, NIS gate + CUSUM",
        {"estimator.fusion": "tracked", **_NIS_CUSUM},
    ),
    Method("gauge+nis", "gauge, NIS gate", {"estimator.fusion": "gauge", **_NIS}),
    Method(
        "gauge+nis+cusum",
        "gauge, NIS gate + CUSUM",
        {"estimator.fusion": "gauge", **_NIS_CUSUM},
    ),
    Method(
        "gauge+nis+cusum+mean",
        "gauge, NIS gate + CUSUM + mean-shift CUSUM",
        {"estimator.fusion": "gauge", **_NIS_CUSUM, **_MEAN},
    ),
)

#: The fusion-consistency table's methods: each fusion with the unit-aware detector (the
#: default scenario's random injections pass the raw-norm gate and would corrupt any fusion),
#: plus the paper's configuration and tracked fusion with the paper's gate for reference.
#: Each "+nis+cusum" row is compared with naive fusion under the same detector.
FUSION_METHODS: tuple[Method, ...] = (
    Method("naive", "naive, raw-norm gate (paper)", {}),
    Method("naive+nis+cusum", "naive, NIS gate + CUSUM", dict(_NIS_CUSUM)),
    Method("ci+nis+cusum", "CI, NIS gate + CUSUM", {"estimator.fusion": "ci", **_NIS_CUSUM}),
    Method(
        "split_ci+nis+cusum",
        "split CI, NIS gate + CUSUM",
        {"estimator.fusion": "split_ci", **_NIS_CUSUM},
    ),
    Method(
        "factorized+nis+cusum",
        "factorized (Luft et al.), NIS gate + CUSUM",
        {"estimator.fusion": "factorized", **_NIS_CUSUM},
    ),
    Method("tracked", "tracked, raw-norm gate", {"estimator.fusion": "tracked"}),
    Method(
        "tracked+nis+cusum",
        "tracked, NIS gate + CUSUM",
        {"estimator.fusion": "tracked", **_NIS_CUSUM},
    ),
    Method(
        "gauge+nis+cusum",
        "gauge, NIS gate + CUSUM",
        {"estimator.fusion": "gauge", **_NIS_CUSUM},
    ),
    Method(
        "gauge(consensus)+nis+cusum",
        "gauge with consensus sums, NIS gate + CUSUM",
        {"estimator.fusion": "gauge", "estimator.gauge_sums": "consensus", **_NIS_CUSUM},
    ),
    Method(
        "gauge+nis+cusum+mean",
        "gauge, NIS gate + CUSUM + mean-shift CUSUM",
        {"estimator.fusion": "gauge", **_NIS_CUSUM, **_MEAN},
    ),
)

#: The naive reference of the fusion target (same detector as the methods it is compared to).
NAIVE_REFERENCE = "naive+nis+cusum"


@dataclass(frozen=True)
class StudyScenario:
    """A scenario of the study: dotted changes on the embedded default."""

    key: str
    label: str
    changes: dict


_SDZ = {"center": [0.45, -0.55], "radius": 0.5, "peak": 0.9}
_CDZ = {"center": [0.2, 0.45], "radius": 0.4, "peak": 1.0}
#: In --quick runs (200 steps) the zones sit where the team is during its first 200 steps.
_QUICK_ZONE = {"center": [-0.55, -0.9], "radius": 0.5, "peak": 0.9}
_BIAS = [0.3, 0.6]

#: The main table's scenarios.
SCENARIOS: tuple[StudyScenario, ...] = (
    StudyScenario("clean", "clean (no zones)", {"sdz": [], "cdz": []}),
    StudyScenario(
        "sdz_fixed",
        "SDZ, fixed bias",
        {"sdz": [_SDZ], "cdz": [], "attack.kind": "fixed", "attack.bias": _BIAS},
    ),
    StudyScenario(
        "sdz_stealthy",
        "SDZ, stealthy",
        {"sdz": [_SDZ], "cdz": [], "attack.kind": "stealthy", "attack.bias": _BIAS},
    ),
    StudyScenario("cdz_jamming", "CDZ jamming", {"sdz": [], "cdz": [_CDZ]}),
)

#: Further attacks, for the paper's method and the best combination.
EXTRA_SCENARIOS: tuple[StudyScenario, ...] = (
    StudyScenario(
        "sdz_stealthy_gate",
        "SDZ, stealthy (knows the gate only)",
        {
            "sdz": [_SDZ],
            "cdz": [],
            "attack.kind": "stealthy",
            "attack.bias": _BIAS,
            "attack.stealth_knowledge": "gate",
        },
    ),
    StudyScenario(
        "sdz_replay",
        "SDZ, replay (2 s old)",
        {"sdz": [_SDZ], "cdz": [], "attack.kind": "replay", "attack.replay_delay": 60},
    ),
)

#: The paper's default scenario (SDZ with random injections + CDZ), for fusion consistency.
DEFAULT = StudyScenario("default", "default (SDZ random + CDZ)", {})

#: The best combination (the target's subject) and its reference.
BEST = "gauge+nis+cusum+mean"
PAPER = "paper"

#: ROC sweeps: raw-norm thresholds rho, NIS gate false-alarm probabilities.
ROC_RHO = (0.05, 0.1, 0.2, 0.3, 0.5, 0.8, 1.5)
ROC_PFA = (0.3, 0.1, 0.03, 0.01, 1e-3, 1e-4, 1e-6)

#: Team sizes of the lambda2 study.
TEAM_SIZES = (5, 10, 17, 26, 36)
QUICK_TEAM_SIZES = (5, 17)


def _quick_changes(changes: dict) -> dict:
    out = dict(changes)
    for key in ("sdz", "cdz"):
        if out.get(key):
            out[key] = [_QUICK_ZONE]
    return out


def study_scenario(
    scenario: StudyScenario,
    method: Method,
    seeds: int,
    steps: int,
    filt: str = "ckf",
    quick: bool = False,
    seed: int = 0,
    robots: int | None = None,
) -> Scenario:
    """The validated :class:`Scenario` of one cell (all seeds as trials of one run)."""
    changes = _quick_changes(scenario.changes) if quick else dict(scenario.changes)
    extra = {} if robots is None else {"team.robots": int(robots)}
    return default_scenario().replace(
        **changes,
        **method.changes,
        **{
            "run.name": f"{scenario.key} / {method.key}",
            "run.trials": int(seeds),
            "run.steps": int(steps),
            "run.seed": int(seed),
            "run.filters": [filt],
            "run.dead_reckoning": False,
            **extra,
        },
    )


def nees_band(dof: int, samples: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided ``level`` chi-square band of an average of ``samples`` independent NEES.

    ``[chi2.ppf((1 - level) / 2, dof M) / M, chi2.ppf((1 + level) / 2, dof M) / M]`` with
    ``M = samples`` (Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4.2). The comparison uses
    ``M = seeds``: with relative measurements only, the team's absolute pose is unobservable,
    so all robots of a trial share one common error and their NEES are not independent;
    the trials are (``docs/beyond.md``).
    """
    m = int(samples)
    lo = chi2.ppf((1.0 - level) / 2.0, dof * m) / m
    hi = chi2.ppf((1.0 + level) / 2.0, dof * m) / m
    return float(lo), float(hi)


# ---------------------------------------------------------------------------- cells
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
        "bytes_per_step": est.bytes_per_trial() / est.series["msle"].shape[0],
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


def _describe(task: dict) -> dict:
    return {k: v for k, v in task.items() if k not in ("scenario", "params")}


def _run_cells(tasks: list[dict], study: Study) -> list[dict]:
    """Every cell: from the study's store, or computed on its backend (in task order)."""
    work = [_cell_task(t) for t in tasks]
    found: dict[str, Any] = {}
    todo = []
    for w in work:
        hit, value = study.lookup(w.keys[0])
        if hit:
            found[w.keys[0]] = value
        else:
            todo.append(w)
    found.update(study.run(todo, cells=len(work), from_store=len(found)))
    if study.failures:
        raise StudyFailedError(study.failures, study.stats)
    return [{"task": _describe(t), **found[w.keys[0]]} for t, w in zip(tasks, work, strict=True)]


def _roc_params(scenario: Scenario, thresholds: np.ndarray, seeds: int):
    """CLParams with a per-robot gate threshold: threshold k on trials k*seeds..k*seeds+s-1."""
    params = scenario.cl_params()
    per_trial = np.repeat(np.asarray(thresholds, float), seeds)
    rho = np.repeat(per_trial, scenario.world.team.robots)
    return dataclasses.replace(params, rho=rho)


# ---------------------------------------------------------------------------- result
def _est(samples) -> dict:
    e = mean_ci(samples)
    return {"mean": e.mean, "ci": e.half, "n": e.n}


@dataclass
class CompareResult:
    """Everything ``resloc compare`` measured (plain, JSON-ready data).

    Attributes
    ----------
    config : dict
        seeds, steps, filter, quick, jobs, wall time.
    table : list of dict
        Main table rows: scenario, method, metric -> {mean, ci, n}.
    fusion : list of dict
        Fusion-consistency rows on the default scenario.
    roc : list of dict
        One row per gate, attack and threshold: TPR / FPR with intervals.
    lambda2 : list of dict
        One row per team size and lambda2 mode.
    targets : list of dict
        The issue's targets with the measured values and whether they are met.
    """

    config: dict
    table: list[dict]
    fusion: list[dict]
    roc: list[dict]
    lambda2: list[dict]
    targets: list[dict]

    def to_dict(self) -> dict:
        """Plain mapping for JSON."""
        return dataclasses.asdict(self)

    def markdown(self) -> str:
        """The report section (Markdown)."""
        return _markdown(self)


def _summarize_cell(out: dict) -> dict:
    m = out["metrics"]
    return {
        "msle": _est(m["msle"]),
        "msle_final": _est(m["msle_final"]),
        "rmse": _est(m["rmse"]),
        "nees": _est(m["nees"]),
        "nees_rel": _est(m.get("nees_rel", [float("nan")])),
        "comm_rate": _est(m["comm_rate"]),
        "bytes_per_step": _est(m.get("bytes_per_step", [float("nan")])),
        "tpr": _est(m["tpr"]),
        "fpr": _est(m["fpr"]),
        "attacked_fused": _est(m["attacked_fused"]),
        "repairs": m["repairs"],
        "wall_time_s": m["wall_time_s"],
    }


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
    """Run the issue-6 comparison.

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
        tasks += _roc_tasks(quick, filt, steps if steps is not None else None, robots)
    if "lambda2" in studies:
        tasks += _lambda2_tasks(quick, seeds, filt, steps)

    total = len(tasks)
    if study is None:
        study = Study(
            jobs=jobs, progress=(lambda d, t: progress(int(d), int(t), "")) if progress else None
        )
    outputs = _run_cells(tasks, study)

    table = [_table_row(o) for o in outputs if o["task"]["study"] in ("table", "extra")]
    fusion = [_fusion_row(o, seeds) for o in outputs if o["task"]["study"] == "fusion"]
    roc = [row for o in outputs if o["task"]["study"] == "roc" for row in _roc_rows(o)]
    lam = [_lambda2_row(o) for o in outputs if o["task"]["study"] == "lambda2"]
    raw = {o["task"]["label"]: o["metrics"] for o in outputs}
    config = {
        "quick": quick,
        "seeds": seeds,
        "steps": steps,
        "filter": filt,
        "jobs": study.stats.workers,
        "study": study.stats.to_dict(),
        "robots": robots or default_scenario().world.team.robots,
        "wall_time_s": time.perf_counter() - t0,
        "cells": total,
    }
    targets = _targets(table, fusion, raw, seeds)
    return CompareResult(config, table, fusion, roc, lam, targets)


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


def _roc_tasks(quick: bool, filt: str, steps=None, robots=None) -> list[dict]:
    """Closed-loop ROC runs: gauge fusion, one threshold per group of trials."""
    seeds = 1 if quick else 3
    if steps is None:
        steps = 200 if quick else 650  # the SDZ is crossed within the first 650 steps
    rhos = ROC_RHO[::3] if quick else ROC_RHO
    pfas = ROC_PFA[::3] if quick else ROC_PFA
    tasks = []
    for attack in ("sdz_stealthy",) if quick else ("sdz_fixed", "sdz_stealthy"):
        sc = next(s for s in SCENARIOS if s.key == attack)
        for gate, values in (("raw-norm", rhos), ("nis", pfas)):
            changes = {"estimator.fusion": "gauge"}
            if gate == "nis":
                changes.update({"detector.norm": "nis"})
            me = Method(f"roc-{gate}", f"ROC {gate}", changes)
            scenario = study_scenario(
                sc, me, seeds * len(values), steps, filt, quick, robots=robots
            )
            thr = np.sqrt([chi2_gate(p) for p in values]) if gate == "nis" else np.asarray(values)
            tasks.append(
                {
                    "study": "roc",
                    "scenario_key": attack,
                    "method_key": gate,
                    "label": f"roc: {attack} / {gate}",
                    "values": list(values),
                    "seeds": seeds,
                    "scenario": scenario,
                    "params": _roc_params(scenario, thr, seeds),
                    "stride": 10,
                }
            )
    return tasks


def _lambda2_tasks(quick: bool, seeds: int, filt: str, steps=None) -> list[dict]:
    sizes = QUICK_TEAM_SIZES if quick else TEAM_SIZES
    if steps is None:
        steps = 200 if quick else 1000
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


def _table_row(o: dict) -> dict:
    t = o["task"]
    return {
        "study": t["study"],
        "scenario": t["scenario_key"],
        "scenario_label": t["scenario_label"],
        "method": t["method_key"],
        "method_label": t["method_label"],
        **_summarize_cell(o),
    }


def _fusion_row(o: dict, seeds: int) -> dict:
    t, m = o["task"], o["metrics"]
    lo, hi = nees_band(3, seeds)
    lo1, hi1 = nees_band(3, 1)
    per_seed = np.asarray(m["nees"], float)
    return {
        "method": t["method_key"],
        "method_label": t["method_label"],
        **_summarize_cell(o),
        "nees_band": [lo, hi],
        "nees_per_seed": per_seed.tolist(),
        "nees_seeds_in_band": float(np.mean((per_seed >= lo1) & (per_seed <= hi1))),
    }


def _roc_rows(o: dict) -> list[dict]:
    t, m = o["task"], o["metrics"]
    seeds = t["seeds"]
    rows = []
    for k, value in enumerate(t["values"]):
        sl = slice(k * seeds, (k + 1) * seeds)
        rows.append(
            {
                "attack": t["scenario_key"],
                "gate": t["method_key"],
                "threshold": value,
                "threshold_name": "p_fa" if t["method_key"] == "nis" else "rho",
                "tpr": _est(np.asarray(m["tpr"])[sl]),
                "fpr": _est(np.asarray(m["fpr"])[sl]),
                "msle": _est(np.asarray(m["msle"])[sl]),
            }
        )
    return rows


def _lambda2_row(o: dict) -> dict:
    t, m = o["task"], o["metrics"]
    row = {
        "robots": t["robots"],
        "mode": t["method_key"],
        "comm_rate": _est(m["comm_rate"]),
        "msle": _est(m["msle"]),
    }
    if "lambda2" in o:
        row["lambda2_true_mean"] = o["lambda2"]["true_mean"]
        if "estimate_mean" in o["lambda2"]:
            row["lambda2_estimate_mean"] = o["lambda2"]["estimate_mean"]
            row["lambda2_abs_rel_error"] = o["lambda2"]["abs_rel_error_after_warmup"]
    return row


def _find(rows: list[dict], scenario: str, method: str) -> dict | None:
    return next((r for r in rows if r["scenario"] == scenario and r["method"] == method), None)


def _targets(table: list[dict], fusion: list[dict], raw: dict, seeds: int) -> list[dict]:
    """The issue's quantitative targets, checked on the measurements."""
    out = []
    naive = next((r for r in fusion if r["method"] == NAIVE_REFERENCE), None)
    for r in fusion:
        if "nis" not in r["method"] or naive is None or r["method"] == NAIVE_REFERENCE:
            continue
        lo, hi = r["nees_band"]
        nees = r["nees"]["mean"]
        fac = r["msle"]["mean"] / naive["msle"]["mean"]
        out.append(
            {
                "target": (
                    f"fusion {r['method']}: NEES in band, MSLE <= 2x {NAIVE_REFERENCE} "
                    "(default scenario)"
                ),
                "measured": f"NEES {nees:.3g} (band {lo:.2f}-{hi:.2f}), MSLE x{fac:.3g}",
                "met": bool(lo <= nees <= hi and fac <= 2.0),
            }
        )
    for method in (BEST, PAPER):
        a = raw.get(f"table: sdz_stealthy / {method}")
        b = raw.get(f"table: clean / {method}")
        if a is None or b is None:
            continue
        est = ratio(a["msle"], b["msle"])
        fac = float(np.nanmean(a["msle"]) / np.nanmean(b["msle"]))
        met = fac <= 3.0 if method == BEST else fac > 3.0
        out.append(
            {
                "target": (
                    f"stealthy: {method} MSLE within 3x of its clean run"
                    if method == BEST
                    else "stealthy: the paper's configuration far worse than 3x of its clean run"
                ),
                "measured": f"ratio of means x{fac:.3g} (per-seed ratio {est.format('.3g')})",
                "met": bool(met),
            }
        )
    return out


# ---------------------------------------------------------------------------- output
def _fmt(e: dict, spec: str = ".3g") -> str:
    mean, half = e.get("mean"), e.get("ci")
    if mean is None or not math.isfinite(mean):
        return "-"
    if half is None or not math.isfinite(half):
        return f"{mean:{spec}}"
    return f"{mean:{spec}} ± {half:{spec}}"


def _markdown(res: CompareResult) -> str:
    c = res.config
    lines = [
        "## Beyond the paper: consistent fusion, unit-aware detection, stealthy attackers, "
        "local lambda2",
        "",
        f"`resloc compare{' --quick' if c['quick'] else ''}`: {c['robots']} robots "
        f"(arc-turn), filter {c['filter'].upper()}, {c['seeds']} seeds per cell, "
        f"{c['steps']} steps; means ± 95% Student-t half-widths over seeds; "
        f"{c['cells']} runs in {c['wall_time_s']:.0f} s with {c['jobs']} job(s). "
        "Methods and references: `docs/beyond.md`.",
        "",
    ]
    if c["quick"]:
        lines += [
            "*--quick is a smoke test (zones moved onto the first 200 steps, while the filters "
            "are still converging): its numbers and target checks are not the study's.*",
            "",
        ]
    if res.table:
        lines += [
            "### Method x scenario",
            "",
            "NEES rel.: the relative error's NEES (the team's least-squares rigid-body error "
            "removed). Bytes/step: every robot-to-robot frame (estimates, gauge "
            "acknowledgements, consensus) at the runtime's wire sizes.",
            "",
            "| scenario | method | MSLE | RMSE (m) | NEES | NEES rel. | comm. rate | bytes/step "
            "| TPR | FPR |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in res.table:
            lines.append(
                f"| {r['scenario_label']} | {r['method_label']} | {_fmt(r['msle'])} | "
                f"{_fmt(r['rmse'])} | {_fmt(r['nees'])} | {_fmt(r['nees_rel'])} | "
                f"{_fmt(r['comm_rate'], '.3f')} | {_fmt(r['bytes_per_step'], '.4g')} | "
                f"{_fmt(r['tpr'], '.3f')} | {_fmt(r['fpr'], '.3f')} |"
            )
        lines.append("")
    if res.fusion:
        lo, hi = res.fusion[0]["nees_band"]
        lines += [
            "### Fusion consistency (default scenario: SDZ random injections + CDZ)",
            "",
            f"NEES: the time-and-robot average of each seed, then the mean over seeds; the "
            f"95% chi-square band of a mean of {c['seeds']} independent 3-DoF NEES is "
            f"{lo:.2f}-{hi:.2f} (the robots of one trial share the team's unobservable "
            "absolute error, so the seeds are the independent samples). 'seeds in band': the "
            "share of seeds inside the single-trial band (0.22-9.35).",
            "",
            f"'MSLE / naive': against naive fusion with the same detector ({NAIVE_REFERENCE}).",
            "",
            "| fusion, detector | NEES | seeds in band | MSLE | MSLE / naive | RMSE (m) | "
            "comm. rate |",
            "|---|---|---|---|---|---|---|",
        ]
        ref = next((r for r in res.fusion if r["method"] == NAIVE_REFERENCE), res.fusion[0])
        naive = ref["msle"]["mean"]
        for r in res.fusion:
            lines.append(
                f"| {r['method_label']} | {_fmt(r['nees'])} | {r['nees_seeds_in_band']:.0%} | "
                f"{_fmt(r['msle'])} | {r['msle']['mean'] / naive:.3g} | {_fmt(r['rmse'])} | "
                f"{_fmt(r['comm_rate'], '.3f')} |"
            )
        lines.append("")
    if res.roc:
        lines += [
            "### Detector ROC (closed loop, gauge fusion; each threshold its own trials)",
            "",
            "| attack | gate | threshold | TPR | FPR | MSLE |",
            "|---|---|---|---|---|---|",
        ]
        for r in res.roc:
            lines.append(
                f"| {r['attack']} | {r['gate']} | {r['threshold_name']} = {r['threshold']:g} | "
                f"{_fmt(r['tpr'], '.3f')} | {_fmt(r['fpr'], '.4f')} | {_fmt(r['msle'])} |"
            )
        lines.append("")
    if res.lambda2:
        lines += [
            "### lambda2 and the trigger with team size (clean, paper's method)",
            "",
            "| N | lambda2 | true lambda2 (mean) | estimate error (mean abs. rel.) | "
            "comm. rate | MSLE |",
            "|---|---|---|---|---|---|",
        ]
        for r in res.lambda2:
            true = r.get("lambda2_true_mean")
            err = r.get("lambda2_abs_rel_error")
            lines.append(
                f"| {r['robots']} | {r['mode']} | {'-' if true is None else f'{true:.3g}'} | "
                f"{'-' if err is None else f'{err:.1%}'} | {_fmt(r['comm_rate'], '.3f')} | "
                f"{_fmt(r['msle'])} |"
            )
        lines.append("")
    if res.targets:
        lines += ["### Targets", "", "| target | measured | met |", "|---|---|---|"]
        for t in res.targets:
            lines.append(f"| {t['target']} | {t['measured']} | {'yes' if t['met'] else 'no'} |")
        lines.append("")
    return "\n".join(lines)


def save_compare(result: CompareResult, out: Path, plots: bool = True) -> list[Path]:
    """Write ``compare.json``, ``compare.md`` (the report section), ``roc.csv``,
    ``lambda2.csv`` and, with matplotlib and ``plots``, ``roc.png``."""
    from resloc.experiments.output import write_json

    out = Path(out)
    written = []
    p = out / "compare.json"
    write_json(p, result.to_dict())
    written.append(p)
    p = out / "compare.md"
    p.write_text(result.markdown() + "\n", encoding="utf-8")
    written.append(p)
    nan = float("nan")
    tables = {
        "roc.csv": (
            "attack,gate,threshold_name,threshold,tpr,fpr,msle",
            (
                f"{r['attack']},{r['gate']},{r['threshold_name']},{r['threshold']:g},"
                f"{r['tpr']['mean']:.6g},{r['fpr']['mean']:.6g},{r['msle']['mean']:.6g}"
                for r in result.roc
            ),
        ),
        "lambda2.csv": (
            "robots,mode,comm_rate,lambda2_true_mean,lambda2_abs_rel_error",
            (
                f"{r['robots']},{r['mode']},{r['comm_rate']['mean']:.6g},"
                f"{r.get('lambda2_true_mean', nan):.6g},{r.get('lambda2_abs_rel_error', nan):.6g}"
                for r in result.lambda2
            ),
        ),
    }
    for name, (header, rows) in tables.items():
        p = out / name
        p.write_text("".join(f"{line}\n" for line in (header, *rows)), encoding="utf-8")
        written.append(p)
    if plots and result.roc:
        try:
            from resloc.experiments.plots import pyplot

            plt = pyplot()
        except Exception:  # matplotlib missing: the CSV holds the curves
            plt = None
        if plt is not None:
            written.append(_plot_roc(plt, result, out / "roc.png"))
    return written


def _plot_roc(plt, result: CompareResult, path: Path) -> Path:
    fig, axes = plt.subplots(1, 2, figsize=(9, 4), sharey=True)
    for ax, attack in zip(axes, ("sdz_fixed", "sdz_stealthy"), strict=True):
        for gate, style in (("raw-norm", "o-"), ("nis", "s-")):
            rows = [r for r in result.roc if r["attack"] == attack and r["gate"] == gate]
            # Closed loop, the points need not be monotone: join them from the strictest
            # threshold to the loosest (large rho / small p_fa first).
            rows.sort(key=lambda r: -r["threshold"] if gate == "raw-norm" else r["threshold"])
            ax.plot(
                [r["fpr"]["mean"] for r in rows],
                [r["tpr"]["mean"] for r in rows],
                style,
                label=gate,
            )
        ax.set_xscale("symlog", linthresh=1e-3)
        ax.set_xlabel("false-alarm rate")
        ax.set_title(attack.replace("_", " "))
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("true-positive rate")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
