"""The reciprocal range check's numbers, computed from runs (nothing typed by hand).

Two modes:

``clean``: the false-alarm cost in the clean run (no SDZ, nothing attacked), per seed
(paired), CKF, the default scenario: the clean MSLE with no detector, with
``full+redundancy+sequence`` and with ``full+redundancy+sequence+reciprocal`` (also the
``zone+...`` variants' clean runs: without an SDZ the zone map is empty), and the share of
honest readings each discards::

    .venv/bin/python bench/reciprocal_report.py clean --seeds 4 --steps 300

``report``: the worst case per defence from ``resloc attack`` outputs (``attack.json``; the
same seeds and steps), with the per-seed ratios, the 3x verdict and the clean cost::

    .venv/bin/python bench/reciprocal_report.py report runs/reciprocal_300x4 \\
        runs/baseline_two_ended_300x4 --name reciprocal_300x4

Both write into ``docs/attack/`` (``reciprocal_clean_cost_<steps>x<seeds>.json``;
``<name>.md``, ``.csv``, ``.json``).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
from pathlib import Path

import numpy as np

DOCS = Path(__file__).resolve().parent.parent / "docs" / "attack"
CLEAN_RUNS = ("none", "full+redundancy+sequence", "full+redundancy+sequence+reciprocal")
TARGET = 3.0


def clean(seeds: int, steps: int) -> dict:
    from resloc.experiments.config import default_scenario
    from resloc.experiments.defences import DEFENCES
    from resloc.experiments.runner import run_scenario

    base = default_scenario().replace(
        **{
            "run.trials": seeds,
            "run.steps": steps,
            "run.filters": ["ckf"],
            "run.dead_reckoning": False,
            "sdz": [],
        }
    )
    out: dict = {"seeds": seeds, "steps": steps}
    for name in CLEAN_RUNS:
        changes = {"detector.enabled": False} if name == "none" else dict(DEFENCES[name])
        est = run_scenario(base.replace(**changes)).estimators["ckf"]
        out[name] = {
            "msle": est.per_trial("msle_mean").tolist(),
            "discarded_share": float(est.totals["detected"].sum() / est.totals["candidates"].sum()),
        }
        print(name, json.dumps(out[name]), flush=True)
    for name in CLEAN_RUNS[1:]:
        for ref in CLEAN_RUNS:
            if ref == name or CLEAN_RUNS.index(ref) > CLEAN_RUNS.index(name):
                continue
            ratio = np.divide(out[name]["msle"], out[ref]["msle"])
            out[f"{name} / {ref}"] = {
                "mean": float(ratio.mean()),
                "min": float(ratio.min()),
                "max": float(ratio.max()),
            }
            print(f"{name} / {ref}:", json.dumps(out[f"{name} / {ref}"]), flush=True)
    path = DOCS / f"reciprocal_clean_cost_{steps}x{seeds}.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"written {path}")
    return out


def _rows(studies: list[Path]) -> tuple[list[dict], dict]:
    """Per (defence, attacker point): per-seed MSLE ratios against the defence's clean run."""
    rows, config = [], {}
    for study in studies:
        data = json.loads((Path(study) / "attack.json").read_text())
        config.setdefault("seeds", data["config"]["seeds"])
        config.setdefault("steps", data["config"]["steps"])
        config.setdefault("commands", []).append(str(study))
        for defence, cells in data["cells"].items():
            clean_msle = np.asarray(cells["clean"]["msle"], float)
            family = {r["attacker"]: r["family"] for r in data["table"]}
            for label, m in cells.items():
                ratio = np.asarray(m["msle"], float) / clean_msle
                rows.append(
                    {
                        "defence": defence,
                        "attacker": label,
                        "family": family.get(label, label),
                        "clean_msle": float(clean_msle.mean()),
                        "ratio_mean": float(np.mean(ratio)),
                        "ratio_worst_seed": float(np.max(ratio)),
                        "ratio_best_seed": float(np.min(ratio)),
                        "seeds_over_3x": int(np.sum(ratio > TARGET)),
                        "seeds": len(ratio),
                        "per_seed": [float(v) for v in ratio],
                        "tpr": float(np.nanmean(m["tpr"])) if np.isfinite(m["tpr"]).any() else None,
                        "fpr": float(np.nanmean(m["fpr"])),
                        "nees_rel": float(np.mean(m["nees_rel"])),
                    }
                )
    return rows, config


