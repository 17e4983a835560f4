"""Per-step cost of every estimator option relative to the paper's default (issue 12).

``python bench/bench_options.py`` runs the paper's scenario (17 robots, 1 trial, the CKF, no
dead reckoning) once per option, the options interleaved (repeat 1 of every option, then
repeat 2, ...) so that a change of the machine's load hits them alike, and records per
option and repeat:

* ``estimator_ms``: the estimator's wall time per simulated step (predict, the fusion
  method's bookkeeping, the correction with its detector / trigger / channel, the exchanges:
  ``EstimatorResult.wall / steps``);
* ``simulation_ms``: the whole ``run_scenario`` per step (world, estimator, per-step metrics);
* ``compiled``: the share of corrections the compiled kernel ran (``LinkOutcome.compiled``).

Medians (and best) over the repeats, each option's ratio to the default's median *measured
in the same invocation*, and, robust to a machine whose load changes within seconds, the
median of *paired* ratios: every run of an option follows a run of the default, and the
pair's ratio of estimator times is recorded. The kernels are compiled (or loaded from
numba's on-disk cache) and every option run once before anything is timed. Writes
``runs/bench_options/<timestamp>.json`` (``--out`` to choose) and prints a table.
``bench/run_bench.py`` may call :func:`run_options`.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import resloc  # noqa: E402
from resloc.cl import kernels  # noqa: E402
from resloc.cl import step as cl_step  # noqa: E402
from resloc.experiments.config import default_scenario  # noqa: E402
from resloc.experiments.config_parse import load_scenario  # noqa: E402
from resloc.experiments.defences import DEFENCES  # noqa: E402
from resloc.experiments.runner import run_scenario  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
NIS = {"detector.norm": "nis", "detector.false_alarm": 0.01}

#: Option name -> dotted changes of the default scenario (or a scenario file).
OPTIONS: dict[str, dict | str] = {
    "default (paper, ckf)": {},
    "filter ukf": {"run.filters": ["ukf"]},
    "filter ekf": {"run.filters": ["ekf"]},
    "detector nis gate": NIS,
    "detector cusum": {**NIS, "detector.cusum": True},
    "detector mean_cusum": {**NIS, "detector.mean_cusum": True},
    "fusion gauge": {"estimator.fusion": "gauge"},
    "fusion tracked": {"estimator.fusion": "tracked"},
    "fusion factorized": {"estimator.fusion": "factorized"},
    "fusion ci": {"estimator.fusion": "ci"},
    "fusion split_ci": {"estimator.fusion": "split_ci"},
    "neighbour cached": {"estimator.neighbour_estimate": "cached"},
    "update summed": {"estimator.update_mode": "summed"},
    "attack stealthy": {"attack.kind": "stealthy", "attack.bias": [0.3, 0.6]},
    "defence full": dict(DEFENCES["full"]),
    "defence full+redundancy+sequence": dict(DEFENCES["full+redundancy+sequence"]),
    "defence full+reciprocal": dict(DEFENCES["full+reciprocal"]),
    "defence full+redundancy+sequence+reciprocal": dict(
        DEFENCES["full+redundancy+sequence+reciprocal"]
    ),
    "defence zone+full+redundancy+sequence": dict(DEFENCES["zone+full+redundancy+sequence"]),
    "defence zone+full+redundancy+sequence+cap": dict(
        DEFENCES["zone+full+redundancy+sequence+cap"]
    ),
    "defence zone+full+redundancy+sequence+cap+landmarks": dict(
        DEFENCES["zone+full+redundancy+sequence+cap+landmarks"]
    ),
    "defence zone+full+redundancy+sequence+reciprocal": dict(
        DEFENCES["zone+full+redundancy+sequence+reciprocal"]
    ),
    "defence zone+full+redundancy+sequence+cap+landmarks+witness": dict(
        DEFENCES["zone+full+redundancy+sequence+cap+landmarks+witness"]
    ),
    "defence zone+full+redundancy+sequence+cap+landmarks+witness+outvoted": dict(
        DEFENCES["zone+full+redundancy+sequence+cap+landmarks+witness+outvoted"]
    ),
    "defence zone+full+redundancy+sequence+cap+landmarks+witness+outvoted+startup": dict(
        DEFENCES["zone+full+redundancy+sequence+cap+landmarks+witness+outvoted+startup"]
    ),
    "defence zone+full+redundancy+sequence+cap+landmarks+witness+outvoted+startup-decay": dict(
        DEFENCES["zone+full+redundancy+sequence+cap+landmarks+witness+outvoted+startup-decay"]
    ),
    "defence zone+full+redundancy+sequence+cap+landmarks+witness+outvoted+startup-decay+lockout": (
        dict(
            DEFENCES[
                "zone+full+redundancy+sequence+cap+landmarks+witness+outvoted+startup-decay+lockout"
            ]
        )
    ),
    "examples/beyond/resilient.toml": "examples/beyond/resilient.toml",
}


class _CompiledShare:
    """Counts which path ran each correction (wraps ``resloc.cl.step.correct``)."""

    def __init__(self) -> None:
        self.compiled = 0
        self.total = 0
        self._correct = cl_step.correct

    def __enter__(self):
        import resloc.experiments.lockstep as lockstep

        def counted(*args, **kwargs):
            out = self._correct(*args, **kwargs)
            self.total += 1
            self.compiled += bool(out[2].compiled)
            return out

        self._lockstep = lockstep
        self._saved = lockstep.correct
        lockstep.correct = counted
        return self

    def __exit__(self, *exc) -> None:
        self._lockstep.correct = self._saved


def _scenario(option: dict | str, steps: int):
    if isinstance(option, str):
        sc = load_scenario(ROOT / option).replace(**{"run.filters": ["ckf"]})
    else:
        sc = default_scenario().replace(**{"run.filters": ["ckf"], **option})
    return sc.replace(**{"run.steps": steps, "run.trials": 1, "run.dead_reckoning": False})


def _measure(option: dict | str, steps: int) -> dict:
    sc = _scenario(option, steps)
    with _CompiledShare() as share:
        t0 = time.perf_counter()
        result = run_scenario(sc)
        wall = time.perf_counter() - t0
    est = next(iter(result.estimators.values()))
    return {
        "estimator_ms": 1e3 * est.wall_time / steps,
        "simulation_ms": 1e3 * wall / steps,
        "compiled": share.compiled / max(share.total, 1),
    }


def run_options(steps: int = 300, repeats: int = 5, options: dict | None = None) -> dict:
    """Measure every option; returns the JSON-ready record (see the module docstring)."""
    options = OPTIONS if options is None else options
    kernels.warm_up()
    for option in options.values():  # compile / load every kernel, warm every code path
        _measure(option, 5)
    samples: dict[str, list[dict]] = {name: [] for name in options}
    paired: dict[str, list[float]] = {name: [] for name in options}
    default = next(iter(options.values()))
    for _ in range(repeats):
        for name, option in options.items():
            # The default right before each option: the pair sees the same load.
            base_run = _measure(default, steps)
            run = _measure(option, steps)
            samples[name].append(run)
            paired[name].append(run["estimator_ms"] / base_run["estimator_ms"])
    rows = {}
    base = None
    for name, runs in samples.items():
        row = {}
        for key in ("estimator_ms", "simulation_ms"):
            values = [r[key] for r in runs]
            row[key] = {"median": statistics.median(values), "best": min(values), "all": values}
        row["compiled_share"] = float(np.mean([r["compiled"] for r in runs]))
        row["paired_estimator_ratio"] = {
            "median": statistics.median(paired[name]),
            "all": paired[name],
        }
        if base is None:
            base = row
        for key in ("estimator_ms", "simulation_ms"):
            row[key]["ratio_to_default"] = row[key]["median"] / base[key]["median"]
        rows[name] = row
    return {
        "what": "per simulated step, 17 robots x 1 trial, CKF, no dead reckoning",
        "steps": steps,
        "repeats": repeats,
        "backend": kernels.backend(),
        "resloc_source": str(Path(resloc.__file__).resolve().parent),
        "git_commit": _git_commit(),
        "machine": {
            "python": platform.python_version(),
            "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "load_average_1_5_15": list(os.getloadavg()),
        },
        "options": rows,
    }


def _git_commit() -> str | None:
    try:
        src = Path(resloc.__file__).resolve().parent
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=src, capture_output=True, text=True, timeout=10
        )
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def _table(record: dict) -> str:
    lines = [
        f"{'option':34s} {'est ms/step':>12s} {'x default':>10s} {'sim ms/step':>12s}"
        f" {'x default':>10s} {'paired x':>9s} {'compiled':>9s}"
    ]
    for name, row in record["options"].items():
        e, s = row["estimator_ms"], row["simulation_ms"]
        lines.append(
            f"{name:34s} {e['median']:12.3f} {e['ratio_to_default']:10.2f} "
            f"{s['median']:12.3f} {s['ratio_to_default']:10.2f} "
            f"{row['paired_estimator_ratio']['median']:9.2f} {row['compiled_share']:9.0%}"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=300, help="simulated steps per run")
    parser.add_argument("--repeats", type=int, default=5, help="runs per option (>= 5)")
    parser.add_argument("--only", nargs="*", help="option names to run (default: all)")
    parser.add_argument("--out", type=Path, help="JSON file (default: runs/bench_options/...)")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.repeats < 1:
        parser.error("--steps and --repeats must be >= 1")
    options = OPTIONS
    if args.only:
        unknown = [n for n in args.only if n not in OPTIONS]
        if unknown:
            parser.error(f"--only: unknown option(s) {unknown}; choose from {list(OPTIONS)}")
        first = next(iter(OPTIONS))
        options = {n: OPTIONS[n] for n in [first, *args.only] if n in OPTIONS}
    record = run_options(args.steps, args.repeats, options)
    out = args.out or ROOT / "runs" / "bench_options" / f"{time.strftime('%Y%m%dT%H%M%S')}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(record, indent=2))
    tmp.replace(out)
    print(_table(record))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
