"""MRCLAM replay: step discretization, the estimators against dead reckoning on the shipped
excerpt, the attack layer on real data, saved outputs and the ``resloc mrclam`` command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from resloc.angles import wrap_angle
from resloc.cli.app import app
from resloc.datasets.mrclam import load_mrclam
from resloc.errors import ConfigError
from resloc.experiments.mrclam import (
    DEAD_RECKONING,
    MRCLAMConfig,
    default_zones,
    estimate_noise,
    ground_truth_at,
    prepare_replay,
    range_noise_std,
    run_mrclam,
    save_mrclam,
    step_commands,
)
from resloc.models.motion import unicycle_step

FIXTURE = Path(__file__).parent / "fixtures" / "mrclam" / "MRCLAM_Dataset6_60s"
DATASET6 = Path(__file__).resolve().parents[1].parent / "shared/data/mrclam/MRCLAM_Dataset6"
needs_shared = pytest.mark.skipif(
    not DATASET6.is_dir(), reason="full MRCLAM Dataset 6 not found under ../shared"
)
FILTERS = ("ckf", "ukf", "ekf")
runner = CliRunner()


@pytest.fixture(scope="module")
def data():
    return load_mrclam(FIXTURE)


@pytest.fixture(scope="module")
def with_landmarks(data):
    return run_mrclam(data, MRCLAMConfig(filters=FILTERS))


@pytest.fixture(scope="module")
def with_zones(data):
    return run_mrclam(data, MRCLAMConfig(filters=("ckf",), zones=True, seed=3))


# ---------------------------------------------------------------------------- building blocks
def teststep_commands_integrate_the_zero_order_hold_exactly():
    odo = np.array([[0.05, 1.0, 0.5], [0.13, 2.0, -1.0], [0.30, 0.0, 0.0]])
    times = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    u = step_commands(odo, times)
    # Step 1 (0, 0.1]: 0 until 0.05, then (1, 0.5) -> mean (0.5, 0.25).
    # Step 2 (0.1, 0.2]: (1, .5) until 0.13, then (2, -1) -> mean (1.7, -0.55).
    np.testing.assert_allclose(u, [[0.5, 0.25], [1.7, -0.55], [2.0, -1.0], [0.0, 0.0]])
    np.testing.assert_allclose(step_commands(np.zeros((0, 3)), times), np.zeros((4, 2)))


def test_ground_truth_interpolation_wraps_heading_and_flags_gaps():
    gt = np.array(
        [[0.0, 0.0, 0.0, 3.1], [0.1, 1.0, 0.0, -3.1], [0.2, 2.0, 0.0, -3.0], [2.0, 3.0, 0.0, 0.0]]
    )
    pose, ok = ground_truth_at(gt, np.array([-0.1, 0.05, 0.15, 1.0, 2.5]), max_gap=0.25)
    np.testing.assert_allclose(pose[1, :2], [0.5, 0.0])
    # Halfway between 3.1 and -3.1 across +-pi is pi, not 0.
    assert abs(wrap_angle(pose[1, 2] - np.pi)) < 1e-12
    np.testing.assert_array_equal(ok, [False, True, True, False, False])


def test_config_is_validated():
    with pytest.raises(ConfigError, match=r"dt: 0\.0 is out of range"):
        MRCLAMConfig(dt=0.0)
    with pytest.raises(ConfigError, match="unknown filter 'pf'"):
        MRCLAMConfig(filters=("pf",))
    with pytest.raises(ConfigError, match="also pass --zones"):
        MRCLAMConfig(sdz=(1.0, 1.0, 0.5))
    with pytest.raises(ConfigError, match="radius > 0"):
        MRCLAMConfig(zones=True, sdz=(1.0, 1.0, 0.0))
    # Per-step odometry std = density / sqrt(dt): the same noise per second at any dt.
    a = np.asarray(MRCLAMConfig(dt=0.02).cl_params().odometry_std)
    b = np.asarray(MRCLAMConfig(dt=0.08).cl_params().odometry_std)
    np.testing.assert_allclose(a**2 * 0.02, b**2 * 0.08)


def test_range_noise_grows_with_range():
    cfg = MRCLAMConfig()
    s = range_noise_std(np.array([0.0, 1.0, 5.0]), cfg)
    assert s[0] == pytest.approx(cfg.range_std)
    assert s[2] == pytest.approx(np.hypot(cfg.range_std, 5.0 * cfg.range_std_rel))
    assert np.all(np.diff(s) > 0)


def test_replay_assigns_every_measurement_once_in_order(data):
    cfg = MRCLAMConfig()
    rp = prepare_replay(data, cfg)
    assert rp.steps == int(np.ceil(data.end / cfg.dt - 1e-9))
    assert rp.u.shape == (rp.steps, 5, 2) and rp.truth.shape == (rp.steps + 1, 5, 3)
    assert len(rp.step) == data.counts()["measurements"]
    assert np.all(np.diff(rp.step) >= 0)
    # Each measurement is fused at the end of the step containing its time stamp.
    t = np.concatenate([r.measurements[:, 0] for r in data.robots])
    assert np.all(t > 0.0)
    assert rp.bounds[-1] == len(rp.step)
    for k in np.unique(rp.step)[:50]:
        lo, hi = rp.bounds[k], rp.bounds[k + 1]
        assert np.all(rp.step[lo:hi] == k)
        # Landmark rows first, then robot rows, each sorted by observer.
        robot = rp.is_robot[lo:hi]
        assert np.all(np.diff(robot.astype(int)) >= 0)
        for part in (~robot, robot):
            assert np.all(np.diff(rp.obs[lo:hi][part]) >= 0)
    # Initial poses are the first ground-truth sample.
    np.testing.assert_allclose(rp.x0, rp.truth[0])
    assert not rp.attacked.any() and rp.channel_ok.all()
    no_lm = prepare_replay(data, MRCLAMConfig(landmarks=False))
    assert no_lm.is_robot.all() and len(no_lm.step) == rp.is_robot.sum()


def test_noise_estimates_are_plausible(data):
    noise = estimate_noise(data)
    for kind in ("robot", "landmark"):
        assert noise[kind]["n"] > 100
        assert 0.02 < noise[kind]["range_std_robust"] < 0.3
        assert 0.001 < noise[kind]["bearing_std_robust"] < 0.03
    assert 0.0 < noise["odometry"]["v_density"] < 0.05
    assert 0.0 < noise["odometry"]["omega_density"] < 0.2


# ---------------------------------------------------------------------------- the replay
def test_dead_reckoning_is_the_odometry_integral(data, with_landmarks):
    rp = prepare_replay(data, with_landmarks.config)
    x = rp.x0.copy()
    for k in range(rp.steps):
        x = unicycle_step(x, rp.u[k], with_landmarks.config.dt)
    dr = with_landmarks.estimators[DEAD_RECKONING]
    np.testing.assert_allclose(dr.track[-1], x, atol=1e-9)
    assert dr.overall["comm_rate"] == 0.0 and dr.overall["robot_fused"] == 0
    assert np.isnan(dr.overall["detector_precision"])


def test_every_filter_beats_dead_reckoning_with_landmarks(with_landmarks):
    res = with_landmarks
    dr = res.estimators[DEAD_RECKONING].overall
    for name in FILTERS:
        s = res.estimators[name].overall
        assert s["position_rmse"] < dr["position_rmse"], name
        assert s["heading_rmse"] < dr["heading_rmse"], name
        assert s["msle_mean"] < dr["msle_mean"], name
        assert s["landmark_fused"] > 0.9 * s["landmark_measurements"]
        assert 0.0 < s["comm_rate"] <= 1.0
        assert np.isfinite(s["nees_mean"]) and s["nees_mean"] > 0
    # The CKF and the UKF (alpha = 1, beta = 2, kappa = 0) are near-identical here.
    ckf, ukf = res.estimators["ckf"].overall, res.estimators["ukf"].overall
    assert ckf["position_rmse"] == pytest.approx(ukf["position_rmse"], rel=0.02)


def test_result_arrays_and_per_robot_stats(with_landmarks):
    res = with_landmarks
    K1 = len(res.time)
    assert res.truth.shape == (K1, 5, 3) and res.valid.shape == (K1, 5)
    for est in res.estimators.values():
        assert est.track.shape == (K1, 5, 3)
        assert est.pos_err.shape == (K1, 5) and est.nees.shape == (K1, 5)
        assert est.msle.shape == (K1,)
        np.testing.assert_allclose(est.track[0], res.truth[0])
        for key, v in est.per_robot.items():
            assert v.shape == (5,), key
        rmse = np.sqrt(np.nanmean(est.pos_err**2))
        assert est.overall["position_rmse"] == pytest.approx(rmse)
    # Robot 2 never observes another robot in the first 60 s: no candidate links.
    ckf = res.estimators["ckf"].per_robot
    assert ckf["robot_measurements"][1] == 0 and np.isnan(ckf["comm_rate"][1])


def test_robot_links_alone_beat_dead_reckoning(data):
    res = run_mrclam(data, MRCLAMConfig(filters=("ckf",), landmarks=False))
    s, dr = res.estimators["ckf"].overall, res.estimators[DEAD_RECKONING].overall
    assert s["landmark_measurements"] == 0 and s["robot_fused"] > 100
    assert s["position_rmse"] < dr["position_rmse"]
    assert s["msle_mean"] < dr["msle_mean"]


def test_attack_layer_on_real_data(data, with_zones):
    res = with_zones
    rp = prepare_replay(data, res.config)
    sdz, cdz = res.zones["sdz"][0], res.zones["cdz"][0]
    auto_s, auto_c = default_zones(rp.truth, rp.valid)
    assert (sdz, cdz) == (auto_s, auto_c)
    assert rp.attacked.sum() > 10
    assert not rp.attacked[~rp.is_robot].any(), "landmark sightings are never falsified"
    assert rp.channel_ok[~rp.is_robot].all()
    assert (~rp.channel_ok).sum() > 0
    changed = np.any(rp.z != rp.z_clean, axis=1)
    np.testing.assert_array_equal(changed, rp.attacked)
    ckf = res.estimators["ckf"]
    delivered = ckf.links["delivered"]
    assert not (delivered & ~rp.channel_ok).any(), "a jammed transmission is never delivered"
    s = ckf.overall
    assert s["attacked"] == rp.attacked.sum()
    assert s["detector_tp"] + s["detector_fn"] == s["attacked"]
    # Same seed, same draws; another seed, other draws.
    again = prepare_replay(data, res.config)
    np.testing.assert_array_equal(again.z, rp.z)
    np.testing.assert_array_equal(again.channel_ok, rp.channel_ok)
    other = prepare_replay(data, MRCLAMConfig(zones=True, seed=4))
    assert not np.array_equal(other.attacked, rp.attacked)


def test_explicit_zones_and_a_strict_nis_detector(data):
    cfg = MRCLAMConfig(
        filters=("ckf",),
        zones=True,
        sdz=(2.3, -1.5, 1.5),
        cdz=(9.0, 9.0, 0.5),
        attack_bias=(1.0, 1.0),
        detector_norm="nis",
        rho=4.0,
    )
    res = run_mrclam(data, cfg)
    assert res.zones["sdz"][0].center == (2.3, -1.5)
    assert res.info["jammed"] == 0  # the CDZ is outside the arena
    s = res.estimators["ckf"].overall
    assert s["attacked"] > 10
    assert s["detector_recall"] > 0.5 and s["detector_precision"] > 0.5


def test_save_writes_summary_csv_and_plots(with_landmarks, tmp_path: Path):
    files = save_mrclam(with_landmarks, tmp_path, plots=True)
    names = {p.name for p in files}
    assert names == {
        "summary.json",
        "per_robot.csv",
        "timeseries.csv",
        "trajectories.png",
        "errors.png",
        "recording.npz",
    }
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert set(summary["overall"]) == {DEAD_RECKONING, *FILTERS}
    assert summary["config"]["dt"] == 0.02
    assert summary["info"]["dataset"] == "MRCLAM_Dataset6_60s"
    assert summary["per_robot"]["robots"] == [1, 2, 3, 4, 5]
    rows = (tmp_path / "per_robot.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 4 * 6
    ts = (tmp_path / "timeseries.csv").read_text().strip().splitlines()
    assert ts[0].startswith("time_s,robot,valid,x_true")
    assert len(ts) > 1000
    for png in ("trajectories.png", "errors.png"):
        assert (tmp_path / png).read_bytes()[:4] == b"\x89PNG"


# ---------------------------------------------------------------------------- the command
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


# ---------------------------------------------------------------------------- full dataset
@needs_shared
@pytest.mark.shared
def test_full_dataset6_first_120s_beats_dead_reckoning():
    res = run_mrclam(DATASET6, MRCLAMConfig(filters=("ckf",), duration=120.0))
    assert res.info["replayed_s"] == pytest.approx(120.0)
    s, dr = res.estimators["ckf"].overall, res.estimators[DEAD_RECKONING].overall
    assert s["position_rmse"] < dr["position_rmse"]
    assert s["heading_rmse"] < dr["heading_rmse"]
