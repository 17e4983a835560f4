"""The ``resloc mrclam`` command: outputs, zones, one-line errors, the noise fit."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from resloc.cli.app import app

FIXTURE = Path(__file__).parent / "fixtures" / "mrclam" / "MRCLAM_Dataset6_60s"
runner = CliRunner()


def _stderr(res) -> str:
    return res.stderr if hasattr(res, "stderr") else res.output


def test_cli_writes_outputs(tmp_path: Path):
    out = tmp_path / "run"
    res = runner.invoke(
        app,
        ["mrclam", str(FIXTURE), "-f", "ckf", "--duration", "30", "-o", str(out), "--no-plots"],
    )
    assert res.exit_code == 0, res.output
    assert "CKF" in res.stdout and "DR" in res.stdout
    assert {p.name for p in out.iterdir()} == {
        "summary.json",
        "per_robot.csv",
        "timeseries.csv",
        "recording.npz",
    }
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["overall"]) == {"dr", "ckf"}
    assert summary["info"]["replayed_s"] == pytest.approx(30.0)


def test_cli_zones_and_plots(tmp_path: Path):
    out = tmp_path / "zones"
    args = ["mrclam", str(FIXTURE), "-f", "ekf", "--duration", "40", "--zones", "-o", str(out)]
    res = runner.invoke(app, [*args, "--sdz", "2.3", "-1.5", "1.0", "--seed", "2"])
    assert res.exit_code == 0, res.output
    assert "falsified in the SDZ" in res.stdout
    assert (out / "trajectories.png").exists() and (out / "errors.png").exists()
    assert json.loads((out / "summary.json").read_text())["config"]["sdz"] == [2.3, -1.5, 1.0]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["/definitely/not/here"], "no such dataset folder"),
        ([str(FIXTURE), "--dt", "0"], "--dt: 0.0 is out of range; use >= 0.001 s"),
        ([str(FIXTURE), "--sdz", "1", "1", "1"], "also pass --zones"),
    ],
)
def test_cli_bad_input_exits_2_with_one_line(args, message, tmp_path: Path):
    res = runner.invoke(app, ["mrclam", *args, "-o", str(tmp_path / "x")])
    assert res.exit_code == 2
    err = _stderr(res).strip()
    assert message in err
    assert len(err.splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_cli_malformed_file_exits_2_naming_file_and_line(tmp_path: Path):
    import shutil

    bad = tmp_path / "MRCLAM_Dataset6_60s"
    shutil.copytree(FIXTURE, bad)
    path = bad / "Robot1_Odometry.dat"
    path.write_text(path.read_text() + "1248444300.0 0.1\n")
    n = path.read_text().count("\n")
    res = runner.invoke(app, ["mrclam", str(bad), "-o", str(tmp_path / "x")])
    assert res.exit_code == 2
    err = _stderr(res).strip()
    assert f"Robot1_Odometry.dat:{n}: expected 3 columns" in err
    assert len(err.splitlines()) == 1


def test_cli_estimate_noise():
    res = runner.invoke(app, ["mrclam", str(FIXTURE), "--estimate-noise"])
    assert res.exit_code == 0, res.output
    assert "landmark sightings" in res.stdout and "omega density" in res.stdout
