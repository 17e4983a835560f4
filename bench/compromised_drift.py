"""Where the compromised robots' damage goes over a long run: team drift or relative error.

For each seed (its own run, so the recorded trial-0 track is that seed's), the default
scenario with a defence, clean and against ``compromised``; per step, the team's mean squared
position error split into its rigid-body part (the least-squares SE(2) motion of the team,
unobservable to relative measurements) and the relative part (what is left), the error of
the compromised robots' neighbours against the others, the attacker's lie per step (the
accepted shift, m) and the share of honest links discarded.

Usage::

    .venv/bin/python bench/compromised_drift.py --defence full+redundancy --seeds 2 \
        --steps 1000 --robots 3 --claimed-cov 0.01 --out docs/attack/compromised_drift.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from resloc.experiments.config import default_scenario
from resloc.experiments.defences import defence_overrides
from resloc.experiments.metrics import remove_team_rigid_motion
from resloc.experiments.runner import run_scenario
from resloc.world.attackers import make_attacker


def _split(truth: np.ndarray, track: np.ndarray) -> dict[str, np.ndarray]:
    """Per-step mean squared position error: total, rigid-body, relative, common translation."""
    err = track[..., :2] - truth[..., :2]
    total = (err**2).sum(-1).mean(-1)
    aligned = remove_team_rigid_motion(truth, track)
    rel = ((aligned[..., :2] - truth[..., :2]) ** 2).sum(-1).mean(-1)
    translation = (err.mean(1) ** 2).sum(-1)
    return {
        "total": total,
        "relative": rel,
        "rigid": total - rel,
        "translation": translation,
        "mean_x": err[..., 0].mean(1),
    }


class _Logged:
    """Wraps the attacker's tamper hook to record the accepted shift per step."""

    def __init__(self, adversary):
        self.adversary = adversary
        self.shifts: list[tuple[int, float, float]] = []

    def __getattr__(self, name):
        return getattr(self.adversary, name)

    def attack(self, links, step, params, memory):
        out = self.adversary.attack(links, step, params, memory)
        if out.tamper is None:
            return out
        inner = out.tamper
        log = self.shifts

        def tamper(rows, z_hat, S):
            z = inner(rows, z_hat, S)
            moved = np.hypot(*(z - links.z[rows]).T)
            if moved.size:
                log.append((int(step.k), float(moved.mean()), float(moved.max())))
            return z

        import dataclasses

        return dataclasses.replace(out, tamper=tamper)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--defence", default="full+redundancy")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--claimed-cov", type=float, default=0.01)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    base = default_scenario().replace(
        **defence_overrides(args.defence),
        **{
            "run.filters": ["ckf"],
            "run.dead_reckoning": False,
            "run.trials": 1,
            "run.steps": args.steps,
        },
    )
    report = []
    checkpoints = [k for k in (50, 100, 200, 300, 500, 700, 1000) if k <= args.steps]
    for seed in range(args.seeds):
        row = {"seed": seed}
        for label in ("clean", "attacked"):
            if label == "clean":
                res = run_scenario(base.replace(sdz=[]), first_trial=seed)
                logged = None
            else:
                adv = make_attacker("compromised", robots=args.robots, claimed_cov=args.claimed_cov)
                logged = _Logged(adv)
                res = run_scenario(
                    base.replace(**adv.overrides), adversary=logged, first_trial=seed
                )
            est = res.estimators["ckf"]
            parts = _split(res.truth, est.track)
            links = est.links
            liars = make_attacker("compromised", robots=args.robots).targets(res.truth.shape[1])
            honest = ~np.isin(links["j"], liars) & ~np.isin(links["i"], liars)
            victim_rows = np.isin(links["j"], liars)
            per = {}
            for k in checkpoints:
                per[k] = {name: float(v[k]) for name, v in parts.items()}
                window = (links["step"] > max(0, k - 50)) & (links["step"] <= k)
                per[k]["honest_discarded"] = float(links["detected"][honest & window].mean())
                per[k]["liar_links_discarded"] = float(
                    links["detected"][victim_rows & window].mean()
                )
            row[label] = {
                "msle": float(est.per_trial("msle_mean")[0]),
                "checkpoints": per,
            }
            if logged is not None:
                sh = np.array(logged.shifts)
                row[label]["shift_by_window"] = {
                    k: float(sh[(sh[:, 0] > max(0, k - 50)) & (sh[:, 0] <= k), 1].mean())
                    for k in checkpoints
                }
        row["ratio"] = row["attacked"]["msle"] / row["clean"]["msle"]
        report.append(row)
        print(json.dumps(row, indent=1))
    if args.out:
        args.out.write_text(
            json.dumps({"args": vars(args) | {"out": str(args.out)}, "seeds": report}, indent=1)
        )


if __name__ == "__main__":
    main()
