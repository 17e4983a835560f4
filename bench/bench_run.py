"""The whole ``resloc run``, phase by phase: import, kernel load, simulate (of which the
metrics), write, plot; and the command's wall time from outside.

``python bench/bench_run.py`` times the embedded default scenario (17 robots x 1 trial,
1000 steps, CKF, UKF, EKF and dead reckoning) in fresh processes, ``--repeats`` rounds
(default 5), and records per phase the median and the best over the rounds:

* ``import``: from the first line of a fresh interpreter to the command line and everything
  ``resloc run`` imports before it starts work (``resloc.cli.app``, the runner, the output
  writers);
* ``numba_init``: numba's own first-use initialization, which any numba program pays once
  per process before its first compiled call (its typing and lowering registries, whose
  import pulls in ``scipy.linalg`` to find a BLAS);
* ``kernel_load``: loading the compiled kernels the default run uses from numba's on-disk
  cache (compiling them on a cold cache: an untimed warm-up process runs first);
* ``simulate``: ``run_scenario``: world, every estimator, the per-step metrics;
  ``metrics``: the part of it spent computing MSLE / RMSE / NEES;
* ``write``: ``save_run`` without figures (scenario, summary, CSVs, recording);
* ``plot``: the three figures of a run, matplotlib's import included;
* ``command_s`` / ``command_no_plots_s``: the wall time of ``resloc run`` (with and without
  ``--no-plots``) as a user sees it, and ``help_s`` of ``resloc --help``;
* ``startup_share``: ``import`` over the command's wall time (``--no-plots``);
  ``startup_share_of_run``: over ``resloc run``'s (with its figures, the issue's measure).

Each tree's Python files are compiled to bytecode (``compileall``) before the first round,
as on a user's machine after the first run (an environment with
``PYTHONDONTWRITEBYTECODE`` would otherwise recompile every resloc module in every timed
process, about half a second of "import" that no installed copy pays).

``--compare PATH`` times a second source tree (e.g. ``git archive`` of an older commit,
its ``src/`` put first on ``PYTHONPATH``) in the same rounds, alternating with this one, so
that both see the same load; the record then has both and, per phase, the ratio of medians
and the median of the per-round ratios. Writes ``runs/bench/run.json`` (``--out``) and prints
a Markdown table (``--markdown FILE`` prints it from a saved record).
"""

from __future__ import annotations

import time

_START = time.perf_counter()  # a measuring process's import phase starts here

import os  # noqa: E402

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
PHASES = ("import", "numba_init", "kernel_load", "simulate", "metrics", "write", "plot")
COMMANDS = ("command_s", "command_no_plots_s", "help_s")
LABELS = {
    "import": "import (CLI + run command)",
    "numba_init": "numba's first-use initialization",
    "kernel_load": "kernel load (numba cache)",
    "simulate": "simulate (world + CL + metrics)",
    "metrics": "  of which metrics",
    "write": "write (no figures)",
    "plot": "plot (3 figures, matplotlib import)",
    "command_s": "`resloc run` (wall)",
    "command_no_plots_s": "`resloc run --no-plots` (wall)",
    "help_s": "`resloc --help` (wall)",
}


# ---------------------------------------------------------------------------------------
# One measurement, in a fresh interpreter (``--child``)
# ---------------------------------------------------------------------------------------
def _child(start: float) -> dict:
    """Time the phases of one ``resloc run`` (``start``: ``perf_counter`` at the first
    line of this interpreter)."""
    import resloc.cli.app  # noqa: F401  (the command line, as ``resloc`` loads it)
    from resloc.cli import run as _run_command  # noqa: F401
    from resloc.experiments import runner
    from resloc.experiments.config import default_scenario
    from resloc.experiments.run_files import save_run

    phases = {"import": time.perf_counter() - start}
    t = time.perf_counter()
    from numba.core.registry import cpu_target

    cpu_target.target_context.refresh()  # what numba's first cache load or compile does first
    phases["numba_init"] = time.perf_counter() - t
    t = time.perf_counter()
    from resloc.experiments.backends import warm_up_kernels

    try:  # the forms run_scenario loads for the default scenario (no option, no attacker)
        warm_up_kernels(paper=True, options=False)
    except TypeError:  # an older tree's warm-up took no arguments
        warm_up_kernels()
    phases["kernel_load"] = time.perf_counter() - t
    metric_time = _time_metrics(runner)
    t = time.perf_counter()
    result = runner.run_scenario(default_scenario())
    phases["simulate"] = time.perf_counter() - t
    phases["metrics"] = metric_time[0]
    out = Path(tempfile.mkdtemp(prefix="resloc-bench-run-"))
    try:
        t = time.perf_counter()
        save_run(result, out, plots=False)
        phases["write"] = time.perf_counter() - t
        t = time.perf_counter()
        from resloc.experiments import plots

        plots.pyplot()
        plots.plot_run(result, out)
        phases["plot"] = time.perf_counter() - t
    finally:
        shutil.rmtree(out, ignore_errors=True)
    return {
        "phases_s": phases,
        "estimator_wall_s": {n: e.wall_time for n, e in result.estimators.items()},
        "msle_mean": {n: e.summary()["msle_mean"] for n, e in result.estimators.items()},
    }


