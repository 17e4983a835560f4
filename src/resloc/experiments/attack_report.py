"""The adversary study's files: ``attack.md`` (worst cases, the defence x attacker matrix,
every point), ``attack.csv`` (a row per defence and attacker point) and ``attack.json``
(everything), written atomically each (:func:`save_attack_study`)."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from resloc.experiments.attack import AttackStudyResult

__all__ = ["CSV_COLUMNS", "markdown", "save_attack_study"]

CSV_COLUMNS = (
    "defence",
    "attacker",
    "family",
    "params",
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
    "msle_ratio_max",
    "honest_ratio",
    "honest_ratio_ci",
    "honest_ratio_max",
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
                r["family"],
                json.dumps(r["params"], sort_keys=True),
                f"{r['msle_ratio']['mean']:.6g}",
                f"{r['msle_ratio']['ci_half']:.6g}",
                f"{r['msle_ratio_min']:.6g}",
                *(f"{r[k]['mean']:.6g}" for k in CSV_COLUMNS[7:14]),
                f"{r['msle_ratio_max']:.6g}",
                *(
                    ("", "", "")
                    if r["honest_ratio"] is None
                    else (
                        f"{r['honest_ratio']['mean']:.6g}",
                        f"{r['honest_ratio']['ci_half']:.6g}",
                        f"{r['honest_ratio_max']:.6g}",
                    )
                ),
            ]
        )
    return buf.getvalue()


def _cell(e: dict, spec: str = ".3g") -> str:
    if not np.isfinite(e["mean"]):
        return "-"
    if not np.isfinite(e["ci_half"]):
        return f"{e['mean']:{spec}}"
    return f"{e['mean']:{spec}} ± {e['ci_half']:{spec}}"


def _matrix(result: AttackStudyResult) -> list[str]:
    """Defence x attacker: the worst point of each attacker's search per defence."""
    families = list(result.config["attackers"])
    by = {(r["defence"], r["family"]): r for r in result.searched}
    lines = [
        "| defence | " + " | ".join(families) + " |",
        "|---|" + "---|" * len(families),
    ]
    for dname in result.config["defences"]:
        cells = []
        for f in families:
            r = by.get((dname, f))
            cells.append("-" if r is None else f"{r['msle_ratio']['mean']:.3g}")
        lines.append(f"| {dname} | " + " | ".join(cells) + " |")
    return lines


def _honest_cell(r: dict) -> str:
    if r.get("honest_ratio") is None:
        return "-"
    return f"{_cell(r['honest_ratio'])} (max {r['honest_ratio_max']:.3g})"


def _worst_line(r: dict) -> str:
    return (
        f"| {r['defence']} | {r['attacker']} | {_cell(r['msle_ratio'])} | "
        f"{r['msle_ratio_min']:.3g} | {r['msle_ratio_max']:.3g} | {_honest_cell(r)} | "
        f"{_cell(r['nees_rel'])} | {_cell(r['tpr'], '.2f')} | {_cell(r['fpr'], '.3f')} |"
    )


def markdown(result: AttackStudyResult) -> str:
    """The study as a markdown section: worst cases first, the defence x attacker matrix
    (worst point of each attacker's search), then every point."""
    c = result.config
    lines = [
        "## Defence x attacker",
        "",
        f"Scenario `{c['scenario']}`, {c['steps']} steps, {c['seeds']} seeds, "
        f"{c['filter'].upper()}. MSLE ratio: attacked / the same defence's clean run, per "
        "seed (same world), mean ± 95% CI over seeds; 'min': the smallest per-seed ratio. "
        "NEES rel.: NEES of the relative error (the team's least-squares rigid-body error "
        "removed). TPR / FPR: the detector on the links the attacker falsified / did not. "
        "Every attacker is run at each of its parameter points listed under 'Searched' "
        "below (its whole grid unless pinned) against every defence; an attacker's entry is "
        "its worst point (largest mean MSLE ratio) for that defence. 'Honest robots': "
        "against an attacker that runs robots (compromised robots), the same ratio over "
        "the other robots only, paired with the clean run's MSLE over the same robots "
        "(the robots it runs hold whatever estimate it gives them).",
        "",
        "### Worst case per defence",
        "",
        "| defence | worst attacker | MSLE ratio | min | max | honest robots | NEES rel. | "
        "TPR | FPR |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result.worst:
        lines.append(_worst_line(r))
    lines += [
        "",
        "### Worst case per defence over the robots the attacker does not run",
        "",
        "| defence | worst attacker | MSLE ratio | min | max | honest robots | NEES rel. | "
        "TPR | FPR |",
        "|---|---|---|---|---|---|---|---|---|",
        *(_worst_line(r) for r in result.protected),
    ]
    lines += [
        "",
        "### Defence x attacker (mean MSLE ratio at the attacker's worst grid point)",
        "",
        *_matrix(result),
        "",
        "### Every defence and attacker point",
        "",
        "| defence | attacker | MSLE ratio | honest robots | MSLE | NEES | NEES rel. | TPR | "
        "FPR | comm. rate | bytes/step |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result.table:
        lines.append(
            f"| {r['defence']} | {r['attacker']} | {_cell(r['msle_ratio'])} | "
            f"{_honest_cell(r)} | {_cell(r['msle'])} | {_cell(r['nees'])} | "
            f"{_cell(r['nees_rel'])} | "
            f"{_cell(r['tpr'], '.2f')} | {_cell(r['fpr'], '.3f')} | "
            f"{_cell(r['comm_rate'], '.3f')} | {_cell(r['bytes_per_step'], '.4g')} |"
        )
    lines += ["", "Defences (dotted overrides):", ""]
    for name, ov in c["defences"].items():
        lines.append(f"* `{name}`: `{json.dumps(ov)}`")
    lines += ["", "Attackers (default parameters) and the grid searched per defence:", ""]
    for name, text in c["attackers"].items():
        grid = ", ".join(f"`{g}`" for g in c.get("grids", {}).get(name, []))
        lines.append(f"* `{name}`: {text}. Searched: {grid}")
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
                "protected": result.protected,
                "searched": result.searched,
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
