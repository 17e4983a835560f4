"""Sweep files, parallel runs (dedupe, workers) and ``resloc sweep``."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from resloc.cli.app import app
from resloc.errors import ConfigError
from resloc.experiments.config import default_scenario
from resloc.experiments.config_parse import parse_scenario
from resloc.experiments.runner import run_scenario
from resloc.experiments.sweep import (
    apply_parameter,
    dump_sweep,
    load_sweep,
    parse_sweep,
    run_scenarios,
    run_sweep,
)

runner = CliRunner()

TINY = {
    "run": {"steps": 25, "trials": 2, "filters": ["ckf", "ekf"]},
    "team": {"robots": 5},
    "sdz": [{"center": [0.45, -0.55], "radius": 0.4}],
    "cdz": [{"center": [0.2, 0.45], "radius": 0.3}],
}
TINY_SWEEP = """
[sweep]
name = "tiny radius sweep"
parameter = "zones.radius"
values = [0.2, 0.5]
filters = ["ckf"]

[run]
steps = 25
trials = 2

[team]
robots = 5

[[sdz]]
center = [-0.4, -0.9]
radius = 0.4

[[cdz]]
center = [0.2, 0.45]
radius = 0.3
"""


def test_parse_sweep_and_zone_parameter(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text(TINY_SWEEP)
    spec = load_sweep(p)
    assert spec.parameter == "zones.radius" and spec.values == (0.2, 0.5)
    assert spec.base.run.filters == ["ckf"] and spec.base.world.team.robots == 5
    pts = spec.scenarios(seeds=3, steps=10)
    assert [s.run.trials for s in pts] == [3, 3] and pts[0].run.steps == 10
    for s, v in zip(pts, spec.values, strict=True):
        assert [z.radius for z in (*s.world.sdz, *s.world.cdz)] == [v, v]
    # sdz.<key> changes only the SDZs; other dotted keys are scenario keys.
    only = apply_parameter(spec.base, "sdz.radius", 0.25)
    assert only.world.sdz[0].radius == 0.25 and only.world.cdz[0].radius == 0.3
    assert apply_parameter(spec.base, "detector.rho", 0.9).detector.rho == 0.9
    # The file round-trips through dump_sweep.
    again = tmp_path / "again.toml"
    again.write_text(dump_sweep(spec))
    assert load_sweep(again) == spec


def test_sweep_base_default_and_relative_file(tmp_path):
    spec = parse_sweep(
        {"sweep": {"parameter": "trigger.alpha", "values": [0.2], "base": "default"}}
    )
    assert spec.base == default_scenario()
    (tmp_path / "base.toml").write_text("[team]\nrobots = 6\n")
    spec = parse_sweep(
        {"sweep": {"parameter": "team.robots", "values": [4], "base": "base.toml"},
         "run": {"steps": 7}},
        base_dir=tmp_path,
    )  # fmt: skip
    assert spec.base.world.team.robots == 6 and spec.base.run.steps == 7


@pytest.mark.parametrize(
    "sweep, extra, needle",
    [
        (None, {}, "no [sweep] table"),
        ({"parameter": "detector.rho", "values": [0.1], "colour": 1}, {}, "sweep.colour: unknown"),
        ({"values": [0.1]}, {}, "sweep.parameter"),
        ({"parameter": "detector.rho", "values": []}, {}, "sweep.values: expected a non-empty"),
        ({"parameter": "detector.rho", "values": [0.1, 0.1]}, {}, "lists a value twice"),
        ({"parameter": "detector.rhoo", "values": [0.1]}, {}, "detector.rhoo: unknown key"),
        ({"parameter": "detector.rho", "values": [0.1, -1.0]}, {}, "sweep.values[1]"),
        ({"parameter": "team.robots", "values": [1.5]}, {}, "team.robots"),
        ({"parameter": "zones.radius", "values": [0.2]}, {}, "no [[sdz]] or [[cdz]] zones"),
        ({"parameter": "run.trials", "values": [2]}, {}, "use --seeds"),
        ({"parameter": "detector.rho", "values": [0.1], "metric": "speed"}, {}, "sweep.metric"),
        ({"parameter": "detector.rho", "values": [0.1], "filters": ["kf"]}, {}, "run.filters"),
        ({"parameter": "detector.rho", "values": [0.1]}, {"run": {"stepz": 3}}, "run.stepz"),
        ({"parameter": "detector.rho", "values": [0.1], "base": "nope.toml"}, {}, "no such"),
    ],
)
def test_sweep_validation_names_the_field(tmp_path, sweep, extra, needle):
    data = dict(extra)
    if sweep is not None:
        data["sweep"] = sweep
    with pytest.raises(ConfigError) as err:
        parse_sweep(data, source="s.toml", base_dir=tmp_path)
    msg = str(err.value)
    assert needle in msg and msg.startswith("s.toml") and "\n" not in msg


@pytest.mark.parametrize(
    "content, needle",
    [
        ("[sweep]\nparameter = 'detector.rho'\nvalues = [-0.5]\n", "detector.rho"),
        ("[sweep]\nvalues = [1]\n", "sweep.parameter"),
        ("[run]\nsteps = 3\n", "no [sweep] table"),
        ("[sweep\n", "not valid TOML"),
    ],
)
def test_bad_sweep_file_exits_2_with_one_line(tmp_path, content, needle):
    bad = tmp_path / "bad.toml"
    bad.write_text(content)
    out = tmp_path / "never"
    res = runner.invoke(app, ["sweep", str(bad), "--out", str(out)])
    assert res.exit_code == 2
    err = res.stderr if hasattr(res, "stderr") else res.output
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], err
    assert not out.exists()
    res = runner.invoke(app, ["sweep", str(tmp_path / "missing.toml")])
    assert res.exit_code == 2 and "no such sweep file" in (res.stderr or res.output)


def test_run_scenarios_dedupes_and_matches_separate_runs():
    base = parse_scenario(TINY)
    a = base.replace(**{"run.filters": ["ckf"], "run.name": "a"})
    b = base.replace(**{"run.filters": ["ekf"], "run.dead_reckoning": False})
    c = base.replace(**{"detector.rho": 0.3, "run.filters": ["ckf"]})
    ra, rb, rc = run_scenarios([a, b, c], jobs=1)
    assert set(ra.estimators) == {"ckf", "dr"} and set(rb.estimators) == {"ekf"}
    assert ra.truth is rb.truth  # simulated once
    assert ra.scenario == a and rb.scenario == b
    alone = run_scenario(b)
    np.testing.assert_array_equal(
        rb.estimators["ekf"].series["msle"], alone.estimators["ekf"].series["msle"]
    )
    assert not np.array_equal(
        ra.estimators["ckf"].series["msle"], rc.estimators["ckf"].series["msle"]
    )


def test_parallel_workers_give_the_same_numbers():
    base = parse_scenario(TINY)
    scen = [base.replace(**{"detector.rho": r}) for r in (0.3, 0.6)]
    seen = []
    serial = run_scenarios(scen, jobs=1)
    parallel = run_scenarios(scen, jobs=2, progress=lambda d, t: seen.append((d, t)))
    for s, p in zip(serial, parallel, strict=True):
        for name in ("ckf", "ekf", "dr"):
            np.testing.assert_array_equal(
                s.estimators[name].series["msle"], p.estimators[name].series["msle"]
            )
    assert seen and seen[-1][0] == pytest.approx(seen[-1][1])


def test_sweep_command_writes_outputs(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text(TINY_SWEEP)
    out = tmp_path / "out"
    res = runner.invoke(app, ["sweep", str(f), "--out", str(out), "--seeds", "2", "-j", "1"])
    assert res.exit_code == 0, res.output
    assert "zones.radius" in res.output and "CKF" in res.output
    for name in ("sweep.toml", "summary.json", "sweep.csv", "sweep.png", "msle_time.png"):
        assert (out / name).is_file(), name
    assert (out / "transmissions_0.png").is_file() and (out / "transmissions_1.png").is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["values"] == [0.2, 0.5] and summary["seeds"] == 2
    point = summary["points"][1]["estimators"]["ckf"]["msle_mean"]
    assert len(point["per_seed"]) == 2 and point["ci_lo"] <= point["mean"] <= point["ci_hi"]
    assert load_sweep(out / "sweep.toml").values == (0.2, 0.5)
    # The library call gives the same numbers.
    again = run_sweep(load_sweep(f), seeds=2)
    assert again.estimates("ckf")[1].mean == pytest.approx(point["mean"], rel=1e-12)