def report(studies: list[Path], name: str) -> None:
    rows, config = _rows(studies)
    seeds, steps = config["seeds"], config["steps"]
    costs = [json.loads(p.read_text()) for p in sorted(DOCS.glob("reciprocal_clean_cost_*.json"))]
    defences = list(dict.fromkeys(r["defence"] for r in rows))
    lines = [
        f"# Reciprocal range check: {steps} steps x {seeds} seeds (computed)",
        "",
        f"Default scenario `arc-turn`, CKF. MSLE ratio: attacked / the same defence's clean run "
        f"on the same seed; 'worst seed' the largest per-seed ratio; the 3x target asks the "
        f"best defence's worst case within {TARGET:g}x on every seed. Generated by "
        "`bench/reciprocal_report.py` from the `resloc attack` outputs "
        f"{', '.join(f'`{c}`' for c in config['commands'])}.",
        "",
        "## Worst case per defence",
        "",
        "| defence | clean MSLE | worst attacker (by mean) | mean | worst seed | seeds > 3x | "
        "worst attacker (by seed) | its worst seed | 3x met |",
        "|---|---:|---|---:|---:|---:|---|---:|---|",
    ]
    for d in defences:
        mine = [r for r in rows if r["defence"] == d and r["attacker"] != "clean"]
        if not mine:
            continue
        by_mean = max(mine, key=lambda r: r["ratio_mean"])
        by_seed = max(mine, key=lambda r: r["ratio_worst_seed"])
        met = "yes" if by_seed["ratio_worst_seed"] <= TARGET else "no"
        lines.append(
            f"| {d} | {by_mean['clean_msle']:.3g} | {by_mean['attacker']} | "
            f"{by_mean['ratio_mean']:.3g} | {by_mean['ratio_worst_seed']:.3g} | "
            f"{by_mean['seeds_over_3x']} of {by_mean['seeds']} | {by_seed['attacker']} | "
            f"{by_seed['ratio_worst_seed']:.3g} | {met} |"
        )
    lines += [
        "",
        "## Every attacker point",
        "",
        "| defence | attacker | mean | worst seed | best seed | seeds > 3x | TPR | FPR | "
        "rel. NEES | per seed |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        if r["attacker"] == "clean":
            continue
        tpr = "-" if r["tpr"] is None else f"{r['tpr']:.2f}"
        lines.append(
            f"| {r['defence']} | {r['attacker']} | {r['ratio_mean']:.3g} | "
            f"{r['ratio_worst_seed']:.3g} | {r['ratio_best_seed']:.3g} | "
            f"{r['seeds_over_3x']} of {r['seeds']} | {tpr} | {r['fpr']:.4f} | "
            f"{r['nees_rel']:.3g} | {', '.join(f'{v:.3g}' for v in r['per_seed'])} |"
        )
    for cost in costs:
        lines += [
            "",
            f"## False alarms in the clean run ({cost['steps']} steps x {cost['seeds']} seeds, "
            "no SDZ, per seed against no detector)",
            "",
            "| defence | clean MSLE ratio mean | min | max | honest readings discarded |",
            "|---|---:|---:|---:|---:|",
        ]
        for d in CLEAN_RUNS[1:]:
            c = cost[f"{d} / none"]
            lines.append(
                f"| {d} | {c['mean']:.4f} | {c['min']:.4f} | {c['max']:.4f} | "
                f"{cost[d]['discarded_share']:.4f} |"
            )
        c = cost[f"{CLEAN_RUNS[2]} / {CLEAN_RUNS[1]}"]
        lines.append("")
        lines.append(
            f"The reciprocal check's own cost (with it / without it, per seed): mean "
            f"{c['mean']:.4f}, seeds {c['min']:.4f} to {c['max']:.4f}."
        )
    (DOCS / f"{name}.md").write_text("\n".join(lines) + "\n")
    buf = io.StringIO()
    fields = [k for k in rows[0] if k != "per_seed"] + ["per_seed"]
    w = csv.DictWriter(buf, fieldnames=fields)
    w.writeheader()
    for r in rows:
        w.writerow({**r, "per_seed": " ".join(f"{v:.6g}" for v in r["per_seed"])})
    (DOCS / f"{name}.csv").write_text(buf.getvalue())
    (DOCS / f"{name}.json").write_text(json.dumps({"config": config, "rows": rows}, indent=1))
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="mode", required=True)
    c = sub.add_parser("clean")
    c.add_argument("--seeds", type=int, default=4)
    c.add_argument("--steps", type=int, default=300)
    r = sub.add_parser("report")
    r.add_argument("studies", nargs="+", type=Path)
    r.add_argument("--name", required=True)
    args = parser.parse_args()
    if args.mode == "clean":
        clean(args.seeds, args.steps)
    else:
        report(args.studies, args.name)


if __name__ == "__main__":
    main()
