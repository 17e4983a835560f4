"""Generalized sweep files (grid, zip, several dotted keys) and the tidy results table."""

import csv
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from resloc.cli.app import app
from resloc.errors import ConfigError
from resloc.experiments.sweep import (
    METRICS,
    TIDY_COLUMNS,
    dump_sweep,
    load_sweep,
    parse_sweep,
    run_sweep,
    save_sweep,
    tidy_rows,
)

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "paper"
runner = CliRunner()

BASE = {
    "run": {"steps": 12, "trials": 2},
    "team": {"robots": 4},
    "sdz": [{"center": [0.45, -0.55], "radius": 0.4}],
    "cdz": [{"center": [0.2, 0.45], "radius": 0.3}],
}
GRID_FILE = """
[sweep]
name = "grid and zip"
filters = ["ckf", "ekf"]

[sweep.grid]
detector.rho = [0.3, 0.9]

[sweep.zip]
"sdz.radius" = [0.2, 0.5]
"cdz.radius" = [0.25, 0.45]

[run]
steps = 12
trials = 2

[team]
robots = 4

[[sdz]]
center = [0.45, -0.55]
radius = 0.4

[[cdz]]
center = [0.2, 0.45]
radius = 0.3
"""


def _sweep(**sweep):
    return parse_sweep({"sweep": sweep, **BASE}, source="s.toml")


def test_grid_is_the_product_in_file_order():
    spec = _sweep(grid={"detector.rho": [0.3, 0.9], "trigger": {"alpha": [0.1, 0.2, 0.4]}})
    assert spec.parameters == ("detector.rho", "trigger.alpha")
    assert spec.values == tuple((r, a) for r in (0.3, 0.9) for a in (0.1, 0.2, 0.4))
    scen = spec.scenarios()
    assert [(s.detector.rho, s.trigger.alpha) for s in scen] == list(spec.values)
    assert spec.label(spec.values[1]) == "rho=0.3, alpha=0.2" and not spec.numeric


def test_zip_and_grid_times_zip(tmp_path):
    spec = _sweep(zip={"detector.rho": [0.3, 0.9], "team.robots": [4, 6]})
    assert spec.values == ((0.3, 4), (0.9, 6))
    f = tmp_path / "g.toml"
    f.write_text(GRID_FILE)
    spec = load_sweep(f)
    assert spec.parameters == ("detector.rho", "sdz.radius", "cdz.radius")
    assert spec.values == ((0.3, 0.2, 0.25), (0.3, 0.5, 0.45), (0.9, 0.2, 0.25), (0.9, 0.5, 0.45))
    s = spec.scenario(spec.values[3])
    assert (s.detector.rho, s.world.sdz[0].radius, s.world.cdz[0].radius) == (0.9, 0.5, 0.45)
    again = tmp_path / "again.toml"
    again.write_text(dump_sweep(spec))
    assert load_sweep(again) == spec  # several parameters round-trip as explicit zip columns


@pytest.mark.parametrize(
    "sweep, needle",
    [
        ({"grid": {"detector.rho": [0.3]}, "parameter": "detector.rho"}, "not both"),
        ({"grid": {}}, "sweep.grid: expected a table"),
        ({"grid": {"detector.rho": []}}, "sweep.grid.detector.rho: expected a non-empty"),
        ({"grid": {"detector.rho": [0.3, -1.0]}}, "sweep.grid.detector.rho[1]"),
        ({"zip": {"detector.rhoo": [0.3]}}, "sweep.zip.detector.rhoo"),
        ({"grid": {"run.seed": [1, 2]}}, "sweep.grid.run.seed: run.seed cannot be swept"),
        ({"zip": {"detector.rho": [0.3, 0.5], "trigger.alpha": [0.1]}}, "different lengths"),
        ({"zip": {"detector.rho": [0.3, 0.3], "trigger.alpha": [0.1, 0.1]}}, "a point twice"),
        (
            {"grid": {"detector.rho": [0.3]}, "zip": {"detector.rho": [0.5]}},
            "sweep.zip.detector.rho: also in sweep.grid",
        ),
        ({"grid": {"team.robots": [[4]]}}, "sweep.grid.team.robots[0]"),
    ],
)
def test_schema_errors_name_the_field(sweep, needle):
    with pytest.raises(ConfigError) as err:
        _sweep(**sweep)
    msg = str(err.value)
    assert needle in msg and msg.startswith("s.toml: ") and "\n" not in msg


