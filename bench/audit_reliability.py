"""Reliability audit: hostile inputs and kills against the ``resloc`` command line.

Re-runs the classes of the issue-14 audit and counts what must be zero:

* ``traceback``: an exception other than a clean exit (exit codes other than 0/2, or a
  traceback in the output);
* ``multi_line``: a refusal (exit 2) whose error is not exactly one ``error:`` line;
* ``hang``: a case still running after ``CASE_LIMIT`` seconds (stopped);
* ``absurd_accepted``: a non-finite or absurd number (inf, nan, +-1e300) that ran (exit 0);
* ``silent_drop``: MRCLAM data rows neither loaded nor counted as dropped;
* ``lost_result``: a command that printed its results and then failed, or an ``--out``
  left without a complete result set after a kill;
* ``wrote_into_input``: results written inside the dataset folder being read;
* ``orphan``: a process of a killed command still alive;
* ``leftover``: a hidden ``.OUT.tmp-*``/``.OUT.old-*`` still present after the next run.

Usage::

    python bench/audit_reliability.py [--kills 12] [--json bench/audit_results.json]

Cases run in-process through typer's ``CliRunner`` (fast); kills run real processes.
Seeded: the same cases and kill moments on every run.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "fixtures" / "mrclam" / "MRCLAM_Dataset6_60s"
TINY = {"run": {"steps": 15, "filters": ["ckf", "ukf", "ekf"]}, "team": {"robots": 4}}
ABSURD = ["inf", "-inf", "nan", "1e300", "-1e300"]
HOSTILE = [*ABSURD, "0", "0.0", "-1", "1e-7", "100000000000000000000", "true", '"x"', "[1]"]
FLOAT_FIELDS = {
    "team": ["spacing", "leader_gap", "init_pos_std", "init_heading_std"],
    "motion": ["dt", "v_max", "omega_max", "leader_speed", "gain", "projection"],
    "sensing": ["radius", "comm_radius", "range_std", "bearing_std"],
    "estimator": ["ukf_alpha", "ukf_beta", "ukf_kappa", "gauge_rounds"],
    "detector": ["rho", "false_alarm", "cusum_k", "cusum_h", "mean_cusum_k", "mean_cusum_h"],
    "trigger": ["alpha", "gamma", "zeta_s", "zeta_c", "risk_factor_floor", "lambda2_rounds"],
    "attack": ["link_fraction", "stealth_margin", "replay_delay"],
    "run": ["seed", "steps", "trials"],
}
RESULT_MARKERS = ("MSLE mean", "RMSE m", "comm rate")
#: A case that runs longer than this (s) counts as a hang (and is stopped).
CASE_LIMIT = 60


class CaseTimeout(BaseException):
    """Raised by SIGALRM inside a case that ran past CASE_LIMIT."""


def _alarm(signum, frame):
    raise CaseTimeout()


def toml_text(sections: dict) -> str:
    lines = []
    for name, table in sections.items():
        lines.append(f"[{name}]")
        for key, value in table.items():
            lines.append(f"{key} = {value if isinstance(value, str) else json.dumps(value)}")
    return "\n".join(lines) + "\n"


def scenario_with(section: str, key: str, value: str) -> str:
    data = json.loads(json.dumps(TINY))
    data.setdefault(section, {})[key] = value
    return toml_text(data)


class Audit:
    def __init__(self, work: Path) -> None:
        from typer.testing import CliRunner

        from resloc.cli.app import app

        self.app, self.runner, self.work = app, CliRunner(), work
        self.counts: Counter = Counter()
        self.cases: Counter = Counter()
        self.examples: dict[str, list[str]] = {}
        self.n = 0
        self.skip: set[str] = set()

    def note(self, kind: str, case: str) -> None:
        self.counts[kind] += 1
        self.examples.setdefault(kind, [])
        if len(self.examples[kind]) < 8:
            self.examples[kind].append(case)

    def fresh(self, name: str) -> Path:
        self.n += 1
        d = self.work / f"{self.n:04d}-{name}"
        d.mkdir()
        return d

    def invoke(self, klass: str, case: str, args: list[str], absurd: bool = False):
        self.cases[klass] += 1
        previous = signal.signal(signal.SIGALRM, _alarm)
        signal.alarm(CASE_LIMIT)
        try:
            res = self.runner.invoke(self.app, args)
        except CaseTimeout:
            self.note("hang", f"{klass}: {case} (stopped after {CASE_LIMIT} s)")
            return None
        finally:
            signal.alarm(0)
            signal.signal(signal.SIGALRM, previous)
        out, err = res.stdout, res.stderr
        crashed = res.exception is not None and not isinstance(res.exception, SystemExit)
        if res.exit_code != 0 and any(m in out for m in RESULT_MARKERS):
            self.note("lost_result", f"{klass}: {case}: failed after printing its results")
        if isinstance(res.exception, CaseTimeout):
            self.note("hang", f"{klass}: {case} (stopped after {CASE_LIMIT} s)")
        elif crashed or res.exit_code not in (0, 2) or "Traceback" in out + err:
            self.note("traceback", f"{klass}: {case} (exit {res.exit_code}, {res.exception!r})")
        elif res.exit_code == 2:
            errors = [ln for ln in err.splitlines() if ln.startswith("error: ")]
            others = [
                ln
                for ln in err.splitlines()
                if ln.strip() and not ln.startswith(("error: ", "note: ", "warning: "))
            ]
            if len(errors) != 1 or others:
                self.note("multi_line", f"{klass}: {case}: {err.strip()[:200]!r}")
        elif absurd:
            self.note("absurd_accepted", f"{klass}: {case}")
        return res

    # ------------------------------------------------------------------ classes
    def scenarios(self) -> None:
        for section, keys in FLOAT_FIELDS.items():
            for key in keys:
                for value in HOSTILE:
                    d = self.fresh("scenario")
                    p = d / "s.toml"
                    p.write_text(scenario_with(section, key, value))
                    self.invoke(
                        "scenario",
                        f"{section}.{key} = {value}",
                        ["run", str(p), "--out", str(d / "out"), "--no-plots"],
                        absurd=value in ABSURD,
                    )
        specials = {
            "bom": "\ufeff" + toml_text(TINY),
            "name $": toml_text({**TINY, "run": {**TINY["run"], "name": "a $\\alpha_{x$"}}),
            "name newline": toml_text({**TINY, "run": {**TINY["run"], "name": "a\nb"}}),
            "waypoints string": toml_text({**TINY, "motion": {"waypoints": [[0, "a"], [1, 1]]}}),
            "waypoints flat": toml_text({**TINY, "motion": {"waypoints": [1, 2]}}),
            "waypoints table": "[motion]\nwaypoints = [{x = 1}, [0, 0]]\n",
            "waypoints inf": "[motion]\nwaypoints = [[0, inf], [1, 1]]\n",
            "zero noise": toml_text(
                {
                    **TINY,
                    "sensing": {"range_std": 0.0, "bearing_std": 0.0},
                    "motion": {"odometry_std": [0.0, 0.0], "process_floor_std": [0.0, 0.0, 0.0]},
                }
            ),
            "robots 200000": toml_text({"run": {"steps": 2}, "team": {"robots": 200000}}),
            "robot-trials 5e6": toml_text(
                {"run": {"steps": 2, "trials": 1000000}, "team": {"robots": 5}}
            ),
            "init_heading_std 1.5 (UKF diverges)": toml_text(
                {"run": {"steps": 120}, "team": {"robots": 5, "init_heading_std": 1.5}}
            ),
        }
        for case, text in specials.items():
            if case in self.skip:
                self.note("skipped", f"scenario: {case}")
                continue
            d = self.fresh("special")
            p = d / "s.toml"
            p.write_text(text, encoding="utf-8")
            res = self.invoke(
                "scenario", case, ["run", str(p), "--out", str(d / "out"), "--no-plots"]
            )
            if res is None:
                continue
            if res.exit_code == 0 and not (d / "out" / "summary.json").exists():
                self.note("lost_result", f"scenario: {case}: exit 0 without summary.json")
            if res.exit_code == 0 and "name" in case:
                again = self.runner.invoke(
                    self.app, ["scenario", "show", str(d / "out/scenario.toml")]
                )
                if again.exit_code != 0:
                    self.note("lost_result", f"scenario: {case}: scenario.toml does not reload")

    def sweeps(self) -> None:
        for parameter, values in [
            ("sensing.radius", "[inf]"),
            ("sensing.radius", "[1e300]"),
            ("detector.rho", "[nan]"),
            ("detector.rho", '["x"]'),
            ("estimator.ukf_kappa", "[-3.0]"),
            ("team.spacing", "[0.25, 1e300]"),
            ("trigger.zeta_s", "[inf]"),
            ("motion.dt", "[1e-7]"),
            ("nope.key", "[1]"),
        ]:
            d = self.fresh("sweep")
            p = d / "sweep.toml"
            p.write_text(
                toml_text(TINY) + f'[sweep]\nparameter = "{parameter}"\nvalues = {values}\n'
            )
            self.invoke(
                "sweep",
                f"{parameter} = {values}",
                [
                    "sweep",
                    str(p),
                    "--out",
                    str(d / "o"),
                    "--seeds",
                    "1",
                    "--jobs",
                    "1",
                    "--no-plots",
                ],
                absurd=any(a in values for a in ABSURD),
            )

    def options(self) -> None:
        d = self.fresh("options")
        tiny = d / "tiny.toml"
        tiny.write_text(toml_text(TINY))
        mr = ["mrclam", str(FIXTURE), "-f", "ekf", "--no-plots", "--duration", "20"]
        cases = {
            "--seed 10**40": ["run", str(tiny), "--seed", str(10**40)],
            "--seed -1": ["run", str(tiny), "--seed", "-1"],
            "--seed abc": ["run", str(tiny), "--seed", "abc"],
            "--filter kalman": ["run", str(tiny), "--filter", "kalman"],
            "--bogus": ["run", "--bogus"],
            "no such command": ["bogus"],
            "mrclam missing path": ["mrclam"],
            "sweep --jobs 0": ["sweep", str(tiny), "--jobs", "0"],
            "reproduce --seeds 1": ["reproduce", "--seeds", "1"],
            "compare --seeds 1": ["compare", "--seeds", "1"],
        }
        for value in ["1e-7", "inf", "nan", "0", "-1", "2", "abc"]:
            cases[f"mrclam --dt {value}"] = [*mr, "--dt", value]
        for flag in ["--duration", "--rho", "--range-std", "--bearing-std"]:
            for value in ["inf", "nan", "-1", "1e300"]:
                cases[f"mrclam {flag} {value}"] = [*mr[:-2], flag, value]
        cases["mrclam --seed 2**64"] = [*mr, "--seed", str(2**64)]
        for case, args in cases.items():
            out = self.fresh("opt") / "out"
            absurd = any(a in case.split()[-1] for a in ("inf", "nan", "1e300", "10**40", "2**64"))
            self.invoke("options", case, [*args, "--out", str(out)], absurd=absurd)

    def outs(self) -> None:
        d = self.fresh("outs")
        tiny = d / "tiny.toml"
        tiny.write_text(toml_text(TINY))
        sweep = d / "sweep.toml"
        sweep.write_text(toml_text(TINY) + '[sweep]\nparameter = "detector.rho"\nvalues = [0.5]\n')
        afile = d / "afile"
        afile.write_text("x")
        commands = {
            "run": ["run", str(tiny), "--no-plots"],
            "mrclam": ["mrclam", str(FIXTURE), "-f", "ekf", "--duration", "20", "--no-plots"],
            "sweep": ["sweep", str(sweep), "--seeds", "1", "--jobs", "1", "--no-plots"],
        }
        outs = {
            ".": ".",
            "afile/sub": str(afile / "sub"),
            "long name": str(d / ("n" * 250)),
            "/proc/x": "/proc/resloc-audit",
            "inside the input": str(FIXTURE / "results"),
        }
        cwd = os.getcwd()
        os.chdir(d)
        try:
            for command, args in commands.items():
                for case, out in outs.items():
                    if case == "inside the input" and command != "mrclam":
                        continue  # the fixture is only mrclam's input
                    self.invoke("out", f"{command} --out {case}", [*args, "--out", out])
        finally:
            os.chdir(cwd)
        leaked = FIXTURE / "results"
        if leaked.exists():
            self.note("wrote_into_input", "mrclam --out inside its dataset folder was written")
            shutil.rmtree(leaked)

    def mrclam(self) -> None:
        def edit(name: str, fn) -> callable:
            def apply(folder: Path) -> None:
                p = folder / name
                lines = p.read_text().splitlines()
                p.write_text("\n".join(fn(lines)) + "\n")

            return apply

        def data_idx(lines):
            return [k for k, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")]

        def move_late_row_up(lines):
            idx = data_idx(lines)
            late = lines.pop(idx[int(0.8 * len(idx))])
            lines.insert(idx[2], late)
            return lines

        def replace_value(col, value):
            def fn(lines):
                k = data_idx(lines)[5]
                parts = lines[k].split()
                parts[col] = value
                lines[k] = " ".join(parts)
                return lines

            return fn

        def duplicate(conflict):
            def fn(lines):
                k = data_idx(lines)[10]
                row = lines[k].split()
                if conflict:
                    row[1] = str(float(row[1]) + 0.5)
                lines.insert(k + 1, " ".join(row))
                return lines

            return fn

        def header_only(lines):
            return [ln for ln in lines if ln.startswith("#")]

        def equal_times(lines):
            idx = data_idx(lines)
            t = lines[idx[0]].split()[0]
            for k in idx:
                lines[k] = " ".join([t, *lines[k].split()[1:]])
            return lines

        def far_future(lines):
            k = data_idx(lines)[-1]
            lines[k] = " ".join(["2248444175.0", *lines[k].split()[1:]])
            return lines

        cases = {}
        for dur in (None, "30"):
            for name in ("Robot1_Odometry.dat", "Robot3_Groundtruth.dat", "Robot2_Measurement.dat"):
                cases[f"late row moved up in {name}, duration {dur}"] = (
                    edit(name, move_late_row_up),
                    dur,
                )
            cases[f"duplicate odometry row, duration {dur}"] = (
                edit("Robot2_Odometry.dat", duplicate(False)),
                dur,
            )
            cases[f"conflicting odometry row, duration {dur}"] = (
                edit("Robot2_Odometry.dat", duplicate(True)),
                dur,
            )
        for value, col, name in [
            ("1e300", 2, "Robot1_Odometry.dat"),
            ("1e6", 3, "Robot1_Measurement.dat"),
            ("1e300", 1, "Robot4_Groundtruth.dat"),
            ("-0.1", 3, "Landmark_Groundtruth.dat"),
            ("1_000", 1, "Robot1_Odometry.dat"),
            ("inf", 1, "Robot1_Odometry.dat"),
            ("nan", 2, "Robot2_Groundtruth.dat"),
            ("0x10", 0, "Robot2_Groundtruth.dat"),
            ("-5", 0, "Robot5_Measurement.dat"),
            ("14.5", 1, "Robot5_Measurement.dat"),
        ]:
            cases[f"{name} column {col} = {value}"] = (edit(name, replace_value(col, value)), None)
        cases["empty odometry file"] = (edit("Robot3_Odometry.dat", header_only), None)
        cases["empty measurement file"] = (edit("Robot3_Measurement.dat", header_only), None)
        cases["all-equal odometry timestamps"] = (edit("Robot3_Odometry.dat", equal_times), None)
        cases["one timestamp 1e9 s late (the 37 GiB case)"] = (
            edit("Robot2_Odometry.dat", far_future),
            None,
        )
        cases["missing Barcodes.dat"] = (lambda f: (f / "Barcodes.dat").unlink(), None)
        cases["CRLF line endings"] = (
            lambda f: (f / "Robot1_Odometry.dat").write_bytes(
                (f / "Robot1_Odometry.dat").read_bytes().replace(b"\n", b"\r\n")
            ),
            None,
        )
        for case, (mutate, duration) in cases.items():
            if case in self.skip:
                self.note("skipped", f"mrclam: {case}")
                continue
            d = self.fresh("mrclam")
            folder = d / FIXTURE.name
            shutil.copytree(FIXTURE, folder)
            mutate(folder)
            args = ["mrclam", str(folder), "-f", "ekf", "--no-plots", "--out", str(d / "out")]
            if duration:
                args += ["--duration", duration]
            res = self.invoke("mrclam", case, args)
            if res is not None and res.exit_code == 0:
                self.check_rows(case, folder, d / "out" / "summary.json", duration)

    def check_rows(self, case: str, folder: Path, summary_path: Path, duration) -> None:
        """Rows in the files (inside the replay window) = rows loaded + rows counted."""
        summary = json.loads(summary_path.read_text())
        info = summary["info"]

        def times(p: Path) -> list[float]:
            out = []
            for ln in p.read_text().splitlines():
                if ln.strip() and not ln.lstrip().startswith("#"):
                    out.append(float(ln.split()[0]))
            return out

        t0 = max(min(times(p)) for p in folder.glob("Robot*_Groundtruth.dat"))
        keys = {"Groundtruth": "groundtruth", "Odometry": "odometry", "Measurement": "measurements"}
        for kind, key in keys.items():
            cut = np.inf if duration is None else t0 + float(duration)
            if kind == "Groundtruth":
                cut += 1.0
            expected = sum(
                sum(1 for t in times(p) if t <= cut) for p in folder.glob(f"Robot*_{kind}.dat")
            )
            counted = sum(
                v
                for name, counts in info["rows_skipped_by_file"].items()
                if name.endswith(f"_{kind}.dat")
                for reason, v in counts.items()
                if reason != "out_of_order"
            )
            missing = expected - info["rows_loaded"][key] - counted
            if missing > 0:
                self.note("silent_drop", f"mrclam: {case}: {missing} {kind} rows")

    # ------------------------------------------------------------------ kills
    def kills(self, n: int, seed: int = 20261123) -> None:
        rng = np.random.default_rng(seed)
        d = self.fresh("kills")
        scenario = d / "k.toml"
        scenario.write_text('[run]\nsteps = 150\nfilters = ["ckf", "ekf"]\n[team]\nrobots = 6\n')
        commands = {
            "run": ["run", str(scenario), "--no-progress"],
            "mrclam": ["mrclam", str(FIXTURE), "-f", "ekf", "--duration", "20", "--no-progress"],
        }
        for command, base in commands.items():
            out = d / f"out-{command}"
            args = [*base, "--out", str(out), "--overwrite"]
            t0 = time.perf_counter()
            self.process(args).wait(timeout=300)
            duration = time.perf_counter() - t0
            signals = [signal.SIGTERM, signal.SIGKILL, signal.SIGINT]
            for k in range(n):
                self.cases["kill"] += 1
                kind = signals[k % 3]
                proc = self.process(args)
                time.sleep(float(rng.uniform(0.1, 1.1 * duration)))
                proc.send_signal(kind)
                try:
                    proc.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    self.note("orphan", f"{command}: did not stop after {kind.name}")
                err = proc.stderr.read()
                proc.stderr.close()
                if "Traceback" in err:
                    self.note("traceback", f"kill {command} {kind.name}: {err[-200:]!r}")
                time.sleep(0.2)
                try:
                    os.killpg(proc.pid, 0)
                    self.note("orphan", f"{command}: process group alive after {kind.name}")
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                if not (out / "summary.json").exists():
                    self.note("lost_result", f"kill {command} {kind.name}: --out without results")
                nxt = self.process(args)
                nxt.wait(timeout=300)
                nxt.stderr.close()
                litter = [p.name for p in d.iterdir() if p.name.startswith(f".{out.name}.")]
                if litter:
                    self.note("leftover", f"{command} after {kind.name} + next run: {litter}")

    @staticmethod
    def process(args: list[str]) -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, "-c", "from resloc.cli.app import main; main()", *args],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=12, help="kills per command (run, mrclam)")
    ap.add_argument("--json", type=Path, default=None, help="write the counts here")
    ap.add_argument(
        "--skip",
        action="append",
        default=[],
        help="skip a special case by name (e.g. a version that runs 'robots 200000' for minutes)",
    )
    opts = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="resloc-audit-"))
    t0 = time.perf_counter()
    audit = Audit(work)
    audit.skip = set(opts.skip)
    try:
        for klass in (audit.scenarios, audit.sweeps, audit.options, audit.outs, audit.mrclam):
            klass()
        audit.kills(opts.kills)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    kinds = ["traceback", "multi_line", "hang", "absurd_accepted", "silent_drop",
             "lost_result", "wrote_into_input", "orphan", "leftover", "skipped"]  # fmt: skip
    report = {
        "cases": dict(audit.cases),
        "total_cases": sum(audit.cases.values()),
        "counts": {k: audit.counts.get(k, 0) for k in kinds},
        "examples": audit.examples,
        "wall_time_s": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(report, indent=2))
    if opts.json:
        opts.json.write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
