"""The compromised robots against a defence over long runs, all seeds in one batched run.

The study's cells (``resloc attack``) run one seed each; this runs the same scenario, defence
and attacker points with every seed batched (the same per-seed worlds and results, several
times faster on a loaded machine), clean run (no SDZ) included, and prints the per-seed MSLE
ratios. Extra scenario overrides (``--set key=value``, JSON values) vary a defence's option;
``--honest`` also reports the MSLE over the honest robots only (the compromised robots'
own estimates left out, in the clean run too), beside the paper's MSLE of every robot.

    .venv/bin/python bench/compromised_long.py \
        --defence zone+full+redundancy+sequence+cap+landmarks \
        --set detector.zone_landmarks_inflation=100 --seeds 10 --steps 1000 --out runs/long.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from resloc.experiments.config import default_scenario
from resloc.experiments.defences import defence_overrides
from resloc.experiments.runner import run_scenario
from resloc.world.attackers import make_attacker

#: The suite's grid of the compromised attacker.
POINTS = ({"robots": 1}, {"robots": 1, "claimed_cov": 0.01}, {"robots": 3, "claimed_cov": 0.01})
#: Not in the suite's grid: three robots claiming their honest covariance (against the
#: witness stage a small claim tightens the liar's own test, docs/attack/witness.md).
POINTS = (*POINTS, {"robots": 3})


def honest_msle_series(robot_counts: list[int]) -> dict[str, np.ndarray]:
    """The ``without`` of :func:`~resloc.experiments.runner.run_scenario` that also records,
    for each count ``r`` of compromised robots, the MSLE of the team without the first ``r``
    ids of :data:`~resloc.world.attackers.estimates.COMPROMISED_ORDER` (series
    ``msle_honest{r}``, beside ``msle``; in the clean run too, so that the ratio is paired on
    the same robots). Why beside and not instead: the paper's MSLE counts every robot, the
    compromised ones' own estimates included (``docs/attack/own_estimates.md``)."""
    from resloc.world.attackers.estimates import COMPROMISED_ORDER

    robots = default_scenario().world.team.robots
    order = [t for t in COMPROMISED_ORDER if t < robots]
    return {f"honest{r}": np.asarray(order[:r], int) for r in robot_counts}


def reused_clean(path: Path, run: dict) -> np.ndarray:
    """The per-seed clean MSLE of an earlier run (its JSON), which must have been run with
    the same defence, overrides, seeds, steps and first trial as ``run`` (``ValueError``
    naming the field that differs otherwise)."""
    earlier = json.loads(path.read_text())
    for key in ("defence", "set", "seeds", "steps", "first_trial"):
        if earlier.get(key) != run.get(key):
            raise ValueError(
                f"--clean-from {path}: its {key} is {earlier.get(key)!r}, this run's "
                f"{run.get(key)!r}; run the clean run again (drop --clean-from)"
            )
    return np.asarray(earlier["clean"], float)


def reused_clean_honest(path: Path, counts: list[int]) -> dict[str, list[float]]:
    """The honest robots' clean MSLE of an earlier ``--honest`` run (its JSON) for each
    count of compromised robots in ``counts`` (``ValueError`` naming the count it lacks)."""
    held = json.loads(path.read_text()).get("clean_honest", {})
    missing = [r for r in counts if str(r) not in held]
    if missing:
        raise ValueError(
            f"--clean-from {path}: it has no honest clean MSLE for {missing[0]} compromised "
            "robot(s) (run it with --honest and those points, or drop --clean-from)"
        )
    return {str(r): held[str(r)] for r in counts}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--defence", required=True)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=JSON")
    ap.add_argument(
        "--attack", action="append", default=[], metavar="KEY=JSON",
        help="an attacker parameter added to every point (e.g. give_up=1)",
    )  # fmt: skip
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument(
        "--first-trial", type=int, default=0,
        help="the first trial (seed run.seed.T) of the batch: one seed alone, for diagnosis",
    )  # fmt: skip
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--points", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument(
        "--clean-from", type=Path, default=None,
        help="reuse the clean MSLE of an earlier run's JSON (same defence, --set, seeds, "
        "steps, first trial; checked) instead of running it again",
    )  # fmt: skip
    ap.add_argument(
        "--honest", action="store_true",
        help="also report the MSLE over the honest robots only (clean run included; "
        "with --clean-from, that run's must have been recorded)",
    )  # fmt: skip
    args = ap.parse_args()
    extra = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    counts = sorted({int({**POINTS[p]}.get("robots", 1)) for p in args.points})
    without = honest_msle_series(counts) if args.honest else None
    attack = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.attack)}
    base = default_scenario().replace(
        **defence_overrides(args.defence),
        **extra,
        **{
            "run.trials": args.seeds,
            "run.steps": args.steps,
            "run.filters": ["ckf"],
            "run.dead_reckoning": False,
        },
    )
    first = {"first_trial": args.first_trial}
    out = {"defence": args.defence, "set": extra, "seeds": args.seeds, "steps": args.steps}
    if args.first_trial:
        out["first_trial"] = args.first_trial
    if args.clean_from:
        try:
            clean = reused_clean(args.clean_from, out)
            if args.honest:
                out["clean_honest"] = reused_clean_honest(args.clean_from, counts)
        except ValueError as exc:
            print(exc, file=sys.stderr)
            raise SystemExit(2) from None
        out["clean_from"] = str(args.clean_from)
    else:
        clean_run = run_scenario(base.replace(sdz=[]), **first, without=without).estimators["ckf"]
        clean = clean_run.per_trial("msle_mean")
        if args.honest:
            out["clean_honest"] = {
                str(r): clean_run.per_trial(f"msle_honest{r}_mean").tolist() for r in counts
            }
    if attack:
        out["attack"] = attack
    out["clean"] = clean.tolist()
    print(f"{args.defence} {extra}: clean MSLE {clean.mean():.4g}", flush=True)
    for p in args.points:
        params = {**POINTS[p], **attack}
        adv = make_attacker("compromised", **params)
        res = run_scenario(base.replace(**adv.overrides), adversary=adv, **first, without=without)
        msle = res.estimators["ckf"].per_trial("msle_mean")
        ratio = msle / clean
        out[json.dumps(params, sort_keys=True)] = {"msle": msle.tolist(), "ratio": ratio.tolist()}
        print(
            f"  {params}: mean x{ratio.mean():.3g}, worst x{ratio.max():.3g}, best "
            f"x{ratio.min():.3g}, above 3x {int((ratio > 3).sum())}/{len(ratio)}; per seed "
            + " ".join(f"{r:.2f}" for r in ratio),
            flush=True,
        )
        if args.honest:  # printed after the paper's MSLE line
            r = str(int(params.get("robots", 1)))
            honest = res.estimators["ckf"].per_trial(f"msle_honest{r}_mean")
            h_ratio = honest / np.asarray(out["clean_honest"][r])
            out[json.dumps(params, sort_keys=True)]["honest_msle"] = honest.tolist()
            out[json.dumps(params, sort_keys=True)]["honest_ratio"] = h_ratio.tolist()
            print(
                f"    honest robots only: mean x{h_ratio.mean():.3g}, worst x{h_ratio.max():.3g}; "
                "per seed " + " ".join(f"{v:.2f}" for v in h_ratio),
                flush=True,
            )
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
