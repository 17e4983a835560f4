"""The adversary study: every defence against every attacker of the suite, per-seed paired.

A *defence* is a name and dotted scenario overrides (detector, estimator, trigger options:
:data:`DEFENCES`, or any mapping a caller passes, so a defence added to ``cl/`` later is one
more entry, no code). An *attacker* is a strategy of :mod:`resloc.world.attackers`. For
each defence the study runs its clean run (no sensing danger zone: nothing attacked) and
one run per attacker, all on the same seeds (the world's random streams do not depend on
the attack, so seed ``s`` is the same world in every run), on the shared executor and
result store. Per seed it records the MSLE, NEES, relative NEES, detector TPR / FPR, the
communication rate and bytes; the table gives the mean ratio of attacked to clean MSLE
over seeds with its 95% confidence interval, and the worst attacker per defence.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from resloc.experiments.config import Scenario, scenario_to_dict
from resloc.experiments.defences import DEFENCES
from resloc.experiments.executor import Study, StudyFailedError, Task
from resloc.experiments.stats import mean_ci, ratio
from resloc.experiments.store import cell_key

__all__ = [
    "CLEAN",
    "AttackStudyResult",
    "attack_cells",
    "run_attack_study",
    "save_attack_study",
]

#: The attacker name of a defence's clean run.
CLEAN = "clean"

#: Per-seed metrics of a cell.
CELL_METRICS = ("msle", "nees", "nees_rel", "tpr", "fpr", "comm_rate", "bytes_per_step")


def attack_cells(
    scenario: Scenario, defence: Mapping[str, Any], attacker_name: str, filt: str
) -> list[dict]:
    """Run ``scenario`` (its ``run.trials`` seeds batched) under ``defence`` against one
    attacker (or :data:`CLEAN`); one metrics mapping per seed (picklable; runs on a worker).
    """
    from resloc.experiments.runner import run_scenario
    from resloc.world.attackers import attacker

    changes = {**dict(defence), "run.filters": [filt], "run.dead_reckoning": False}
    adversary = None
    if attacker_name == CLEAN:
        changes["sdz"] = []
    else:
        adversary = attacker(attacker_name)
        changes.update(adversary.overrides)
    result = run_scenario(scenario.replace(**changes), adversary=adversary)
    est = result.estimators[filt]
    t = est.totals
    with np.errstate(invalid="ignore", divide="ignore"):
        tpr = t["tp"] / (t["tp"] + t["fn"])
        fpr = t["fp"] / (t["fp"] + t["tn"])
    per_seed = {
        "msle": est.per_trial("msle_mean"),
        "nees": est.per_trial("nees_mean"),
        "nees_rel": est.per_trial("nees_rel_mean"),
        "tpr": tpr,
        "fpr": fpr,
        "comm_rate": est.per_trial("comm_rate"),
        "bytes_per_step": est.bytes_per_trial() / est.series["msle"].shape[0],
    }
    return [{k: float(v[s]) for k, v in per_seed.items()} for s in range(scenario.run.trials)]


@dataclass
class AttackStudyResult:
    """The defence x attacker study (plain, JSON-ready data).

    Attributes
    ----------
    cells : dict
        ``{defence: {attacker: {metric: [per seed]}}}`` (attacker :data:`CLEAN` included).
    table : list of dict
        One row per defence and attacker: MSLE ratio to the clean run (mean, CI), relative
        NEES, NEES, TPR, FPR, communication rate and bytes per step.
    worst : list of dict
        The row of the worst attacker (largest mean MSLE ratio) of every defence.
    config : dict
        Seeds, steps, filter, defences (their overrides), attackers and their summaries.
    """

    cells: dict
    table: list[dict]
    worst: list[dict]
    config: dict = field(default_factory=dict)


def run_attack_study(
    scenario: Scenario,
    defences: Mapping[str, Mapping[str, Any]] | None = None,
    attackers: Sequence[str] | None = None,
    seeds: int = 10,
    filt: str = "ckf",
    study: Study | None = None,
) -> AttackStudyResult:
    """Every defence against its clean run and every attacker, on ``seeds`` paired seeds.

    Parameters
    ----------
    scenario : Scenario
        The base scenario (its sensing danger zones are where sensing attackers act).
    defences : mapping of str to mapping, optional
        ``{name: {dotted key: value}}`` (default :data:`DEFENCES`).
    attackers : sequence of str, optional
        Names in :data:`resloc.world.attackers.ATTACKERS` (default: all).
    seeds : int
    filt : str
    study : Study, optional
        The executor and store (default: in this process, no store).

    Returns
    -------
    AttackStudyResult

    Raises
    ------
    KeyError
        An unknown attacker name.
    """
    from resloc.world.attackers import ATTACKERS, attacker

    defences = dict(DEFENCES if defences is None else defences)
    names = list(ATTACKERS if attackers is None else attackers)
    for name in names:
        attacker(name)
    base = scenario.replace(**{"run.trials": int(seeds)})
    group = scenario_to_dict(base)
    study = Study(jobs=1) if study is None else study
    cell_keys = {
        (dname, aname): tuple(
            cell_key(
                "attack",
                scenario=group,
                defence=dict(overrides),
                attacker=aname,
                filter=filt,
                trial=s,
            )
            for s in range(seeds)
        )
        for dname, overrides in defences.items()
        for aname in [CLEAN, *names]
    }
    tasks, found = [], {}
    for dname, overrides in defences.items():
        for aname in [CLEAN, *names]:
            keys = cell_keys[dname, aname]
            hits = [study.lookup(k) for k in keys]
            if all(h for h, _ in hits):
                found.update({k: v for k, (_, v) in zip(keys, hits, strict=True)})
                continue
            tasks.append(
                Task(
                    attack_cells,
                    (base, dict(overrides), aname, filt),
                    keys,
                    f"{dname} vs {aname}",
                    {"defence": dname, "overrides": dict(overrides), "attacker": aname},
                    float(seeds * base.run.steps),
                )
            )
    cells_total = len(defences) * (len(names) + 1) * seeds
    found.update(study.run(tasks, cells=cells_total, from_store=len(found)))
    if study.failures:
        raise StudyFailedError(study.failures, study.stats)
    cells: dict = {}
    for dname in defences:
        cells[dname] = {}
        for aname in [CLEAN, *names]:
            per = [found[key] for key in cell_keys[dname, aname]]
            cells[dname][aname] = {m: [p[m] for p in per] for m in CELL_METRICS}
    table = _table(cells)
    worst = []
    for dname in defences:
        rows = [r for r in table if r["defence"] == dname and r["attacker"] != CLEAN]
        if rows:
            worst.append(max(rows, key=lambda r: _finite(r["msle_ratio"]["mean"])))
    config = {
        "seeds": int(seeds),
        "steps": base.run.steps,
        "filter": filt,
        "scenario": base.run.name,
        "defences": {k: dict(v) for k, v in defences.items()},
        "attackers": {n: ATTACKERS[n].summary for n in names},
        "stats": study.stats.to_dict(),
    }
    return AttackStudyResult(cells, table, worst, config)


def _finite(v: float) -> float:
    return v if np.isfinite(v) else -np.inf


def _table(cells: dict) -> list[dict]:
    rows = []
    for dname, per in cells.items():
        clean = per[CLEAN]
        for aname, m in per.items():
            rows.append(
                {
                    "defence": dname,
                    "attacker": aname,
                    "msle": mean_ci(m["msle"]).to_dict(),
                    "msle_ratio": ratio(m["msle"], clean["msle"]).to_dict(),
                    "msle_ratio_min": float(np.nanmin(np.divide(m["msle"], clean["msle"]))),
                    **{k: mean_ci(m[k]).to_dict() for k in CELL_METRICS if k != "msle"},
                }
            )
    return rows


CSV_COLUMNS = (
    "defence",
    "attacker",
    "msle_ratio",
    "msle_ratio_ci",
    "msle_ratio_min",
    "msle",
    "nees",
    "nees_rel",
    "tpr",
    "fpr",
    "comm_rate",
    "bytes_per_step",
)


def _csv(result: AttackStudyResult) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(CSV_COLUMNS)
    for r in result.table:
        w.writerow(
            [
                r["defence"],
                r["attacker"],
                f"{r['msle_ratio']['mean']:.6g}",
                f"{r['msle_ratio']['ci_half']:.6g}",
                f"{r['msle_ratio_min']:.6g}",
                *(f"{r[k]['mean']:.6g}" for k in CSV_COLUMNS[5:]),
            ]
        )
    return buf.getvalue()


def _cell(e: dict, spec: str = ".3g") -> str:
    if not np.isfinite(e["mean"]):
        return "-"
    if not np.isfinite(e["ci_half"]):
        return f"{e['mean']:{spec}}"
    return f"{e['mean']:{spec}} ± {e['ci_half']:{spec}}"


def markdown(result: AttackStudyResult) -> str:
    """The study as a markdown section: worst cases first, then the full table."""
    c = result.config
    lines = [
        "## Defence x attacker",
        "",
        f"Scenario `{c['scenario']}`, {c['steps']} steps, {c['seeds']} seeds, "
        f"{c['filter'].upper()}. MSLE ratio: attacked / the same defence's clean run, per "
        "seed (same world), mean ± 95% CI over seeds; 'min': the smallest per-seed ratio. "
        "NEES rel.: NEES of the relative error (the team's least-squares rigid-body error "
        "removed). TPR / FPR: the detector on the links the attacker falsified / did not.",
        "",
        "### Worst case per defence",
        "",
        "| defence | worst attacker | MSLE ratio | min | NEES rel. | TPR | FPR |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in result.worst:
        lines.append(
            f"| {r['defence']} | {r['attacker']} | {_cell(r['msle_ratio'])} | "
            f"{r['msle_ratio_min']:.3g} | {_cell(r['nees_rel'])} | "
            f"{_cell(r['tpr'], '.2f')} | {_cell(r['fpr'], '.3f')} |"
        )
    lines += [
        "",
        "### Every defence and attacker",
        "",
        "| defence | attacker | MSLE ratio | MSLE | NEES | NEES rel. | TPR | FPR | comm. "
        "rate | bytes/step |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result.table:
        lines.append(
            f"| {r['defence']} | {r['attacker']} | {_cell(r['msle_ratio'])} | "
            f"{_cell(r['msle'])} | {_cell(r['nees'])} | {_cell(r['nees_rel'])} | "
            f"{_cell(r['tpr'], '.2f')} | {_cell(r['fpr'], '.3f')} | "
            f"{_cell(r['comm_rate'], '.3f')} | {_cell(r['bytes_per_step'], '.4g')} |"
        )
    lines += ["", "Defences (dotted overrides):", ""]
    for name, ov in c["defences"].items():
        lines.append(f"* `{name}`: `{json.dumps(ov)}`")
    lines += ["", "Attackers:", ""]
    for name, text in c["attackers"].items():
        lines.append(f"* `{name}`: {text}")
    return "\n".join(lines) + "\n"


def save_attack_study(result: AttackStudyResult, out: Path) -> list[Path]:
    """Write ``attack.md``, ``attack.csv`` and ``attack.json`` into ``out`` (atomically each)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "attack.md": markdown(result),
        "attack.csv": _csv(result),
        "attack.json": json.dumps(
            {
                "config": result.config,
                "worst": result.worst,
                "table": result.table,
                "cells": result.cells,
            },
            indent=1,
            default=float,
        ),
    }
    written = []
    for name, text in files.items():
        tmp = out / f".{name}.tmp"
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(out / name)
        written.append(out / name)
    return written
