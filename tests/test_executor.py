"""The study executor: store hits, resumed cells, failures, backend choice (in-process)."""

import json
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from resloc.cli.app import app
from resloc.errors import ConfigError
from resloc.experiments import backends
from resloc.experiments import cells as cells_mod
from resloc.experiments.cells import run_scenarios
from resloc.experiments.config_parse import parse_scenario
from resloc.experiments.executor import Study, StudyFailedError, Task, open_backend
from resloc.experiments.store import CorruptEntryWarning, ResultStore

runner = CliRunner()

TINY = {
    "run": {"steps": 20, "trials": 2, "filters": ["ckf", "ekf"]},
    "team": {"robots": 4},
    "sdz": [{"center": [0.45, -0.55], "radius": 0.4}],
}
SWEEP = """
[sweep]
name = "failing point"
parameter = "detector.rho"
values = [0.3, 0.5, 0.8]
filters = ["ckf"]

[run]
steps = 15
trials = 2

[team]
robots = 4
"""


def _double(x):
    return [2 * x]


def _boom(x):
    raise ValueError(f"cell {x} cannot be computed")


def _series(results, name="ckf", key="msle"):
    return [r.estimators[name].series[key] for r in results]


def test_failing_task_is_reported_and_the_others_go_on(tmp_path):
    store = ResultStore(tmp_path)
    study = Study(jobs=1, store=store)
    tasks = [
        Task(_double, (1,), ("k1",), "one"),
        Task(_boom, (2,), ("k2",), "two", {"scenario": {"team": {"robots": 3}}}),
        Task(_double, (3,), ("k3",), "three"),
    ]
    out = study.run(tasks, cells=3)
    assert out == {"k1": 2, "k3": 6}
    assert store.get("k1") == (True, 2) and store.get("k2") == (False, None)
    (failure,) = study.failures
    assert failure.key == "k2" and failure.context["scenario"]["team"]["robots"] == 3
    assert "ValueError: cell 2 cannot be computed" in failure.error
    assert "_boom" in failure.traceback and "Traceback" in failure.traceback
    assert (study.stats.computed, study.stats.failed) == (2, 1)


def test_store_serves_repeated_and_extended_studies(tmp_path):
    base = parse_scenario(TINY)
    scen = [base.replace(**{"detector.rho": r}) for r in (0.3, 0.6)]
    fresh = run_scenarios([s.replace(**{"run.trials": 4}) for s in scen], jobs=1)

    store = ResultStore(tmp_path)
    first = Study(jobs=1, store=store)
    run_scenarios(scen, study=first)  # trials 0, 1 of both points, ckf + ekf + dr
    assert (first.stats.cells, first.stats.computed) == (12, 12)

    again = Study(jobs=1, store=store)
    repeated = run_scenarios(scen, study=again)
    assert (again.stats.from_store, again.stats.computed) == (12, 0)
    assert repeated[0].truth is not None and repeated[0].truth is repeated[0].truth

    # Two more seeds: only their cells are computed; the numbers equal a run of all four.
    more = Study(jobs=1, store=store)
    extended = run_scenarios([s.replace(**{"run.trials": 4}) for s in scen], study=more)
    assert (more.stats.from_store, more.stats.computed) == (12, 12)
    for a, b in zip(_series(fresh), _series(extended), strict=True):
        np.testing.assert_array_equal(a, b)
    # A filter subset is read from the same cells.
    ekf_only = Study(jobs=1, store=store)
    (one,) = run_scenarios([scen[0].replace(**{"run.filters": ["ekf"]})], study=ekf_only)
    assert ekf_only.stats.computed == 0 and set(one.estimators) == {"ekf", "dr"}

    # --fresh: nothing read, everything computed (and written again).
    refreshed = Study(jobs=1, store=ResultStore(tmp_path, read=False))
    run_scenarios(scen, study=refreshed)
    assert (refreshed.stats.from_store, refreshed.stats.computed) == (0, 12)


def test_corrupt_cell_is_recomputed_with_a_warning(tmp_path):
    store = ResultStore(tmp_path)
    scen = [parse_scenario(TINY)]
    (ref,) = run_scenarios(scen, study=Study(jobs=1, store=store))
    victim = store.path(store.keys()[0])
    victim.write_bytes(victim.read_bytes()[:-7])
    study = Study(jobs=1, store=store)
    with pytest.warns(CorruptEntryWarning):
        (again,) = run_scenarios(scen, study=study)
    assert (study.stats.from_store, study.stats.computed) == (5, 1)  # only the corrupt cell
    for name in ("ckf", "ekf", "dr"):
        np.testing.assert_array_equal(
            ref.estimators[name].series["nees"], again.estimators[name].series["nees"]
        )


