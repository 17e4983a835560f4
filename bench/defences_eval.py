"""Clean cost and attack ratios of the defences (experiments/defences.py) on the default
scenario, per trial paired (the same world trials for every defence). Writes JSON lines.

    python bench/defences_eval.py OUT.jsonl [TRIALS] [DEFENCE ...]
"""

from __future__ import annotations

import json
import sys
import time

from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.experiments.runner import run_scenario

CONDITIONS = {
    "clean": {"sdz": []},
    "random": {},
    "fixed_full": {"attack.kind": "fixed", "attack.links": "full"},
    "stealthy": {"attack.kind": "stealthy"},
    # Knows only the per-measurement gate (not the sequence tests): it does not hold back.
    "stealthy_gate": {"attack.kind": "stealthy", "attack.stealth_knowledge": "gate"},
    "replay": {"attack.kind": "replay"},
}


def main() -> None:
    out = sys.argv[1]
    trials = int(sys.argv[2]) if len(sys.argv) > 2 else 4
    names = [a for a in sys.argv[3:] if "=" not in a] or ["none", *DEFENCES]
    only = [a.split("=", 1)[1] for a in sys.argv[3:] if a.startswith("conditions=")]
    base = default_scenario().replace(
        **{"run.filters": ["ekf"], "run.dead_reckoning": False, "run.trials": trials}
    )
    with open(out, "a") as fh:
        for name in names:
            overrides = {"detector.enabled": False} if name == "none" else dict(DEFENCES[name])
            conditions = {"clean": CONDITIONS["clean"]} if name == "none" else CONDITIONS
            if only:
                conditions = {k: v for k, v in conditions.items() if k in only[0].split(",")}
            for cond, attack in conditions.items():
                t0 = time.time()
                res = run_scenario(base.replace(**overrides, **attack), seed=0)
                est = res.estimators["ekf"]
                row = {
                    "defence": name,
                    "condition": cond,
                    "trials": trials,
                    "msle_mean": est.per_trial("msle_mean").tolist(),
                    "comm_rate": est.per_trial("comm_rate").tolist(),
                    "wall_s": time.time() - t0,
                }
                fh.write(json.dumps(row) + "\n")
                fh.flush()
                print(name, cond, row["msle_mean"], f"{row['wall_s']:.0f}s", flush=True)


if __name__ == "__main__":
    main()
