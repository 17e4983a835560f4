"""Recovery after rejection runs: a robot whose estimate drifted while it saw nothing is
re-admitted within a bounded number of measurements, and the recovery's bound holds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from resloc.cl.detection import DETECTOR_STAGES, active_stages
from resloc.cl.detection_recovery import recovery_inflation, update_rejection_runs
from resloc.cl.detector import InnovationNorm
from resloc.cl.memory import LinkMemory, LinkStatistic
from resloc.cl.params import CLParams
from resloc.cl.step import LinkBatch, correct, predict
from resloc.filters.base import make_filter
from resloc.models.measurement import range_bearing

ANCHORS = np.array([[2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [-2.0, -1.0, 0.0]])


def _params(**kw) -> CLParams:
    base = dict(
        range_std=0.02,
        bearing_std=0.02,
        odometry_std=(0.01, 0.01),
        detector=True,
        detector_norm=InnovationNorm.NIS,
        rho=math.sqrt(13.8155),
        trigger=False,
    )
    base.update(kw)
    return CLParams(**base)


def _blackout_run(params: CLParams, gap: int, after: int, seed: int = 0) -> np.ndarray:
    """One robot driving a circle, anchors in view except from step 20 to ``gap``, during
    which its odometry is biased beyond its noise model; returns the position error per step
    from the end of the gap."""
    rng = np.random.default_rng(seed)
    filt = make_filter("ekf")
    dt = 0.1
    truth = np.zeros((1, 3))
    x = truth.copy()
    P = np.diag([1e-4, 1e-4, 1e-4])[None]
    memory = LinkMemory(1 + len(ANCHORS))
    u_true = np.array([[0.3, 0.15]])
    errors = []
    for k in range(gap + after):
        truth = truth + dt * np.array(
            [[u_true[0, 0] * np.cos(truth[0, 2]), u_true[0, 0] * np.sin(truth[0, 2]), u_true[0, 1]]]
        )
        # Wheels slip while the robot is unobserved: drift far beyond its odometry model.
        u_meas = u_true + (np.array([[0.03, -0.02]]) if 20 <= k < gap else 0.0)
        x, P = predict(filt, x, P, u_meas, dt, params)
        sighting = k < 20 or k >= gap
        if sighting:
            z = range_bearing(np.repeat(truth, 3, axis=0), ANCHORS)
            z = z + rng.normal(0.0, [params.range_std, params.bearing_std], size=z.shape)
            links = LinkBatch(
                i=np.zeros(3, dtype=np.int64),
                j=np.arange(1, 4),
                z=z,
                x_nb=ANCHORS.copy(),
                P_nb=np.broadcast_to(np.eye(3) * 1e-8, (3, 3, 3)).copy(),
                channel_ok=np.ones(3, bool),
                risk_s=np.zeros(1),
                risk_c=np.zeros(1),
                lambda2=np.ones(1),
            )
            x, P, _ = correct(filt, x, P, links, params, memory)
        if k >= gap:
            errors.append(float(np.hypot(*(x[0, :2] - truth[0, :2]))))
    return np.array(errors)


def test_recovery_stage_registered_last_and_declared_once():
    names = [s.name for s in DETECTOR_STAGES]
    assert names[-1] == "recovery" and "robot_cusum" in names
    assert [s.name for s in active_stages(_params(recovery=True))] == ["gate", "recovery"]
    assert next(s for s in DETECTOR_STAGES if s.name == "recovery").compiled


def test_inflation_doubles_every_R_rejections_and_is_capped():
    f = recovery_inflation(np.array([5.0, 10.0, 20.0, 30.0, 1000.0]), 10.0, 100.0)
    assert np.isnan(f[0])
    np.testing.assert_allclose(f[1:], [1.0, 2.0, 4.0, 100.0])


def test_rejection_runs_count_consecutive_and_reset_on_acceptance():
    runs = LinkStatistic(4)
    update_rejection_runs(runs, np.array([0, 0, 1]), np.array([True, True, True]))
    update_rejection_runs(runs, np.array([0, 1, 1]), np.array([True, False, True]))
    np.testing.assert_array_equal(runs.get(np.arange(2), np.arange(2)), [3.0, 0.0])


def test_nis_gate_alone_locks_the_robot_out_after_a_blackout():
    """The test has power: without recovery the drifted robot never comes back."""
    err = _blackout_run(_params(), gap=150, after=150)
    assert err[0] > 0.5
    assert err[-1] > 0.5  # still lost 150 steps (15 s) after sightings resumed


@pytest.mark.parametrize("gap", [150, 400])
def test_recovery_brings_the_robot_back_within_a_bounded_time(gap):
    R, cap = 5, 100.0
    params = _params(recovery=True, recovery_after=R, recovery_inflation_cap=cap)
    err = _blackout_run(params, gap=gap, after=150)
    assert err[0] > 0.5  # the blackout did displace it
    # Bound: the inflation reaches its cap after R (1 + log2 cap) rejected measurements
    # (3 per step); two more steps to converge.
    bound = math.ceil(R * (1 + math.log2(cap)) / 3) + 2
    back = int(np.argmax(err < 0.1))
    assert err[back] < 0.1 and back <= bound, (back, bound, err[:30])
    assert np.all(err[back:] < 0.1)


def test_recovery_cap_bounds_what_an_attacker_gets_accepted():
    """A lie beyond sqrt(f_max g) innovation sigmas is never re-admitted."""
    params = _params(recovery=True, recovery_after=2, recovery_inflation_cap=4.0)
    filt = make_filter("ekf")
    x = np.zeros((1, 3))
    P = np.diag([1e-4, 1e-4, 1e-4])[None]
    memory = LinkMemory(4)
    for _ in range(200):
        z = range_bearing(np.repeat(x, 3, axis=0), ANCHORS)
        z[:, 0] += 1.0  # 1 m lie on every link: ~50 sigma, far beyond sqrt(4 * 13.8)
        links = LinkBatch(
            np.zeros(3, dtype=np.int64),
            np.arange(1, 4),
            z,
            ANCHORS.copy(),
            np.broadcast_to(np.eye(3) * 1e-8, (3, 3, 3)).copy(),
            np.ones(3, bool),
            np.zeros(1),
            np.zeros(1),
            np.ones(1),
        )
        x_new, P_new, out = correct(filt, x, P, links, params, memory)
        assert out.detected.all()
        x, P = x_new, P_new
    np.testing.assert_allclose(x, 0.0)
