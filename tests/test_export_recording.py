"""``recording.npz``: what a run records for the exports agrees with the run's own counts,
round-trips through the file, and bad files give one clear error."""

from __future__ import annotations

import numpy as np
import pytest

from export_helpers import MRCLAM_FIXTURE
from resloc.errors import DataError
from resloc.experiments.config import default_scenario
from resloc.experiments.mrclam import MRCLAMConfig, run_mrclam
from resloc.experiments.recording import (
    LINK_FLAGS,
    Recording,
    recording_from_mrclam,
    recording_from_run,
)
from resloc.experiments.runner import run_scenario


@pytest.fixture(scope="module")
def run():
    sc = default_scenario().replace(
        **{"run.steps": 240, "run.trials": 2, "run.filters": ["ckf", "ekf"]}
    )
    return run_scenario(sc)


def test_link_log_of_trial_zero_matches_the_run_totals(run):
    for name in ("ckf", "ekf"):
        est = run.estimators[name]
        log, tot = est.links, est.totals
        assert int(log["triggered"].sum()) == tot["triggered"][0]
        assert int(log["detected"].sum()) == tot["detected"][0] > 0
        assert int(log["fused"].sum()) == tot["fused"][0]
        assert int(log["attacked"].sum()) == tot["attacked"][0] > 0
        assert len(log["step"]) == tot["candidates"][0]
        np.testing.assert_array_equal(
            np.bincount(log["step"] - 1, log["triggered"], len(run.time)),
            est.series["triggered"][:, 0],
        )
        assert log["i"].max() < 17 and log["j"].max() < 17  # trial 0 only
    assert run.estimators["ckf"].links["step"] is run.estimators["ekf"].links["step"]
    assert run.estimators["dr"].links is None


def test_covariances_are_recorded_every_step_and_spd(run):
    cov = run.estimators["ckf"].cov
    assert cov.shape == (241, 17, 3, 3)
    assert np.linalg.eigvalsh(cov.astype(float)).min() > 0
    dr = run.estimators["dr"].cov
    assert np.all(np.diff(dr[:, :, 0, 0], axis=0) >= -1e-9)  # dead reckoning only grows


def test_recording_round_trips_through_the_file(run, tmp_path):
    rec = recording_from_run(run)
    back = Recording.load(rec.save(tmp_path / "recording.npz"))
    assert back.robots == rec.robots and back.name == "arc-turn"
    np.testing.assert_allclose(back.truth, rec.truth, atol=1e-6)
    for name in rec.estimates:
        np.testing.assert_allclose(back.estimates[name], rec.estimates[name], atol=1e-6)
        np.testing.assert_allclose(back.covariances[name], rec.covariances[name], rtol=1e-6)
        for key in LINK_FLAGS:
            np.testing.assert_array_equal(back.outcomes[name][key], rec.outcomes[name][key])
    assert [z.kind for z in back.zones] == ["sdz", "cdz"]
    assert not back.outcomes["dr"]["triggered"].any()


def test_mrclam_recording_keeps_every_measurement_and_its_outcome():
    result = run_mrclam(MRCLAM_FIXTURE, MRCLAMConfig(filters=("ckf",), duration=20, zones=True))
    rec = recording_from_mrclam(result)
    over = result.estimators["ckf"].overall
    fused = rec.outcomes["ckf"]["fused"]
    robot = rec.links["j"] < rec.n_robots
    assert int(fused[robot].sum()) == over["robot_fused"]
    assert int(fused[~robot].sum()) == over["landmark_fused"]
    assert int(rec.links["attacked"].sum()) == over["attacked"]
    assert rec.t0 == result.info["t0_unix"] and rec.robots[0] == "robot1"
    assert rec.covariances["dr"].shape == (*rec.truth.shape, 3)


def test_a_damaged_recording_is_one_clear_error(tmp_path):
    bad = tmp_path / "recording.npz"
    bad.write_bytes(b"not a zip file")
    with pytest.raises(DataError, match="not a resloc recording") as exc:
        Recording.load(bad)
    assert "\n" not in str(exc.value)
