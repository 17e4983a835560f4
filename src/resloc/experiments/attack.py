"""The adversary study: every defence against every attacker of the suite, per-seed paired.

A *defence* is a name and dotted scenario overrides (detector, estimator, trigger options:
:data:`DEFENCES`, or any mapping a caller passes, so a defence added to ``cl/`` later is one
more entry, no code). An *attacker* is a strategy of :mod:`resloc.world.attackers`. For
each defence the study runs its clean run (no sensing danger zone: nothing attacked) and
one run per attacker, all on the same seeds (the world's random streams do not depend on
the attack, so seed ``s`` is the same world in every run), on the shared executor and
result store. Per seed it records the MSLE, NEES, relative NEES, detector TPR / FPR, the
communication rate and bytes; the table gives the mean ratio of attacked to clean MSLE
over seeds with its 95% confidence interval, and the worst attacker per defence. Its
files (markdown, CSV, JSON): :mod:`resloc.experiments.attack_report`.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from resloc.experiments.config import Scenario
from resloc.experiments.defences import DEFENCES
from resloc.experiments.executor import Study, StudyFailedError, Task
from resloc.experiments.stats import mean_ci, ratio
from resloc.experiments.store import canonical_json, cell_key

__all__ = [
    "CLEAN",
    "AttackStudyResult",
    "attack_cells",
    "attack_key",
    "protected_ratio",
    "run_attack_study",
]

#: The attacker name of a defence's clean run.
CLEAN = "clean"

#: Per-seed metrics of a cell.
CELL_METRICS = ("msle", "nees", "nees_rel", "tpr", "fpr", "comm_rate", "bytes_per_step")

#: Per-seed metric of a cell whose attacker runs robots: the MSLE of the other robots (the
#: clean run records it as ``msle_honest <ids>`` for each set of robots a point runs).
HONEST = "msle_honest"


def honest_name(owned) -> str:
    """The clean run's metric of the MSLE without robots ``owned``: ``msle_honest 5,10,15``."""
    return f"{HONEST} {','.join(str(int(i)) for i in owned)}"


def attack_cells(
    scenario: Scenario,
    defence: Mapping[str, Any],
    attacker_name: str,
    params: Mapping[str, Any],
    filt: str,
    first_trial: int = 0,
) -> list[dict]:
    """Run ``scenario`` (its ``run.trials`` seeds from ``first_trial``, batched) under
    ``defence`` against one attacker with ``params`` (or :data:`CLEAN`); one metrics
    mapping per seed (picklable; runs on a worker).

    An attacker that runs robots (``owned``) adds :data:`HONEST`, the MSLE without them;
    the clean run's ``params`` may name ``owned_sets`` (lists of ids), each adding
    :func:`honest_name` of the set, so that the two are paired on the same robots."""
    from resloc.experiments.runner import run_scenario
    from resloc.world.attackers import make_attacker

    changes = {**dict(defence), "run.filters": [filt], "run.dead_reckoning": False}
    adversary = None
    left_out = {}  # a metric's name -> the robots its MSLE leaves out
    if attacker_name == CLEAN:
        changes["sdz"] = []
        for ids in dict(params).get("owned_sets", []):
            left_out[honest_name(ids)] = np.asarray(ids, int)
    else:
        adversary = make_attacker(attacker_name, **dict(params))
        changes.update(adversary.overrides)
        owned = adversary.owned(scenario.world.team.robots)
        if owned.size:
            left_out[HONEST] = owned
    result = run_scenario(
        scenario.replace(**changes),
        adversary=adversary,
        first_trial=first_trial,
        without={m.removeprefix("msle_"): ids for m, ids in left_out.items()},  # (msle_<name>)
    )
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
        "bytes_per_step": est.bytes_per_step(result.scenario.estimator.fusion),
        **{m: est.per_trial(f"{m}_mean") for m in left_out},
    }
    return [{k: float(v[s]) for k, v in per_seed.items()} for s in range(scenario.run.trials)]


def attack_key(
    scenario_digest: str,
    defence: Mapping[str, Any],
    attacker_name: str,
    params: Mapping[str, Any],
    filt: str,
    trial: int,
) -> str:
    """Store key of one seed of one cell: the scenario (without ``run.trials``, so more
    seeds reuse the stored ones; ``scenario_digest`` of
    :func:`~resloc.experiments.cells.group_data`), the defence, the attacker and its
    parameters, the filter and the seed."""
    return cell_key(
        "attack",
        scenario=scenario_digest,
        defence=dict(defence),
        attacker=attacker_name,
        params=dict(params),
        filter=filt,
        trial=int(trial),
    )


