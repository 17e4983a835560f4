"""False-alarm cost of the redundancy stage in the clean run (no SDZ, nothing attacked).

Per seed (paired), CKF, the default scenario: the clean MSLE with no detector, with ``full``
and with ``full+redundancy`` (which is also ``zone+full+redundancy``'s clean run: without an
SDZ the zone map is empty), and the share of honest readings each one discards:

    .venv/bin/python bench/redundancy_clean_cost.py [--seeds 10] [--steps 1000]

Writes ``runs/redundancy_clean_cost.json``; ``docs/attack/redundancy.md`` quotes it.
"""

import argparse
import json
from pathlib import Path

import numpy as np

from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.experiments.runner import run_scenario

RUNS = {
    "none": {"detector.enabled": False},
    "full": dict(DEFENCES["full"]),
    "full+redundancy": dict(DEFENCES["full+redundancy"]),
}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args()
    base = default_scenario().replace(
        **{
            "run.trials": args.seeds,
            "run.steps": args.steps,
            "run.filters": ["ckf"],
            "run.dead_reckoning": False,
            "sdz": [],
        }
    )
    out: dict = {"seeds": args.seeds, "steps": args.steps}
    for name, changes in RUNS.items():
        est = run_scenario(base.replace(**changes)).estimators["ckf"]
        out[name] = {
            "msle": est.per_trial("msle_mean").tolist(),
            "discarded_share": float(est.totals["detected"].sum() / est.totals["candidates"].sum()),
        }
        print(name, json.dumps(out[name]), flush=True)
    for name in ("full", "full+redundancy"):
        for ref in ("none", "full"):
            if ref == name:
                continue
            ratio = np.divide(out[name]["msle"], out[ref]["msle"])
            out[f"{name} / {ref}"] = {
                "mean": float(ratio.mean()),
                "min": float(ratio.min()),
                "max": float(ratio.max()),
            }
            print(f"{name} / {ref}:", json.dumps(out[f"{name} / {ref}"]), flush=True)
    Path("runs").mkdir(exist_ok=True)
    Path("runs/redundancy_clean_cost.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
