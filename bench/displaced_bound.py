"""What any defence can do against the displaced robot: isolate it, knowing its links.

The ``displaced`` attacker falsifies every link of one robot (its own readings and every
reading of it) consistently with that robot standing elsewhere. No detector can do better
than a genie that knows exactly which links those are and fuses none of them (the robot
then dead-reckons, and its neighbours lose it as a landmark). This script measures that
genie, per seed, against the same defence's clean run, on the default scenario (CKF):

    .venv/bin/python bench/displaced_bound.py [--seeds 10] [--steps 1000] [--defence NAME]

and writes ``runs/displaced_bound.json`` (``docs/attack/redundancy.md`` quotes it).
"""

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.experiments.lockstep import DEAD_RECKONING
from resloc.experiments.runner import run_scenario

#: The displaced attacker's target (``CoordinatedDisplacement.defaults["target"]``).
TARGET = 5


class Isolate:
    """Not an attacker: every link of robot ``TARGET`` (both directions) is never fused
    (its transmission fails), everything else as in the clean run."""

    name = "isolate"
    summary = "robot 5's links are never fused (a genie that knows the displaced robot)"
    grid = ({},)

    def __init__(self) -> None:
        self.params: dict = {}
        self.overrides: dict = {}

    def mark(self, sdz_attacked, step):
        return (step.i % step.robots == TARGET) | (step.j % step.robots == TARGET)

    def attack(self, links, step, params, memory):
        robots = step.robots
        hit = (links.i % robots == TARGET) | (np.asarray(links.j) % robots == TARGET)
        return dataclasses.replace(links, channel_ok=links.channel_ok & ~hit)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--defence", default="full+redundancy")
    args = parser.parse_args()
    base = default_scenario().replace(
        **{
            **DEFENCES[args.defence],
            "run.trials": args.seeds,
            "run.steps": args.steps,
            "run.filters": ["ckf"],
            "run.dead_reckoning": True,
            # No SDZ: the world's own zone attack stays off (the study's clean run).
            "sdz": [],
        }
    )
    clean = run_scenario(base)
    isolated = run_scenario(base, adversary=Isolate())
    out = {
        "defence": args.defence,
        "seeds": args.seeds,
        "steps": args.steps,
        "clean": clean.estimators["ckf"].per_trial("msle_mean").tolist(),
        "isolated": isolated.estimators["ckf"].per_trial("msle_mean").tolist(),
        "dead_reckoning": clean.estimators[DEAD_RECKONING].per_trial("msle_mean").tolist(),
    }
    ratio = np.divide(out["isolated"], out["clean"])
    out["ratio"] = ratio.tolist()
    print(json.dumps(out, indent=1))
    print(
        f"isolated / clean: mean {ratio.mean():.3g}, min {ratio.min():.3g},  max {ratio.max():.3g}"
    )
    Path("runs").mkdir(exist_ok=True)
    Path("runs/displaced_bound.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