def _time_metrics(runner) -> list[float]:
    """Wrap the runner's metric computations with a timer; returns the running total."""
    total = [0.0]

    def timed(fn):
        def wrapper(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                total[0] += time.perf_counter() - t

        return wrapper

    recorder = getattr(runner, "AccuracyRecorder", None)
    if recorder is not None:  # metrics in bulk: their buffer's add and flush
        recorder.add = timed(recorder.add)
    else:  # the older runner computed them per step with these functions
        for name in ("msle", "position_rmse", "nees", "relative_nees"):
            setattr(runner, name, timed(getattr(runner, name)))
    return total


# ---------------------------------------------------------------------------------------
# Rounds
# ---------------------------------------------------------------------------------------
def _env(source: Path | None) -> dict:
    env = dict(os.environ)
    if source is not None:
        env["PYTHONPATH"] = os.pathsep.join(
            [str(source / "src"), *filter(None, [env.get("PYTHONPATH")])]
        )
    return env


def _resloc_source(source: Path | None) -> str:
    out = subprocess.run(
        [sys.executable, "-c", "import resloc, pathlib; print(pathlib.Path(resloc.__file__))"],
        env=_env(source),
        capture_output=True,
        text=True,
        check=True,
    )
    return out.stdout.strip()


def _measure_child(source: Path | None) -> dict:
    proc = subprocess.run(
        [sys.executable, __file__, "--child"],
        env=_env(source),
        capture_output=True,
        text=True,
        timeout=1800,
    )
    if proc.returncode != 0:
        raise SystemExit(f"bench_run: the measuring process failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _wall(args: list[str], source: Path | None) -> float:
    t = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", "from resloc.cli.app import main; main()", *args],
        env=_env(source),
        capture_output=True,
        text=True,
        timeout=1800,
    )
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"bench_run: resloc {' '.join(args)} failed:\n{proc.stderr[-2000:]}")
    return wall


def _one_round(source: Path | None) -> dict:
    sample = _measure_child(source)
    with tempfile.TemporaryDirectory(prefix="resloc-bench-cmd-") as tmp:
        sample["command_no_plots_s"] = _wall(
            ["run", "--out", str(Path(tmp) / "a"), "--no-plots"], source
        )
        sample["command_s"] = _wall(["run", "--out", str(Path(tmp) / "b")], source)
    sample["help_s"] = _wall(["--help"], source)
    return sample


def _summarize(samples: list[dict]) -> dict:
    def stats(values: list[float]) -> dict:
        return {"median": statistics.median(values), "best": min(values), "all": values}

    out = {p: stats([s["phases_s"][p] for s in samples]) for p in PHASES}
    out |= {c: stats([s[c] for s in samples]) for c in COMMANDS}
    whole = out["command_no_plots_s"]["median"]
    out["startup_share"] = out["import"]["median"] / whole
    out["startup_share_of_run"] = out["import"]["median"] / out["command_s"]["median"]
    out["startup_with_kernel_load_share"] = (
        out["import"]["median"] + out["numba_init"]["median"] + out["kernel_load"]["median"]
    ) / whole
    names = samples[0]["estimator_wall_s"]
    out["estimator_wall_s"] = {n: stats([s["estimator_wall_s"][n] for s in samples]) for n in names}
    out["msle_mean"] = samples[0]["msle_mean"]
    return out


def _compile_bytecode(source: Path | None) -> None:
    """Compile a tree's ``src/`` to ``__pycache__`` (what its first import on a user's
    machine leaves behind)."""
    src = (source if source is not None else ROOT) / "src"
    subprocess.run(
        [sys.executable, "-m", "compileall", "-q", str(src)],
        env=_env(source),
        capture_output=True,
        check=True,
        timeout=600,
    )


