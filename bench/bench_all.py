"""``make bench``: every benchmark of resloc in one command, written under ``runs/bench/``.

Runs, each in its own process, one after the other (so they never share the cores):

1. ``bench/bench_run.py``: the whole ``resloc run`` phase by phase (import, kernel load,
   simulate, metrics, write, plot), medians and best of ``--repeats`` rounds
   -> ``runs/bench/run.json``;
2. ``bench/bench_options.py``: every estimator option's cost per simulated step relative to
   the paper's default (medians, best, paired ratios, compiled share)
   -> ``runs/bench/options.json``;
3. ``bench/run_bench.py``: the CL step from 17 robots up (scale rows, FilterPy, lower
   bound, memory, soak) -> ``runs/bench/scale.json``.

Then ``runs/bench/summary.md`` (the three tables, the machine and its load average) and
``runs/bench/summary.json`` (all three records). ``runs/`` is not committed: a reference
copy lives in ``bench/reference/`` and is replaced only on purpose, by
``make bench-reference`` (``--save-reference``: copy the last ``runs/bench/`` there).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT = ROOT / "runs" / "bench"
REFERENCE = HERE / "reference"
PARTS = ("run", "options", "scale")
FILES = ("run.json", "options.json", "scale.json", "summary.json", "summary.md")


def _commands(args) -> dict[str, list[str]]:
    py = sys.executable
    run = [py, str(HERE / "bench_run.py"), "--out", str(args.out / "run.json")]
    run += ["--repeats", str(1 if args.quick else args.repeats)]
    if args.compare:
        run += ["--compare", str(args.compare)]
    options = [py, str(HERE / "bench_options.py"), "--out", str(args.out / "options.json")]
    if args.quick:
        options += ["--steps", "60", "--repeats", "1"]
    scale = [py, str(HERE / "run_bench.py"), "--out", str(args.out / "scale.json")]
    if args.quick:
        scale += ["--quick", "--repeat", "1"]
    return {"run": run, "options": options, "scale": scale}


def _options_markdown(record: dict) -> str:
    lines = [
        "| option | estimator ms/step: median | best | x default (medians) | x default (paired) "
        "| simulation ms/step: median | x default | compiled |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, row in record.get("options", {}).items():
        est, sim = row["estimator_ms"], row["simulation_ms"]
        paired = row.get("paired_estimator_ratio", {}).get("median", float("nan"))
        lines.append(
            f"| {name} | {est['median']:.3f} | {est['best']:.3f} | "
            f"{est['ratio_to_default']:.2f} | {paired:.2f} | {sim['median']:.3f} | "
            f"{sim['ratio_to_default']:.2f} | {row.get('compiled_share', 0.0):.0%} |"
        )
    return "\n".join(lines)


def _section(title: str, body: str) -> str:
    return f"## {title}\n\n{body.strip()}\n"


def _summary(args, records: dict, failures: dict, loads: list, started: str) -> str:
    py = sys.executable
    parts = [
        "# resloc benchmarks\n",
        f"Started {started}, {platform.python_version()} on {platform.machine()} "
        f"({os.cpu_count()} CPUs); 1-minute load average at the start and after each part: "
        + ", ".join(f"{x:.1f}" for x in loads)
        + ". One BLAS thread. Written by `make bench` (`bench/bench_all.py`).\n",
    ]
    if "run" in records:
        table = subprocess.run(
            [py, str(HERE / "bench_run.py"), "--markdown", str(args.out / "run.json")],
            capture_output=True,
            text=True,
        ).stdout
        parts.append(_section("`resloc run`, phase by phase (`bench/bench_run.py`)", table))
    if "options" in records:
        steps = records["options"].get("steps")
        repeats = records["options"].get("repeats")
        parts.append(
            _section(
                f"Every option's cost per step ({steps} steps, {repeats} repeats; "
                "`bench/bench_options.py`)",
                _options_markdown(records["options"]),
            )
        )
    if "scale" in records:
        table = subprocess.run(
            [py, str(HERE / "run_bench.py"), "--markdown", str(args.out / "scale.json")],
            capture_output=True,
            text=True,
        ).stdout
        parts.append(_section("The CL step at scale (`bench/run_bench.py`)", table))
    for name, reason in failures.items():
        parts.append(_section(f"{name}: FAILED", f"```\n{reason}\n```"))
    return "\n".join(parts)


def save_reference(out: Path) -> int:
    """Copy the last results into ``bench/reference/`` (deliberately, by hand)."""
    missing = [f for f in FILES if not (out / f).is_file()]
    if missing:
        print(f"error: {out} lacks {', '.join(missing)}; run `make bench` first", file=sys.stderr)
        return 2
    REFERENCE.mkdir(exist_ok=True)
    for f in FILES:
        shutil.copy2(out / f, REFERENCE / f)
    print(f"copied {', '.join(FILES)} from {out} to {REFERENCE}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=OUT, help="directory (default runs/bench)")
    parser.add_argument("--only", nargs="+", choices=PARTS, help="parts to run (default all)")
    parser.add_argument("--repeats", type=int, default=5, help="rounds of bench_run.py")
    parser.add_argument("--compare", type=Path, help="older source tree for bench_run.py")
    parser.add_argument("--quick", action="store_true", help="smoke test: tiny sizes")
    parser.add_argument(
        "--save-reference", action="store_true", help="copy the last results to bench/reference"
    )
    args = parser.parse_args(argv)
    if args.save_reference:
        return save_reference(args.out)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.strftime("%Y-%m-%d %H:%M:%S %Z")
    loads = [os.getloadavg()[0]]
    records, failures = {}, {}
    for name, command in _commands(args).items():
        if args.only and name not in args.only:
            continue
        print(f"== {name}: {' '.join(command[1:])}", flush=True)
        t = time.perf_counter()
        proc = subprocess.run(command, cwd=ROOT)
        loads.append(os.getloadavg()[0])
        path = args.out / f"{name}.json"
        if proc.returncode != 0 or not path.is_file():
            failures[name] = f"exit code {proc.returncode}: {' '.join(command)}"
            continue
        records[name] = json.loads(path.read_text())
        print(f"== {name}: {time.perf_counter() - t:.0f} s", flush=True)
    summary = {"started": started, "load_average_1min": loads, **records, "failed": failures}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    (args.out / "summary.md").write_text(_summary(args, records, failures, loads, started))
    print(f"wrote {args.out / 'summary.md'} and summary.json")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
