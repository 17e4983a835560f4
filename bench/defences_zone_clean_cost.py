"""False-alarm cost in the clean run and the price of the map, for the zone defence.

Per seed (4 paired seeds, CKF), on the early-SDZ (300 steps) and default (1000 steps)
scenarios: the clean MSLE (no SDZ) without detector and with ``zone+full``, and the MSLE of
an honest run with the SDZ on the map but nothing attacked (``attack.link_fraction = 0``).
Writes ``runs/clean_cost.json``; ``docs/attack/defences.md`` quotes it.
"""

import json

from resloc.experiments.config import Scenario, default_scenario
from resloc.experiments.config_parse import load_scenario
from resloc.experiments.defences import DEFENCES
from resloc.experiments.runner import run_scenario

COMMON = {"run.trials": 4, "run.filters": ["ckf"], "run.dead_reckoning": False}
HONEST_ZONE = {"attack.links": "partial", "attack.link_fraction": 0.0}


def msle(base: Scenario, changes: dict) -> list[float]:
    result = run_scenario(base.replace(**{**COMMON, **changes}))
    return [float(v) for v in result.estimators["ckf"].per_trial("msle_mean")]


def main() -> None:
    out = {}
    scenarios = {
        "early": load_scenario("examples/attack/early_sdz.toml"),
        "default": default_scenario(),
    }
    for label, base in scenarios.items():
        zone = dict(DEFENCES["zone+full"])
        out[label] = {
            "none": msle(base, {"detector.enabled": False, "sdz": []}),
            "zone+full": msle(base, {**zone, "sdz": []}),
            "zone+full honest zone": msle(base, {**zone, **HONEST_ZONE}),
            "none honest zone": msle(base, {"detector.enabled": False, **HONEST_ZONE}),
        }
        print(label, json.dumps(out[label]), flush=True)
    with open("runs/clean_cost.json", "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
