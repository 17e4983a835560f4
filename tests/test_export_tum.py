"""TUM export: files evo reads, the team / per-robot alignment cross-checked against evo,
old run directories, the ``resloc export`` command and the lazy imports of the exports."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from export_helpers import make_run_dir
from resloc.cli.app import app
from resloc.experiments.config import default_scenario
from resloc.experiments.config_dump import dump_scenario
from resloc.experiments.recording import Recording
from resloc.export import ExportFormat, export_run_dir
from resloc.export.geometry import align_se2, aligned_errors
from resloc.export.tum import read_tum

runner = CliRunner()


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return make_run_dir(tmp_path_factory.mktemp("run"))


@pytest.fixture(scope="module")
def tum(run_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("exp")
    (res,) = export_run_dir(run_dir, [ExportFormat.TUM], out)
    return res


def test_tum_files_hold_every_pose_with_w_last(run_dir, tum):
    rec = Recording.load(run_dir / "recording.npz")
    from evo.tools import file_interface

    for r in (0, 16):
        robot = rec.robots[r]
        traj = file_interface.read_tum_trajectory_file(str(tum.path / f"{robot}.ckf.txt"))
        np.testing.assert_allclose(traj.timestamps, rec.time, atol=1e-6)
        np.testing.assert_allclose(
            traj.positions_xyz[:, :2], rec.estimates["ckf"][:, r, :2], atol=1e-6
        )
        # evo stores quaternions w first: a pure yaw has w = cos(theta / 2) in column 0
        yaw = 2 * np.arctan2(traj.orientations_quat_wxyz[:, 3], traj.orientations_quat_wxyz[:, 0])
        dyaw = np.angle(np.exp(1j * (yaw - rec.estimates["ckf"][:, r, 2])))
        assert np.abs(dyaw).max() < 1e-6
        _stamps, poses = read_tum(tum.path / f"{robot}.groundtruth.txt")
        np.testing.assert_allclose(poses[:, :2], rec.truth[:, r, :2], atol=1e-6)
    assert len(list(tum.path.glob("*.txt"))) == 17 * 4  # truth, ckf, ekf, dr


def test_alignment_matches_evo_ape_per_robot_and_team(tum):
    from evo.core import metrics, sync
    from evo.tools import file_interface

    for robot in ("robot1", "robot9"):
        gt = file_interface.read_tum_trajectory_file(str(tum.path / f"{robot}.groundtruth.txt"))
        for name in ("ckf", "dr"):
            est = file_interface.read_tum_trajectory_file(str(tum.path / f"{robot}.{name}.txt"))
            ref, est = sync.associate_trajectories(gt, est)
            est.align(ref)  # SE(3) Umeyama, one transform for this robot's file
            ape = metrics.APE(metrics.PoseRelation.translation_part)
            ape.process_data((ref, est))
            ours = tum.info[name]["robots"][robot]
            assert ape.get_statistic(metrics.StatisticsType.rmse) == pytest.approx(
                ours["per_robot"], rel=1e-4
            )
            team = file_interface.read_tum_trajectory_file(
                str(tum.path / "team_aligned" / f"{robot}.{name}.txt")
            )
            ref2, team = sync.associate_trajectories(gt, team)
            ape = metrics.APE(metrics.PoseRelation.translation_part)
            ape.process_data((ref2, team))
            assert ape.get_statistic(metrics.StatisticsType.rmse) == pytest.approx(
                ours["team"], rel=1e-4
            )
    # Per-robot alignment flatters dead reckoning (a drift common to one robot vanishes);
    # the team alignment does not.
    dr, ckf = tum.info["dr"], tum.info["ckf"]
    assert dr["per_robot"] < ckf["per_robot"] and dr["team"] > 2 * ckf["team"]


def test_evo_ape_command_line_reads_the_files(tum):
    exe = Path(sys.executable).with_name("evo_ape")
    env = {**os.environ, "HOME": str(tum.path.parent), "MPLBACKEND": "Agg"}
    cmd = [str(exe), "tum", "robot2.groundtruth.txt", "robot2.ukf.txt"]
    aligned = subprocess.run(
        [*cmd[:2], "robot2.groundtruth.txt", "robot2.ekf.txt", "-a"],
        cwd=tum.path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert aligned.returncode == 0, aligned.stderr
    rmse = float(next(ln for ln in aligned.stdout.splitlines() if "rmse" in ln).split()[-1])
    assert rmse == pytest.approx(tum.info["ekf"]["robots"]["robot2"]["per_robot"], rel=1e-3)
    absent = subprocess.run(cmd, cwd=tum.path, env=env, capture_output=True, timeout=120)
    assert absent.returncode != 0  # no UKF in this run: evo says so, nothing made up


def test_team_alignment_recovers_a_common_rigid_motion():
    rng = np.random.default_rng(7)
    truth = rng.uniform(-2, 2, size=(50, 6, 3))
    angle, shift = 0.4, np.array([0.7, -1.2])
    R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    est = truth.copy()
    est[..., :2] = truth[..., :2] @ R.T + shift + rng.normal(0, 0.01, (50, 6, 2))
    err = aligned_errors(truth, est, np.ones((50, 6), bool))
    assert err.raw.min() > 0.5
    assert err.team.max() < 0.02 and err.per_robot.max() < 0.02
    Rb, _tb = align_se2(est[..., :2].reshape(-1, 2), truth[..., :2].reshape(-1, 2))
    np.testing.assert_allclose(Rb, R.T, atol=5e-3)
    # One robot off on its own: team alignment keeps it, per-robot alignment hides it.
    est[:, 2, :2] += np.array([0.5, 0.0])
    err = aligned_errors(truth, est, np.ones((50, 6), bool))
    assert err.team[2] > 0.3 and err.per_robot[2] < 0.02


def test_old_run_directory_gives_tum_and_a_one_line_error_for_the_bag(run_dir, tmp_path):
    old = tmp_path / "old"
    old.mkdir()
    for f in ("scenario.toml", "trajectories.csv", "summary.json"):
        (old / f).write_bytes((run_dir / f).read_bytes())
    res = runner.invoke(app, ["export", str(old), "--format", "tum"])
    assert res.exit_code == 0, res.output
    _stamps, poses = read_tum(old / "export" / "tum" / "robot5.ckf.txt")
    rec = Recording.load(run_dir / "recording.npz")
    np.testing.assert_allclose(poses[:, :2], rec.estimates["ckf"][:, 4, :2], atol=2e-5)
    for fmt in ("rosbag", "foxglove", "html"):
        res = runner.invoke(app, ["export", str(old), "--format", fmt, "-o", str(tmp_path / fmt)])
        assert res.exit_code == 2
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and "re-run" in lines[0] and f"--format {fmt}" in lines[0]
        assert not (tmp_path / fmt).exists() or not any((tmp_path / fmt).iterdir())


def test_export_command_validates_and_refuses_to_overwrite(run_dir, tmp_path):
    res = runner.invoke(app, ["export", str(run_dir), "--format", "tum,png"])
    assert res.exit_code == 2 and "unknown format 'png'" in res.stderr
    res = runner.invoke(app, ["export", str(tmp_path / "nope"), "--format", "tum"])
    assert res.exit_code == 2 and "not a directory" in res.stderr
    res = runner.invoke(app, ["export", str(run_dir), "-F", "html", "--estimator", "ukf"])
    assert res.exit_code == 2 and "--estimator 'ukf'" in res.stderr and "ckf, ekf, dr" in res.stderr
    res = runner.invoke(app, ["export", str(run_dir), "-F", "html", "--rate", "0"])
    assert res.exit_code == 2 and "--rate" in res.stderr
    res = runner.invoke(app, ["export", str(run_dir)])
    assert res.exit_code == 2 and "--format" in res.stderr
    assert not (run_dir / "export").exists()
    res = runner.invoke(app, ["export", str(run_dir), "-F", "tum", "-o", str(tmp_path / "e")])
    assert res.exit_code == 0 and "team-aligned" in res.output
    res = runner.invoke(app, ["export", str(run_dir), "-F", "tum", "-o", str(tmp_path / "e")])
    assert res.exit_code == 2 and "--overwrite" in res.stderr
    res = runner.invoke(
        app, ["export", str(run_dir), "-F", "tum", "-o", str(tmp_path / "e"), "--overwrite"]
    )
    assert res.exit_code == 0
    assert not [p for p in (tmp_path / "e").iterdir() if p.name.startswith(".")]


def test_run_writes_exports_directly_and_checks_the_flag_first(tmp_path):
    sc = tmp_path / "s.toml"
    sc.write_text(dump_scenario(default_scenario().replace(**{"run.steps": 20})))
    bad = runner.invoke(app, ["run", str(sc), "-o", str(tmp_path / "bad"), "--export", "tun"])
    assert bad.exit_code == 2 and "--export" in bad.stderr and not (tmp_path / "bad").exists()
    out = tmp_path / "run"
    res = runner.invoke(
        app, ["run", str(sc), "-o", str(out), "--no-plots", "--no-progress", "--export", "tum"]
    )
    assert res.exit_code == 0, res.output
    assert (out / "export" / "tum" / "robot17.groundtruth.txt").is_file()
    assert "export tum: export/tum" in res.output


def test_help_and_a_run_without_exports_import_no_export_dependency(tmp_path):
    sc = tmp_path / "s.toml"
    sc.write_text(dump_scenario(default_scenario().replace(**{"run.steps": 5})))
    code = f"""