def test_bad_grid_file_exits_2_with_one_line(tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text(GRID_FILE.replace('"cdz.radius" = [0.25, 0.45]', '"cdz.radius" = [0.25]'))
    out = tmp_path / "out"
    res = runner.invoke(app, ["sweep", str(f), "--out", str(out), "-j", "1"])
    assert res.exit_code == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "sweep.zip: arrays of different lengths" in lines[0]
    assert not out.exists()


PAPER_SWEEPS = sorted(p for p in EXAMPLES.glob("*.toml") if "[sweep]" in p.read_text())


def test_paper_sweeps_exist():
    assert len(PAPER_SWEEPS) >= 4


@pytest.mark.parametrize("path", PAPER_SWEEPS, ids=lambda p: p.name)
def test_paper_sweep_files_still_load(path):
    spec = load_sweep(path)
    assert isinstance(spec.parameter, str) and spec.parameters == (spec.parameter,)
    assert len(spec.scenarios(seeds=2, steps=5)) == len(spec.values)


def test_tidy_table_csv_and_parquet(tmp_path):
    spec = load_sweep(_write(tmp_path, GRID_FILE))
    result = run_sweep(spec, jobs=1)
    columns, rows = tidy_rows(result)
    assert columns == ["point", *spec.parameters, *TIDY_COLUMNS]
    names = ["ckf", "ekf", "dr"]
    assert len(rows) == len(spec.values) * len(names) * 2
    by = {(r[0], r[columns.index("estimator")], r[columns.index("trial")]): r for r in rows}
    ckf = result.runs[2].estimators["ckf"]
    for t in range(2):
        row = by[(2, "ckf", t)]
        assert row[1:4] == list(spec.values[2]) and row[columns.index("status")] == "ok"
        for m in METRICS:
            assert row[columns.index(m)] == float(ckf.per_trial(m)[t])
    out = tmp_path / "out"
    out.mkdir()
    save_sweep(result, out, plots=False)
    with (out / "cells.csv").open() as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == len(rows) and table[0]["detector.rho"] == "0.3"
    assert (
        table[0]["comm_rate"] and not next(r for r in table if r["estimator"] == "dr")["comm_rate"]
    )  # dead reckoning does not communicate
    import pyarrow.parquet as pq  # the extra `parquet` (make test installs it)

    frame = pq.read_table(out / "cells.parquet").to_pydict()
    assert frame["msle_mean"] == [float(r["msle_mean"]) for r in table]
    assert frame["sdz.radius"][:3] == [0.2, 0.2, 0.2]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["parameter"] == list(spec.parameters)
    assert summary["values"][1] == [0.3, 0.5, 0.45]


def test_grid_sweep_command(tmp_path):
    f = _write(tmp_path, GRID_FILE)
    out = tmp_path / "out"
    res = runner.invoke(app, ["sweep", str(f), "--out", str(out), "-j", "1"])
    assert res.exit_code == 0, res.output
    assert "rho=0.9, sdz.radius=0.5, cdz.radius=0.45" in res.output
    assert "cells: 24 (0 from the store" in res.stderr
    for name in ("cells.csv", "sweep.csv", "summary.json", "sweep.png", "msle_time.png"):
        assert (out / name).is_file(), name
    assert len((out / "cells.csv").read_text().splitlines()) == 1 + 24


def _write(tmp_path, text):
    f = tmp_path / "s.toml"
    f.write_text(text)
    return f