@dataclass
class AttackStudyResult:
    """The defence x attacker study (plain, JSON-ready data).

    Attributes
    ----------
    cells : dict
        ``{defence: {attacker label: {metric: [per seed]}}}`` (one label per point of
        every attacker's parameter grid, :data:`CLEAN` included).
    table : list of dict
        One row per defence and attacker point (``attacker``: its label, ``family``: the
        strategy, ``params``): MSLE ratio to the clean run (mean, CI), relative NEES,
        NEES, TPR, FPR, communication rate and bytes per step.
    worst : list of dict
        The row of the worst attacker point (largest mean MSLE ratio) of every defence.
    config : dict
        Seeds, steps, filter, defences (their overrides), attackers, their summaries and
        searched grids.
    searched : list of dict
        Per defence and strategy, the row of its worst grid point (the defence x attacker
        table).
    protected : list of dict
        Per defence, the row of the worst attacker point by :func:`protected_ratio` (the
        MSLE over the robots the attacker does not run).
    """

    cells: dict
    table: list[dict]
    worst: list[dict]
    config: dict = field(default_factory=dict)
    searched: list[dict] = field(default_factory=list)
    protected: list[dict] = field(default_factory=list)


def run_attack_study(
    scenario: Scenario,
    defences: Mapping[str, Mapping[str, Any]] | None = None,
    attackers: Sequence[str] | None = None,
    seeds: int = 10,
    filt: str = "ckf",
    study: Study | None = None,
    search: bool = True,
) -> AttackStudyResult:
    """Every defence against its clean run and every attacker, on ``seeds`` paired seeds.

    Each attacker is run at every point of its parameter grid (``search``) and the worst
    point per defence is its entry in the defence x attacker table.

    Parameters
    ----------
    scenario : Scenario
        The base scenario (its sensing danger zones are where sensing attackers act).
    defences : mapping of str to mapping, optional
        ``{name: {dotted key: value}}`` (default :data:`DEFENCES`).
    attackers : sequence of str or (str, dict), optional
        Names in :data:`resloc.world.attackers.ATTACKERS` (searched over their grids), or
        ``(name, params)`` for one parameter point (default: every name).
    seeds : int
    filt : str
    study : Study, optional
        The executor and store (default: in this process, no store).
    search : bool
        Search every attacker's parameter grid (``False``: its defaults only).

    Returns
    -------
    AttackStudyResult

    Raises
    ------
    KeyError
        An unknown attacker name.
    """
    from resloc.experiments.cells import MAX_BATCH, contiguous_runs, group_data
    from resloc.world.attackers import ATTACKERS, attacker, make_attacker, variants

    defences = dict(DEFENCES if defences is None else defences)
    points: list[tuple[str, str, dict]] = [(CLEAN, CLEAN, {})]  # (family, label, params)
    grids: dict[str, list[str]] = {}
    for entry in ATTACKERS if attackers is None else attackers:
        if isinstance(entry, str):
            chosen = variants(entry) if search else [attacker(entry)]
        else:
            chosen = [make_attacker(entry[0], **dict(entry[1]))]
        for adv in chosen:
            if adv.label not in {label for _, label, _ in points}:
                points.append((adv.name, adv.label, dict(adv.params)))
                grids.setdefault(adv.name, []).append(adv.label)
    names = list(grids)
    owned_sets = sorted(
        {tuple(int(i) for i in make_attacker(f, **p).owned(scenario.world.team.robots))
         for f, _, p in points[1:]} - {()}
    )  # fmt: skip
    if owned_sets:  # the clean run's MSLE without each, paired with the attacked runs'
        points[0] = (CLEAN, CLEAN, {"owned_sets": [list(ids) for ids in owned_sets]})
    seeds = int(seeds)
    base = scenario.replace(**{"run.trials": seeds})
    digest = hashlib.sha256(canonical_json(group_data(base)).encode("utf-8")).hexdigest()
    study = Study(jobs=1) if study is None else study
    tasks, found = [], {}
    keys: dict[tuple[str, str], list[str]] = {}
    for dname, overrides in defences.items():
        for family, label, params in points:
            keys[dname, label] = [
                attack_key(digest, overrides, family, params, filt, s) for s in range(seeds)
            ]
            missing = []
            for s, key in enumerate(keys[dname, label]):
                hit, value = study.lookup(key)
                if hit:
                    found[key] = value
                else:
                    missing.append(s)
            for chunk in contiguous_runs(missing, MAX_BATCH):
                tasks.append(
                    Task(
                        attack_cells,
                        (
                            base.replace(**{"run.trials": len(chunk)}),
                            dict(overrides),
                            family,
                            params,
                            filt,
                            chunk[0],
                        ),
                        tuple(keys[dname, label][s] for s in chunk),
                        f"{dname} vs {label} seeds {chunk[0]}..{chunk[-1]}",
                        {"defence": dname, "overrides": dict(overrides), "attacker": label},
                        float(len(chunk) * base.run.steps),
                    )
                )
    cells_total = len(defences) * len(points) * seeds
    found.update(study.run(tasks, cells=cells_total, from_store=len(found)))
    if study.failures:
        raise StudyFailedError(study.failures, study.stats)
    cells: dict = {}
    for dname in defences:
        cells[dname] = {}
        for _, label, _ in points:
            per = [found[key] for key in keys[dname, label]]
            metrics = [*CELL_METRICS, *(m for m in per[0] if m.startswith(HONEST))]
            cells[dname][label] = {m: [p[m] for p in per] for m in metrics}
    family_of = {label: (family, params) for family, label, params in points}
    table = _table(cells, family_of, scenario.world.team.robots)
    searched, worst, protected = [], [], []
    for dname in defences:
        rows = [r for r in table if r["defence"] == dname and r["attacker"] != CLEAN]
        for name in names:
            mine = [r for r in rows if r["family"] == name]
            if mine:
                searched.append(max(mine, key=lambda r: _finite(r["msle_ratio"]["mean"])))
        if rows:
            worst.append(max(rows, key=lambda r: _finite(r["msle_ratio"]["mean"])))
            protected.append(max(rows, key=lambda r: _finite(protected_ratio(r))))
    config = {
        "seeds": seeds,
        "steps": base.run.steps,
        "filter": filt,
        "scenario": base.run.name,
        "defences": {k: dict(v) for k, v in defences.items()},
        "attackers": {n: ATTACKERS[n].summary for n in names},
        "grids": grids,
        "stats": study.stats.to_dict(),
    }
    return AttackStudyResult(cells, table, worst, config, searched, protected)


