"""Benchmark of the study executor (sweeps on Dask): cells per second and overhead per task.

Runs against whichever resloc is importable, so the same script measures the previous
process pool (run it with another checkout's interpreter) and the Dask executor::

    .venv/bin/python bench/bench_sweep.py --out bench/sweep_dask.json
    /path/to/old/checkout/.venv/bin/python bench/bench_sweep.py --out bench/sweep_pool.json

Measures

* ``sweep500``: a 500-cell sweep, 50 values of ``detector.rho`` x 10 seeds, 17 robots
  (the default team), 300 steps, CKF only (no dead reckoning), ``jobs`` workers, no plots;
  with the Dask executor also with a fresh result store (writes every cell) and again from
  the store (reads every cell);
* ``tiny``: ``--tiny`` distinct one-seed scenarios of 2 robots and 1 step (almost no work:
  the time per cell is the executor's overhead per task), ``jobs`` workers and in-process;
* ``noop`` (Dask executor only): tasks that do nothing, on the embedded cluster.

``*_start_*`` is a run of 2 cells/tasks (starting the workers); ``*_marginal_*`` is
(run of n - run of 2) / (n - 2): the cost of one more task. ``*_cpu_*`` counts the CPU
seconds of this process and its workers (children), which other jobs sharing the machine
disturb less than wall time.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import resloc  # noqa: E402
from resloc.experiments.config_parse import parse_scenario  # noqa: E402
from resloc.experiments.sweep import parse_sweep, run_scenarios, run_sweep  # noqa: E402

RHOS = [round(0.2 + 0.02 * k, 2) for k in range(50)]


def _cpu_seconds() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _noop(x):
    return [x]


def sweep500(jobs: int, store_variants: bool = True) -> dict:
    spec = parse_sweep(
        {
            "sweep": {"parameter": "detector.rho", "values": RHOS, "base": "default"},
            "run": {"steps": 300, "trials": 10, "filters": ["ckf"], "dead_reckoning": False},
        }
    )
    cells = len(spec.values) * spec.base.run.trials
    out: dict = {"cells": cells, "robots": spec.base.world.team.robots, "steps": 300}
    cpu0 = _cpu_seconds()
    t0 = time.perf_counter()
    ref = run_sweep(spec, jobs=jobs)
    out["no_store_s"] = time.perf_counter() - t0
    out["no_store_cells_per_s"] = cells / out["no_store_s"]
    # CPU seconds of this process and its finished children (the workers): less sensitive
    # than wall time to other jobs sharing the machine.
    out["no_store_cpu_s"] = _cpu_seconds() - cpu0
    out["no_store_cells_per_cpu_s"] = cells / out["no_store_cpu_s"]
    if not store_variants:
        return out
    try:
        from resloc.experiments.executor import Study
        from resloc.experiments.store import ResultStore
    except ImportError:  # the previous process pool: no executor, no store
        return out
    with tempfile.TemporaryDirectory() as tmp:
        for name in ("fresh_store", "from_store"):
            study = Study(jobs=jobs, store=ResultStore(Path(tmp)))
            t0 = time.perf_counter()
            res = run_sweep(spec, study=study)
            out[f"{name}_s"] = time.perf_counter() - t0
            out[f"{name}_cells_per_s"] = cells / out[f"{name}_s"]
            out[f"{name}_stats"] = study.stats.to_dict()
            assert np.array_equal(res.per_trial("ckf"), ref.per_trial("ckf"))
    return out


def tiny(jobs: int, n: int) -> dict:
    """Marginal time per tiny cell: (time for n cells - time for 2 cells) / (n - 2), so that
    starting the workers is measured apart (``start_s``: the run of 2 cells)."""
    base = parse_scenario(
        {"run": {"steps": 1, "trials": 1, "filters": ["ekf"], "dead_reckoning": False}}
    ).replace(**{"team.robots": 2})
    scenarios = [base.replace(**{"detector.rho": 0.1 + 0.001 * k}) for k in range(n)]
    run_scenarios(scenarios[:2], jobs=1)  # compile / load the kernels in this process
    out: dict = {"cells": n}
    t0 = time.perf_counter()
    run_scenarios(scenarios, jobs=1)
    out["serial_ms_per_cell"] = 1e3 * (time.perf_counter() - t0) / n
    times, cpu = {}, {}
    for size in (2, n):
        cpu0 = _cpu_seconds()
        t0 = time.perf_counter()
        run_scenarios(scenarios[:size], jobs=jobs)
        times[size] = time.perf_counter() - t0
        cpu[size] = _cpu_seconds() - cpu0
    out["parallel_start_s"] = times[2]
    out["parallel_total_s"] = times[n]
    out["parallel_marginal_ms_per_cell"] = 1e3 * (times[n] - times[2]) / (n - 2)
    out["parallel_start_cpu_s"] = cpu[2]
    out["parallel_marginal_cpu_ms_per_cell"] = 1e3 * (cpu[n] - cpu[2]) / (n - 2)
    return out


def noop(jobs: int, n: int) -> dict | None:
    try:
        from resloc.experiments.executor import Study, Task
    except ImportError:
        return None
    times, cpu = {}, {}
    for size in (2, n):  # 2 tasks: the smallest study that starts the cluster
        tasks = [Task(_noop, (k,), (f"k{k}",), f"noop {k}") for k in range(size)]
        cpu0 = _cpu_seconds()
        t0 = time.perf_counter()
        Study(jobs=jobs).run(tasks, cells=size)
        times[size] = time.perf_counter() - t0
        cpu[size] = _cpu_seconds() - cpu0
    return {
        "tasks": n,
        "start_s": times[2],
        "total_s": times[n],
        "marginal_ms_per_task": 1e3 * (times[n] - times[2]) / (n - 2),
        "start_cpu_s": cpu[2],
        "marginal_cpu_ms_per_task": 1e3 * (cpu[n] - cpu[2]) / (n - 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--tiny", type=int, default=300)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--skip-sweep", action="store_true")
    ap.add_argument(
        "--sweep-only", action="store_true", help="only the 500-cell sweep, without a store"
    )
    args = ap.parse_args()
    if args.sweep_only:
        res = {"code": str(Path(resloc.__file__).resolve().parents[2]), "jobs": args.jobs}
        res["load_average_at_start"] = os.getloadavg()
        res["sweep500"] = sweep500(args.jobs, store_variants=False)
        res["load_average_at_end"] = os.getloadavg()
        args.out.write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
        print(json.dumps(res, indent=2))
        return
    res = {
        "resloc": resloc.__version__,
        "code": str(Path(resloc.__file__).resolve().parents[2]),
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "load_average_at_start": os.getloadavg(),
        "jobs": args.jobs,
        "tiny": tiny(args.jobs, args.tiny),
        "noop": noop(args.jobs, 1000),
    }
    if not args.skip_sweep:
        res["sweep500"] = sweep500(args.jobs)
    res["load_average_at_end"] = os.getloadavg()
    args.out.write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
