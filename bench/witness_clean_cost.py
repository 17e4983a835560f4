"""False-alarm cost of the witness stage in the clean run (no SDZ, nothing attacked).

Per seed (paired), CKF, the default scenario: the clean MSLE with no detector, with the best
defence before the stage (``zone+full+redundancy+sequence+cap+landmarks``) and with it
(``...+witness``), the share of honest readings each discards, and the bytes per step:

    .venv/bin/python bench/witness_clean_cost.py [--seeds 10] [--steps 1000] [--out FILE]

``docs/attack/witness.md`` quotes it.
"""

import argparse
import json
from pathlib import Path

from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.experiments.runner import run_scenario

BEST = "zone+full+redundancy+sequence+cap+landmarks"
RUNS = {
    "none": {"detector.enabled": False},
    BEST: dict(DEFENCES[BEST]),
    f"{BEST}+witness": dict(DEFENCES[f"{BEST}+witness"]),
}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--out", type=Path, default=Path("runs/witness_clean_cost.json"))
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
    out = {"seeds": args.seeds, "steps": args.steps}
    for name, overrides in RUNS.items():
        est = run_scenario(base.replace(**overrides)).estimators["ckf"]
        t = est.totals
        msle = est.per_trial("msle_mean")
        out[name] = {
            "msle": msle.tolist(),
            "discarded_share": float(t["detected"].sum() / t["candidates"].sum()),
            "bytes_per_step": est.bytes_per_step(base.estimator.fusion).tolist(),
        }
        print(name, f"MSLE {msle.mean():.4g}", f"discarded {out[name]['discarded_share']:.4f}")
        print("  bytes/step", f"{est.bytes_per_step(base.estimator.fusion).mean():.0f}", flush=True)
    none = out["none"]["msle"]
    for name in RUNS:
        ratio = [a / b for a, b in zip(out[name]["msle"], none, strict=True)]
        print(f"{name}: x{sum(ratio) / len(ratio):.4f} vs none, worst seed x{max(ratio):.4f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
