"""The MRCLAM replay on the shipped excerpt: the estimators against dead reckoning, the attack
layer on real data, saved outputs, and the full Dataset 6 when present."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from resloc.datasets.mrclam import load_mrclam
from resloc.experiments.mrclam import (
    DEAD_RECKONING,
    MRCLAMConfig,
    default_zones,
    prepare_replay,
    run_mrclam,
    save_mrclam,
)
from resloc.models.motion import unicycle_step

FIXTURE = Path(__file__).parent / "fixtures" / "mrclam" / "MRCLAM_Dataset6_60s"
DATASET6 = Path(__file__).resolve().parents[1].parent / "shared/data/mrclam/MRCLAM_Dataset6"
needs_shared = pytest.mark.skipif(
    not DATASET6.is_dir(), reason="full MRCLAM Dataset 6 not found under ../shared"
)
FILTERS = ("ckf", "ukf", "ekf")


@pytest.fixture(scope="module")
def data():
    return load_mrclam(FIXTURE)


@pytest.fixture(scope="module")
def with_landmarks(data):
    return run_mrclam(data, MRCLAMConfig(filters=FILTERS))


@pytest.fixture(scope="module")
def with_zones(data):
    return run_mrclam(data, MRCLAMConfig(filters=("ckf",), zones=True, seed=3))


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


# ---------------------------------------------------------------------------- full dataset
@needs_shared
@pytest.mark.shared
def test_full_dataset6_first_120s_beats_dead_reckoning():
    res = run_mrclam(DATASET6, MRCLAMConfig(filters=("ckf",), duration=120.0))
    assert res.info["replayed_s"] == pytest.approx(120.0)
    s, dr = res.estimators["ckf"].overall, res.estimators[DEAD_RECKONING].overall
    assert s["position_rmse"] < dr["position_rmse"]
    assert s["heading_rmse"] < dr["heading_rmse"]
