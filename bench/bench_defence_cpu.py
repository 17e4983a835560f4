"""The estimator's CPU time per step of the defences against the paper's default (issue 12).

``python bench/bench_defence_cpu.py [--repeats 7] [--steps 300]`` runs the options of
:data:`bench_options.OPTIONS` whose name starts with ``defence`` and the default, the options
alternating (round 1 of every option, then round 2, ...), and times every estimator step
(``resloc.experiments.lockstep._step_estimator``) with ``time.thread_time``: the CPU time of
the estimator, which a wait for a loaded machine's CPU does not inflate (a wall-clock ratio
on 2 cores shared by several processes spread over +-0.4 in one run). Prints each option's
median CPU time per step and its ratio to the default's median (the range over the rounds).
Used in ``docs/performance.md`` ("Defence pre-passes, second pass").
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_options  # noqa: E402

import resloc.experiments.lockstep as lockstep  # noqa: E402
from resloc.cl import kernels  # noqa: E402


def run(steps: int, repeats: int, only: list[str] | None = None) -> dict[str, list[float]]:
    """CPU microseconds per estimator step, per option, one value per round (``only``:
    these options of :data:`bench_options.OPTIONS` beside the default)."""
    spent = [0.0]
    step_estimator = lockstep._step_estimator

    def timed(*args, **kwargs):
        t0 = time.thread_time()
        try:
            return step_estimator(*args, **kwargs)
        finally:
            spent[0] += time.thread_time() - t0

    names = [next(iter(bench_options.OPTIONS))]
    names += [n for n in bench_options.OPTIONS if n.startswith("defence")] if only is None else only
    kernels.warm_up()
    lockstep._step_estimator = timed
    try:
        for name in names:  # compile / load every kernel, warm every code path
            bench_options._measure(bench_options.OPTIONS[name], 5)
        cpu: dict[str, list[float]] = {name: [] for name in names}
        for _ in range(repeats):
            for name in names:
                spent[0] = 0.0
                bench_options._measure(bench_options.OPTIONS[name], steps)
                cpu[name].append(1e6 * spent[0] / steps)
    finally:
        lockstep._step_estimator = step_estimator
    return cpu


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=300, help="simulated steps per run")
    parser.add_argument("--repeats", type=int, default=7, help="rounds")
    parser.add_argument("--only", nargs="*", help="option names (default: every defence)")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.repeats < 1:
        parser.error("--steps and --repeats must be >= 1")
    unknown = sorted(set(args.only or ()) - set(bench_options.OPTIONS))
    if unknown:
        parser.error(f"--only: unknown option {unknown[0]!r} (see bench_options.OPTIONS)")
    cpu = run(args.steps, args.repeats, args.only)
    base = statistics.median(next(iter(cpu.values())))
    print(f"load average {os.getloadavg()}; {kernels.__file__}")
    for name, values in cpu.items():
        lo, hi = min(values) / base, max(values) / base
        print(
            f"{name:55s} {statistics.median(values):7.1f} us CPU/step "
            f"x{statistics.median(values) / base:.2f} (x{lo:.2f}-{hi:.2f})"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