def test_failed_cell_in_sweep_results_then_resumed(tmp_path, monkeypatch):
    f = tmp_path / "s.toml"
    f.write_text(SWEEP)
    store = tmp_path / "store"
    real = cells_mod.simulate_cells

    def flaky(scenario, *args):
        if scenario.detector.rho == 0.5:
            raise FloatingPointError("diverged at rho 0.5")
        return real(scenario, *args)

    monkeypatch.setattr(cells_mod, "simulate_cells", flaky)
    out = tmp_path / "out"
    args = ["sweep", str(f), "-j", "1", "--store", str(store), "--no-plots", "--out", str(out)]
    res = runner.invoke(app, args)
    assert res.exit_code == 1, res.output
    assert "4 cell(s) failed" in res.stderr  # seeds 0, 1 x ckf, dr of one point
    rows = (out / "cells.csv").read_text().splitlines()
    failed = [r for r in rows if ",failed," in r]
    assert len(failed) == 2 * 2 and all("diverged at rho 0.5" in r for r in failed)  # ckf, dr
    assert sum(",ok," in r for r in rows) == 2 * 2 * 2
    failures = json.loads((out / "failures.json").read_text())
    assert len(failures) == 4 and len({f["key"] for f in failures}) == 4
    for fail in failures:
        assert fail["context"]["scenario"]["detector"]["rho"] == 0.5
        assert "FloatingPointError" in fail["traceback"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["points"][1] == {"value": 0.5, "failed": True}

    monkeypatch.setattr(cells_mod, "simulate_cells", real)
    res = runner.invoke(app, [*args[:-1], str(tmp_path / "out2")])
    assert res.exit_code == 0, res.output
    assert "cells: 12 (8 from the store" in res.stderr and "4 computed" in res.stderr


def test_reproduce_with_a_failed_cell_writes_failures(tmp_path, monkeypatch):
    import resloc.experiments.reproduce as rep

    def broken(seeds=None, steps=None, quick=False, jobs=1, progress=None, study=None):
        study.run([Task(_boom, (7,), ("kx",), "exp: seeds 0..1", {"scenario": {}})], cells=1)
        raise StudyFailedError(study.failures, study.stats)

    monkeypatch.setattr(rep, "run_reproduction", broken)
    out = tmp_path / "rep"
    res = runner.invoke(app, ["reproduce", "--quick", "-j", "1", "--out", str(out)])
    assert res.exit_code == 1
    assert "1 of 1 cells failed" in res.stderr and "failures.json" in res.stderr
    (f,) = json.loads((out / "failures.json").read_text())
    assert f["label"] == "exp: seeds 0..1" and "cell 7 cannot be computed" in f["error"]


def test_backend_choice_and_missing_extra(monkeypatch):
    with open_backend(jobs=8, scheduler=None, tasks=1) as backend:
        assert backend.name == "serial"  # capped by the tasks
    monkeypatch.setattr(backends, "default_jobs", lambda: 1)
    with open_backend(jobs=8, scheduler=None, tasks=10) as backend:
        assert backend.name == "serial"  # capped by the CPUs
    monkeypatch.setattr(backends, "default_jobs", lambda: 4)
    monkeypatch.setitem(sys.modules, "distributed", None)  # the extra is not installed
    with open_backend(jobs=None, scheduler=None, tasks=10) as backend:
        assert backend.name == "serial"  # the documented fallback of the default
    with pytest.raises(ConfigError, match=r"--jobs 2 needs Dask .*pip install 'resloc\[cluster\]'"):
        with open_backend(jobs=2, scheduler=None, tasks=10):
            pass
    with pytest.raises(ConfigError, match=r"--scheduler tcp://127\.0\.0\.1:1"):
        with open_backend(jobs=None, scheduler="tcp://127.0.0.1:1", tasks=10):
            pass


def test_bad_scheduler_address_exits_2(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text(SWEEP)
    res = runner.invoke(
        app, ["sweep", str(f), "--scheduler", "localhost", "--out", str(tmp_path / "o")]
    )
    assert res.exit_code == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "--scheduler localhost: expected tcp://HOST:PORT" in lines[0]


def test_unreachable_scheduler_is_one_line_error():
    with pytest.raises(ConfigError, match="cannot connect"):
        with open_backend(jobs=None, scheduler="tcp://127.0.0.1:9", tasks=3, timeout=1.0):
            pass


def test_help_imports_no_optional_extra():
    code = (
        "import sys\n"
        "from typer.testing import CliRunner\n"
        "from resloc.cli.app import app\n"
        "for cmd in ([], ['sweep'], ['reproduce'], ['compare']):\n"
        "    CliRunner().invoke(app, [*cmd, '--help'])\n"
        "bad = [m for m in ('dask', 'distributed', 'pyarrow', 'matplotlib') if m in sys.modules]\n"
        "print(bad)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.strip() == "[]"
