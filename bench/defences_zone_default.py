"""The zone defence on the default scenario (1000 steps, 4 paired seeds): its clean run, an
honest run with the SDZ on the map but nothing attacked (the price of the map), and the
two strongest early-SDZ attackers. Writes runs/default_zone.json."""

import json

from resloc.experiments.attack import run_attack_study
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.experiments.runner import run_scenario

SEEDS = 4
base = default_scenario()
out = {}
for name in ("zone+full",):
    honest = base.replace(
        **{
            **DEFENCES[name],
            "run.trials": SEEDS,
            "run.filters": ["ckf"],
            "run.dead_reckoning": False,
            "attack.links": "partial",
            "attack.link_fraction": 0.0,
        }
    )
    out[name + " honest zone"] = list(run_scenario(honest).estimators["ckf"].per_trial("msle_mean"))
    print(out, flush=True)
    res = run_attack_study(base, {name: DEFENCES[name]}, ["range_bias", "rotation"], seeds=SEEDS)
    out[name] = res.cells[name]
    print(json.dumps(out), flush=True)
with open("runs/default_zone.json", "w") as f:
    json.dump(out, f, indent=1)
