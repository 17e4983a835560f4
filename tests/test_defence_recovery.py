"""Recovery after rejection runs: a robot whose estimate drifted while it saw nothing is
re-admitted within a bounded number of measurements, and the recovery's bound holds."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from resloc.cl.detection import DETECTOR_STAGES, Evidence, active_stages
from resloc.cl.detection_recovery import (
    recovery_inflation,
    remaining_inflation,
    update_rejection_runs,
)
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


def test_total_inflation_between_acceptances_is_capped_at_f_max_squared():
    f = np.array([50.0, 50.0, 50.0, np.nan])
    applied = np.array([0.0, 100.0, 1e4, 0.0])
    np.testing.assert_allclose(remaining_inflation(f, applied, 100.0)[:3], [50.0, 50.0, 1.0])
    assert np.isnan(remaining_inflation(f, applied, 100.0)[3])


def test_readmissions_record_the_applied_inflation_and_an_acceptance_resets_it():
    """A robot kept in recovery by lies on every link: each re-admission multiplies ``A_i``
    by what it applied, never past ``f_max^2``; an ordinary acceptance resets it."""
    params = _params(recovery=True, recovery_after=1, recovery_inflation_cap=4.0)
    stage = next(s for s in DETECTOR_STAGES if s.name == "recovery")
    memory = LinkMemory(2)
    applied = memory.stage_statistic("recovery_applied")
    i = np.array([0])
    P = np.eye(3)[None] * 1e-4
    history = []
    for k in range(30):
        # The covariance the stage sees grows as inflated posteriors would make it.
        P_obs = P * 4.0**k
        S = np.eye(2)[None] * 1e-4 * 4.0**k
        nu = np.array([[0.05, 0.0]]) * 2.0**k  # NIS 25: rejected, re-admitted at f >= 2
        rejected = np.ones(1, bool)
        ev = Evidence(nu, S, np.full(1, 5.0), i, np.ones(1, int), rejected, rejected, P_obs=P_obs)
        stage.discard(ev, params, memory)
        history.append(float(applied.get(i, i)[0]))
    assert max(history) <= 16.0 + 1e-9 and history[-1] == pytest.approx(16.0)
    passed = np.zeros(1, bool)
    ev = Evidence(nu, S, np.zeros(1), i, np.ones(1, int), passed, passed, P_obs=P_obs)
    stage.discard(ev, params, memory)
    assert applied.get(i, i)[0] == 0.0


def test_full_defence_stays_bounded_under_a_persistent_range_bias():
    """Issue 13's divergence: with the recovery, ``full`` blew up under the suite's range
    bias (early-SDZ scenario, one trial: MSLE 3.1 after 150 steps, 1e15 after 300, against
    0.22 for the same stages without the recovery). It must stay with that defence."""
    import resloc
    from resloc.experiments.config_parse import load_scenario
    from resloc.experiments.defences import DEFENCES
    from resloc.world.attackers import make_attacker

    toml = Path(__file__).resolve().parents[1] / "examples" / "attack" / "early_sdz.toml"
    base = load_scenario(toml).replace(
        **{"run.steps": 150, "run.filters": ["ckf"], "run.dead_reckoning": False, "run.trials": 1}
    )
    adv = make_attacker("range_bias", size=2.0)
    msle = {}
    for name in ("full", "nis_link_robot_cusums"):
        scenario = base.replace(**DEFENCES[name]).replace(**adv.overrides)
        msle[name] = resloc.run_scenario(scenario, adversary=adv).summary()["ckf"]["msle_mean"]
    assert np.isfinite(msle["full"])
    assert msle["full"] <= 3.0 * msle["nis_link_robot_cusums"], msle


def test_inflation_of_a_very_long_run_is_the_cap_without_a_warning():
    # 2**n overflows for a run of ~1e4 R; the cap applies and nothing is printed
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f = recovery_inflation(np.array([1e5, 1e7]), 10.0, 1e3)
    np.testing.assert_array_equal(f, [1e3, 1e3])