def run_rounds(repeats: int, compare: Path | None) -> dict:
    """Warm both trees up (bytecode, numba caches), then ``repeats`` alternating rounds."""
    variants = {"this": None} | ({"compare": compare} if compare is not None else {})
    for source in variants.values():
        _compile_bytecode(source)
        _measure_child(source)  # compile or load the kernels, fill the OS file cache
    samples: dict[str, list[dict]] = {name: [] for name in variants}
    loads = [list(os.getloadavg())]
    for rnd in range(repeats):
        for name, source in variants.items():
            samples[name].append(_one_round(source))
        loads.append(list(os.getloadavg()))
        print(f"  round {rnd + 1}/{repeats} done (load {loads[-1][0]:.1f})", flush=True)
    record = {
        "scenario": "embedded default: 17 robots x 1 trial, 1000 steps, ckf+ukf+ekf+dr",
        "repeats": repeats,
        "machine": {
            "python": platform.python_version(),
            "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "load_average_1_5_15_per_round": loads,
            "bytecode": "compiled (compileall) before the first round, both trees",
        },
        "variants": {
            name: {"resloc": _resloc_source(source), **_summarize(samples[name])}
            for name, source in variants.items()
        },
    }
    if compare is not None:
        record["speedup"] = _speedups(samples["compare"], samples["this"])
    return record


def _speedups(before: list[dict], after: list[dict]) -> dict:
    """Per phase: before / after, as a ratio of medians and the median of per-round ratios."""

    def value(sample: dict, key: str) -> float:
        return sample["phases_s"][key] if key in PHASES else sample[key]

    out = {}
    for key in (*PHASES, *COMMANDS):
        b = [value(s, key) for s in before]
        a = [value(s, key) for s in after]
        out[key] = {
            "ratio_of_medians": statistics.median(b) / statistics.median(a),
            "median_paired_ratio": statistics.median(x / y for x, y in zip(b, a, strict=True)),
        }
    return out


# ---------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------
def markdown(record: dict) -> str:
    """The record as a Markdown table (and a line on start-up)."""
    variants = record["variants"]
    this = variants["this"]
    compare = variants.get("compare")
    head = "| phase | median (s) | best (s) | share of `resloc run` |"
    rule = "| --- | ---: | ---: | ---: |"
    if compare:
        head = "| phase | before: median (s) | before: best (s) | " + head[10:]
        head += " before / after (medians) | before / after (paired) |"
        rule += " ---: | ---: | ---: | ---: |"
    lines = [head, rule]
    whole = this["command_s"]["median"]
    for key in (*PHASES, *COMMANDS):
        row = f"| {LABELS[key]} |"
        if compare:
            row += f" {compare[key]['median']:.3f} | {compare[key]['best']:.3f} |"
        share = f"{100 * this[key]['median'] / whole:.0f} %" if key in PHASES else ""
        row += f" {this[key]['median']:.3f} | {this[key]['best']:.3f} | {share} |"
        if compare:
            s = record["speedup"][key]
            row += f" {s['ratio_of_medians']:.2f}x | {s['median_paired_ratio']:.2f}x |"
        lines.append(row)
    loads = record["machine"]["load_average_1_5_15_per_round"]
    lines += [
        "",
        f"Start-up (import) is {100 * this.get('startup_share_of_run', float('nan')):.1f} % "
        f"of `resloc run`, {100 * this['startup_share']:.1f} % of `resloc run --no-plots` "
        f"({100 * this['startup_with_kernel_load_share']:.1f} % with numba's "
        "initialization and the kernel load). "
        "Estimator wall times (median, s): "
        + ", ".join(f"{n} {v['median']:.3f}" for n, v in this["estimator_wall_s"].items())
        + f". {record['repeats']} rounds; 1-minute load average "
        f"{min(x[0] for x in loads):.1f}-{max(x[0] for x in loads):.1f}.",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="rounds (median and best)")
    parser.add_argument("--compare", type=Path, help="another source tree (its src/) to time")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "bench" / "run.json")
    parser.add_argument("--markdown", type=Path, metavar="RECORD", help="print RECORD, exit")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(_child(_START)))
        return 0
    if args.markdown:
        print(markdown(json.loads(args.markdown.read_text())))
        return 0
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    if args.compare is not None and not (args.compare / "src" / "resloc").is_dir():
        parser.error(f"--compare {args.compare}: no src/resloc there; give a source tree")
    print(f"resloc run phases: {args.repeats} rounds", flush=True)
    record = run_rounds(args.repeats, args.compare)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(record, indent=2) + "\n")
    tmp.replace(args.out)
    print(markdown(record))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
