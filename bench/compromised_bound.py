"""What any defence can do against compromised robots: fuse nothing they broadcast.

The ``compromised`` attacker's robots localize honestly and lie only in what they send (their
estimate of themselves, and its covariance). No detector can do better than a genie that
knows which robots those are and fuses none of their broadcasts: every link ``(i, j)`` with
``j`` compromised is dropped (its transmission fails) for every observer ``i``; the
compromised robots still fuse their own honest readings of the others. The genie runs in the
attacked run's scenario (the SDZ stays, so a zone-trust defence pays the map's price there
as in every attacked run; every sensor honest) and is compared, per seed, with the same
defence's clean run (no SDZ), the study's ratio (``resloc attack``). ``--robots 0`` is the
run with nothing dropped: the map's own price.

    .venv/bin/python bench/compromised_bound.py --seeds 10 --steps 1000 \
        --defence zone+full+redundancy+sequence+cap --robots 0 1 3 --out runs/compromised_bound.json

``docs/attack/compromised_long.md`` quotes it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from resloc.experiments.config import default_scenario
from resloc.experiments.defences import defence_overrides
from resloc.experiments.runner import run_scenario
from resloc.world.attackers import make_attacker


class DropBroadcasts:
    """Not an attacker: every link whose neighbour (``j``) is one of ``liars`` is never
    fused by its observer (its transmission fails); everything else as in the attacked
    run with honest messages."""

    name = "drop_broadcasts"
    grid = ({},)

    def __init__(self, liars: np.ndarray) -> None:
        self.liars = np.asarray(liars, int)
        self.summary = f"no robot fuses what robots {self.liars.tolist()} broadcast (a genie)"
        self.params: dict = {}
        self.overrides: dict = {"attack.kind": "stealthy"}

    def mark(self, sdz_attacked, step):
        return np.isin(step.j % step.robots, self.liars)

    def attack(self, links, step, params, memory):
        hit = np.isin(np.asarray(links.j) % step.robots, self.liars)
        return dataclasses.replace(links, channel_ok=links.channel_ok & ~hit)


def bound(
    defence: str, seeds: int, steps: int, robots: list[int], extra: dict | None = None
) -> dict:
    """Per-seed MSLE of the defence's clean run and of the genie for each liar count, and
    the paired ratios; ``extra``: more dotted scenario overrides (a defence's option)."""
    base = default_scenario().replace(
        **defence_overrides(defence),
        **(extra or {}),
        **{
            "run.trials": seeds,
            "run.steps": steps,
            "run.filters": ["ckf"],
            "run.dead_reckoning": False,
        },
    )
    clean = run_scenario(base.replace(sdz=[])).estimators["ckf"].per_trial("msle_mean")
    out = {"defence": defence, "set": extra or {}, "seeds": seeds, "steps": steps}
    out["clean"] = clean.tolist()
    for n in robots:
        liars = make_attacker("compromised", robots=n).targets(base.world.team.robots) if n else []
        genie = DropBroadcasts(np.asarray(liars, int))
        msle = run_scenario(base.replace(**genie.overrides), adversary=genie)
        per = msle.estimators["ckf"].per_trial("msle_mean")
        ratio = per / clean
        out[f"genie_{n}"] = {
            "liars": [int(x) for x in liars],
            "msle": per.tolist(),
            "ratio": ratio.tolist(),
            "ratio_mean": float(ratio.mean()),
            "ratio_worst": float(ratio.max()),
            "ratio_best": float(ratio.min()),
        }
        print(
            f"{defence}, {n} robot(s) dropped: genie / clean mean {ratio.mean():.3g}, "
            f"best {ratio.min():.3g}, worst {ratio.max():.3g}",
            flush=True,
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--defence", default="zone+full+redundancy+sequence+cap")
    ap.add_argument("--robots", type=int, nargs="+", default=[0, 1, 3])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=JSON")
    ap.add_argument("--out", type=Path, default=Path("runs/compromised_bound.json"))
    args = ap.parse_args()
    extra = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    out = bound(args.defence, args.seeds, args.steps, args.robots, extra)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
