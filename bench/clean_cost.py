"""False-alarm cost of defences in the clean run (no SDZ, nothing attacked).

Per seed (paired), CKF, the default scenario: the clean MSLE with no detector and with each
defence named (``resloc.experiments.defences.DEFENCES``), the share of honest readings each
discards, the bytes per step on the radio, and every run's per-seed MSLE ratio to each run
before it (``"B / A"``: mean, min, max):

    .venv/bin/python bench/clean_cost.py full full+redundancy [--seeds 10] [--steps 1000] \
        [--out runs/defence_clean_cost.json]

``docs/attack/redundancy.md`` and ``docs/attack/witness.md`` quote it.
"""

import argparse
import json
from pathlib import Path

import numpy as np

from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.experiments.runner import run_scenario


def clean_cost(defences: list[str], seeds: int, steps: int) -> dict:
    """The record described in the module docstring (``"none"``: no detector, first)."""
    base = default_scenario().replace(
        **{
            "run.trials": seeds,
            "run.steps": steps,
            "run.filters": ["ckf"],
            "run.dead_reckoning": False,
            "sdz": [],
        }
    )
    runs = {"none": {"detector.enabled": False}, **{d: dict(DEFENCES[d]) for d in defences}}
    out: dict = {"seeds": seeds, "steps": steps}
    for name, changes in runs.items():
        est = run_scenario(base.replace(**changes)).estimators["ckf"]
        out[name] = {
            "msle": est.per_trial("msle_mean").tolist(),
            "discarded_share": float(est.totals["detected"].sum() / est.totals["candidates"].sum()),
            "bytes_per_step": est.bytes_per_step(base.estimator.fusion).tolist(),
        }
        print(name, f"MSLE {np.mean(out[name]['msle']):.4g}",
              f"discarded {out[name]['discarded_share']:.4f}",
              f"bytes/step {np.mean(out[name]['bytes_per_step']):.0f}", flush=True)  # fmt: skip
    names = list(runs)
    for k, name in enumerate(names):
        for ref in names[:k]:
            ratio = np.divide(out[name]["msle"], out[ref]["msle"])
            stats = {
                "mean": float(ratio.mean()),
                "min": float(ratio.min()),
                "max": float(ratio.max()),
            }
            out[f"{name} / {ref}"] = stats
            print(f"{name} / {ref}:", json.dumps(stats), flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("defences", nargs="+", choices=list(DEFENCES), metavar="DEFENCE")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--out", type=Path, default=Path("runs/defence_clean_cost.json"))
    args = parser.parse_args()
    out = clean_cost(args.defences, args.seeds, args.steps)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
