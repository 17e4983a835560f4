"""Where and when compromised robots hurt over a long run: per robot, per window, per link.

One seed (its own run, so the recorded trial-0 track is that seed's), the default scenario
with a defence, clean (no SDZ, the study's clean run) and against ``compromised``. Per
window of steps: the MSLE (gauge-free: pairwise distances), the robots that carry it (each
robot's share of the MSLE sum), how many robots' estimates are inside the mapped SDZ, the
lie per fused link from a compromised robot (m), split by whether the victim's estimate is
inside the map and by whether the liar's is, and the share of honest links and of the
compromised robots' links the detector discarded (zone trust's withheld rows included),
split by the observer's estimate inside or outside the map. ``--window A B`` lets the
attacker lie only in steps ``[A, B)`` (ablation: which part of the run the damage comes from).

    .venv/bin/python bench/compromised_windows.py --seed 8 --robots 1 --claimed-cov 0.01 \
        --steps 700 --defence zone+full+redundancy+sequence+cap
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from resloc.cl.detection_zone import inside_zone_map, zone_map
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import defence_overrides
from resloc.experiments.metrics import pair_distances
from resloc.experiments.runner import run_scenario
from resloc.world.attackers import make_attacker


class Logged:
    """The attacker, lying only in steps ``[start, stop)``, its sent lies recorded."""

    def __init__(self, adversary, start: int, stop: int):
        self.adversary = adversary
        self.start, self.stop = start, stop
        self.lies: list[tuple[int, int, int, float]] = []  # step, victim, liar, |shift| m

    def __getattr__(self, name):
        return getattr(self.adversary, name)

    def attack(self, links, step, params, memory):
        if not (self.start <= step.k < self.stop):
            return dataclasses.replace(links, tamper=None)
        out = self.adversary.attack(links, step, params, memory)
        if out.tamper is None:
            return out
        inner, log = out.tamper, self.lies

        def tamper(rows, z_hat, S):
            z = inner(rows, z_hat, S)

            # The lie as a shift of the broadcast position: the change of the relative
            # position read (exact for the injected equivalent reading).
            def rel(zz):
                return zz[:, 0:1] * np.column_stack([np.cos(zz[:, 1]), np.sin(zz[:, 1])])

            moved = np.hypot(*(rel(z) - rel(links.z[rows])).T)
            for r, m in zip(rows, moved, strict=True):
                if m > 0:
                    log.append((int(step.k), int(links.i[r]), int(links.j[r]), float(m)))
            return z

        for attr in ("reported", "notes"):  # what the partners report, the liars' notes
            if hasattr(inner, attr):
                setattr(tamper, attr, getattr(inner, attr))
        return dataclasses.replace(out, tamper=tamper)


def per_robot_msle(truth, track):
    """(T, N): each robot's row of the MSLE sum (sums over robots to the MSLE)."""
    d = (pair_distances(truth[..., :2]) - pair_distances(track[..., :2])) ** 2
    return d.sum(-1) / truth.shape[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--defence", default="zone+full+redundancy+sequence+cap")
    ap.add_argument("--seed", type=int, default=8)
    ap.add_argument("--steps", type=int, default=700)
    ap.add_argument("--robots", type=int, default=1)
    ap.add_argument("--claimed-cov", type=float, default=0.01)
    ap.add_argument("--window", type=int, nargs=2, default=None)
    ap.add_argument("--every", type=int, default=50)
    ap.add_argument("--no-clean", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument(
        "--set", action="append", default=[], metavar="KEY=JSON",
        help="a scenario override (e.g. run.seed=1: the held-out seeds)",
    )  # fmt: skip
    args = ap.parse_args()
    extra = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    base = default_scenario().replace(
        **defence_overrides(args.defence),
        **extra,
        **{
            "run.filters": ["ckf"],
            "run.dead_reckoning": False,
            "run.trials": 1,
            "run.steps": args.steps,
        },
    )
    discs = zone_map([(z.center, z.radius) for z in base.world.sdz])
    report: dict = {
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    }
    if not args.no_clean:
        clean = run_scenario(base.replace(sdz=[]), first_trial=args.seed)
        report["clean_msle"] = float(clean.estimators["ckf"].per_trial("msle_mean")[0])
        clean_pr = per_robot_msle(clean.truth, clean.estimators["ckf"].track)
    adv = make_attacker("compromised", robots=args.robots, claimed_cov=args.claimed_cov)
    start, stop = args.window or (0, args.steps + 1)
    logged = Logged(adv, start, stop)
    res = run_scenario(base.replace(**adv.overrides), adversary=logged, first_trial=args.seed)
    est = res.estimators["ckf"]
    report["attacked_msle"] = float(est.per_trial("msle_mean")[0])
    if "clean_msle" in report:
        report["ratio"] = report["attacked_msle"] / report["clean_msle"]
    N = res.truth.shape[1]
    liars = adv.targets(N)
    pr = per_robot_msle(res.truth, est.track)  # (T, N)
    inside = np.stack([inside_zone_map(est.track[k, :, :2], discs) for k in range(len(est.track))])
    L = est.links
    step, i, j = (np.asarray(L[k]) for k in ("step", "i", "j"))
    i, j = i % N, j % N
    fused, detected = np.asarray(L["fused"], bool), np.asarray(L["detected"], bool)
    delivered = np.asarray(L["delivered"], bool)
    obs_in = inside[np.minimum(step, len(inside) - 1), i]
    from_liar = np.isin(j, liars)
    honest = ~from_liar & ~np.isin(i, liars)
    lies = np.array(logged.lies) if logged.lies else np.zeros((0, 4))
    lie_key = {(int(a), int(b) % N, int(c) % N): m for a, b, c, m in lies}
    lie_m = np.array(
        [lie_key.get((int(s), int(a), int(b)), 0.0) for s, a, b in zip(step, i, j, strict=True)]
    )
    windows = []
    for k0 in range(0, args.steps, args.every):
        k1 = k0 + args.every
        every = (step > k0) & (step <= k1)
        w = every & delivered
        row = {
            "steps": [k0, k1],
            "msle": float(pr[k0 + 1 : k1 + 1].sum(1).mean()),
            "in_map": float(inside[k0 + 1 : k1 + 1].sum(1).mean()),
            "top_robots": [
                (int(r), float(pr[k0 + 1 : k1 + 1, r].mean()))
                for r in np.argsort(-pr[k0 + 1 : k1 + 1].mean(0))[:4]
            ],
        }
        row["liars_in_map"] = {int(r): float(inside[k0 + 1 : k1 + 1, r].mean()) for r in liars}
        liar_in = inside[np.minimum(step, len(inside) - 1), j]
        for tag, sel in (("liar_out", ~liar_in), ("liar_in", liar_in)):
            lw = w & from_liar & sel & fused
            row[f"lie_fused_mean_m_{tag}"] = float(lie_m[lw].mean()) if lw.any() else None
            row[f"lie_fused_links_{tag}"] = int(lw.sum())
        if "clean_msle" in report:
            row["clean_msle"] = float(clean_pr[k0 + 1 : k1 + 1].sum(1).mean())
        for tag, sel in (("victim_out", ~obs_in), ("victim_in", obs_in)):
            lw = w & from_liar & sel
            row[f"liar_links_{tag}"] = int(lw.sum())
            row[f"liar_fused_{tag}"] = float(fused[lw].mean()) if lw.any() else None
            row[f"lie_fused_mean_m_{tag}"] = (
                float(lie_m[lw & fused].mean()) if (lw & fused).any() else None
            )
            hw = every & honest & sel
            row[f"honest_discarded_{tag}"] = float(detected[hw].mean()) if hw.any() else None
            lw = every & from_liar & sel
            row[f"liar_discarded_{tag}"] = float(detected[lw].mean()) if lw.any() else None
        windows.append(row)
        print(json.dumps(row), flush=True)
    report["windows"] = windows
    print(json.dumps({k: v for k, v in report.items() if k != "windows"}), flush=True)
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
