"""The command line: typer's CliRunner on the real app (typer bundles its own click)."""

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from resloc.cli.app import app

runner = CliRunner()

TINY = """
[run]
steps = 40
filters = ["ckf", "ekf"]
[team]
robots = 5
"""


@pytest.fixture
def tiny(tmp_path) -> Path:
    p = tmp_path / "tiny.toml"
    p.write_text(TINY)
    return p


def test_run_writes_every_output(tiny, tmp_path):
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", str(tiny), "--out", str(out), "--seed", "3"])
    assert res.exit_code == 0, res.output
    assert "CKF" in res.output and "EKF" in res.output and "dead reckoning" in res.output
    for name in (
        "scenario.toml",
        "summary.json",
        "timeseries.csv",
        "trajectories.csv",
        "transmissions_ckf.csv",
        "trajectories.png",
        "msle.png",
        "transmissions.png",
    ):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["seed"] == 3 and summary["robots"] == 5
    assert set(summary["estimators"]) == {"ckf", "ekf", "dr"}
    # The written scenario re-runs to the same numbers.
    again = tmp_path / "again"
    res2 = runner.invoke(
        app, ["run", str(out / "scenario.toml"), "--out", str(again), "--no-plots"]
    )
    assert res2.exit_code == 0, res2.output
    s2 = json.loads((again / "summary.json").read_text())
    assert s2["estimators"]["ckf"]["msle_mean"] == summary["estimators"]["ckf"]["msle_mean"]


def test_filter_option_selects_one(tiny, tmp_path):
    out = tmp_path / "o"
    res = runner.invoke(app, ["run", str(tiny), "-f", "ukf", "--out", str(out), "--no-plots"])
    assert res.exit_code == 0, res.output
    assert set(json.loads((out / "summary.json").read_text())["estimators"]) == {"ukf", "dr"}


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        ("[sensing]\nradius = -1.0\n", "sensing.radius"),
        ("[team]\nrobots = 0\n", "team.robots"),
        ("[sensing]\nbearing_std = -0.1\n", "sensing.bearing_std"),
        ("[run]\nstepz = 5\n", "run.stepz: unknown key"),
        ("[detector]\nrho = 'big'\n", "detector.rho"),
        ("not toml at all [", "not valid TOML"),
    ],
)
def test_bad_scenario_exits_2_with_one_line_and_writes_nothing(tmp_path, content, needle):
    bad = tmp_path / "bad.toml"
    bad.write_text(content)
    out = tmp_path / "never"
    res = runner.invoke(app, ["run", str(bad), "--out", str(out)])
    assert res.exit_code == 2
    err = res.stderr if hasattr(res, "stderr") else res.output
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], err
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["bad.toml"]


def test_existing_output_is_not_clobbered(tiny, tmp_path):
    out = tmp_path / "keep"
    out.mkdir()
    (out / "precious.txt").write_text("data")
    res = runner.invoke(app, ["run", str(tiny), "--out", str(out)])
    assert res.exit_code == 2 and "--overwrite" in (res.stderr or res.output)
    assert (out / "precious.txt").read_text() == "data"
    res = runner.invoke(app, ["run", str(tiny), "--out", str(out), "--overwrite", "--no-plots"])
    assert res.exit_code == 0
    assert not (out / "precious.txt").exists() and (out / "summary.json").exists()


def test_missing_file_and_bad_arguments(tmp_path):
    res = runner.invoke(app, ["run", str(tmp_path / "nope.toml")])
    assert res.exit_code == 2 and "no such scenario file" in (res.stderr or res.output)
    res = runner.invoke(app, ["run", "--filter", "kalman"])
    assert res.exit_code == 2
    res = runner.invoke(app, ["run", "--seed", "-4"])
    assert res.exit_code == 2


def test_scenario_show_prints_loadable_toml(tmp_path):
    res = runner.invoke(app, ["scenario", "show"])
    assert res.exit_code == 0
    p = tmp_path / "d.toml"
    p.write_text(res.stdout)
    res2 = runner.invoke(app, ["scenario", "show", str(p)])
    assert res2.exit_code == 0 and res2.stdout == res.stdout
    assert "[[sdz]]" in res.stdout and "robots = 17" in res.stdout


def test_table_helpers(capsys, monkeypatch):
    """One table printer for every command: labels left, numbers right, ``-`` for a missing
    number, the given width when stdout is not a terminal (no wrapping in a log file)."""
    from resloc.cli.common import number, print_table, timestamped_out

    assert number(float("nan")) == "-" and number(None) == "-" and number(0.5, ".2f") == "0.50"
    rows = [("dead reckoning", number(1234.5678, ".1f")), ("CKF", number(2.0, ".1f"))]
    print_table("title", ("estimator", "value"), rows, width=60)
    out = capsys.readouterr().out.splitlines()
    assert max(len(line) for line in out) <= 60
    body = [line for line in out if "CKF" in line or "dead" in line]
    assert body[0].index("1234.6") > body[0].index("dead reckoning")
    assert body[1].endswith("    2.0 │") and body[1].startswith("│ CKF ")  # right / left
    wide = [("x" * 150, "1")]
    print_table("t", ("name", "n"), wide, width=200)
    assert any("x" * 150 in line for line in capsys.readouterr().out.splitlines())
    stamp = timestamped_out("sweep")
    assert stamp.parent.name == "runs" and stamp.name.startswith("sweep-")
    assert timestamped_out().name[:2] == "20"


def test_progress_is_off_without_a_terminal(monkeypatch):
    """``--progress`` (the default) draws a bar only when stderr is a terminal."""
    import sys

    import typer

    compare = typer.main.get_command(app).commands["compare"]
    assert compare.make_context("compare", []).params["progress"] is False
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert compare.make_context("compare", []).params["progress"] is True
    assert compare.make_context("compare", ["--no-progress"]).params["progress"] is False
