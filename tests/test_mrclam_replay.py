"""MRCLAM replay building blocks: step discretization, ground-truth interpolation, the
configuration, the noise model and fit, and the assignment of sightings to steps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from resloc.angles import wrap_angle
from resloc.cl.params import CLParams
from resloc.datasets.mrclam import load_mrclam
from resloc.errors import ConfigError
from resloc.experiments.mrclam import (
    MRCLAMConfig,
    estimate_noise,
    ground_truth_at,
    level_groups,
    prepare_replay,
    range_noise_level,
    range_noise_std,
    step_commands,
)

FIXTURE = Path(__file__).parent / "fixtures" / "mrclam" / "MRCLAM_Dataset6_60s"


@pytest.fixture(scope="module")
def data():
    return load_mrclam(FIXTURE)


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


def test_level_groups_keep_row_order_and_memoize_parameters():
    cfg = MRCLAMConfig()
    z = np.array([0.5, 6.0, 0.5, 6.0, 3.0])
    level = range_noise_level(z, cfg)
    cache: dict = {}
    groups = level_groups(level, CLParams(), cache)
    rows = np.concatenate([r for r, _ in groups])
    assert sorted(rows.tolist()) == list(range(5))
    for r, params in groups:
        assert np.all(np.diff(r) > 0)  # each level's rows in their order
        np.testing.assert_allclose(params.range_std, range_noise_std(z[r], cfg), atol=0.0025)
    again = level_groups(level, CLParams(), cache)
    assert all(a[1] is b[1] for a, b in zip(groups, again, strict=True))