import sys
from typer.testing import CliRunner
from resloc.cli.app import app
r = CliRunner()
assert r.invoke(app, ["--help"]).exit_code == 0
res = r.invoke(app, ["run", {str(sc)!r}, "-o", {str(tmp_path / "o")!r}, "--no-plots"])
assert res.exit_code == 0, res.output
heavy = ("rosbags", "mcap", "evo", "matplotlib")
print(sorted(m for m in sys.modules if m.split(".")[0] in heavy))
"""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert out.stdout.strip() == "[]"
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["steps"] == 5


def test_mrclam_writes_exports_directly(tmp_path):
    from export_helpers import MRCLAM_FIXTURE

    out = tmp_path / "m"
    args = ["mrclam", str(MRCLAM_FIXTURE), "-f", "ckf", "--duration", "20", "--no-plots"]
    res = runner.invoke(app, [*args, "--no-progress", "-o", str(out), "--export", "tum"])
    assert res.exit_code == 0, res.output
    stamps, poses = read_tum(out / "export" / "tum" / "robot3.ckf.txt")
    rec = Recording.load(out / "recording.npz")
    np.testing.assert_allclose(stamps, rec.t0 + rec.time, atol=2e-6)
    np.testing.assert_allclose(poses[:, :2], rec.estimates["ckf"][:, 2, :2], atol=2e-6)
    assert "team-aligned" in res.output