def protected_ratio(row: dict) -> float:
    """The mean MSLE ratio of what a defence can protect: over the robots the attacker does
    not run (``honest_ratio``) when it runs some, the whole team's otherwise. Why: a robot
    the attacker runs holds whatever estimate the attacker gives it (``own`` of the
    compromised attacker), so no defence bounds a metric that counts it."""
    honest = row.get("honest_ratio")
    return (row["msle_ratio"] if honest is None else honest)["mean"]


def _finite(v: float) -> float:
    return v if np.isfinite(v) else -np.inf


def _table(cells: dict, family_of: dict, robots: int) -> list[dict]:
    """One row per defence and attacker point; ``robots``: the team's size (which robots an
    attacker runs)."""
    from resloc.world.attackers import make_attacker

    rows = []
    for dname, per in cells.items():
        clean = per[CLEAN]
        for aname, m in per.items():
            family, params = family_of[aname]
            row = {
                "defence": dname,
                "attacker": aname,
                "family": family,
                "params": dict(params),
                "msle": mean_ci(m["msle"]).to_dict(),
                "msle_ratio": ratio(m["msle"], clean["msle"]).to_dict(),
                "msle_ratio_min": float(np.nanmin(np.divide(m["msle"], clean["msle"]))),
                "msle_ratio_max": float(np.nanmax(np.divide(m["msle"], clean["msle"]))),
                **{k: mean_ci(m[k]).to_dict() for k in CELL_METRICS if k != "msle"},
                "honest_ratio": None,
                "honest_ratio_max": None,
            }
            if HONEST in m:  # paired with the clean run's MSLE without the same robots
                owned = make_attacker(family, **params).owned(robots)
                reference = clean[honest_name(owned)]
                row["honest_ratio"] = ratio(m[HONEST], reference).to_dict()
                row["honest_ratio_max"] = float(np.nanmax(np.divide(m[HONEST], reference)))
            rows.append(row)
    return rows
