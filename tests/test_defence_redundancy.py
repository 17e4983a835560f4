"""Redundancy (cl/detection_redundancy.py): the position fixes, the leave-one-out test, the
cap on claimed covariances, the scenario keys, robot nodes equal to the batched engine, and
the attackers' oracle, which must use the stage's whole acceptance region."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import resloc
from resloc.cl import kernels
from resloc.cl.cusum import chi2_gate
from resloc.cl.detection import DETECTOR_STAGES, Evidence, detect
from resloc.cl.detection_redundancy import fix_evidence
from resloc.cl.detection_redundancy_exclusion import (
    exclude_inconsistent,
    leave_one_out,
    redundancy_statistic,
)
from resloc.cl.detection_redundancy_fixes import (
    _group_median,
    position_fix,
    weight_capped_covariance,
)
from resloc.cl.links import LinkBatch
from resloc.cl.params import CLParams
from resloc.errors import ConfigError
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters.base import make_filter
from resloc.models.measurement import range_bearing
from resloc.world.attackers import AttackStep, accepted, make_attacker
from resloc.world.attackers.oracle import fix_context
from test_node import assert_same, hot_scenario, run_batched, run_nodes, simulate

R = np.diag([0.005**2, 0.05**2])
GATE = chi2_gate(1e-3)

#: Robot 0 at the centre, robots 1-5 around it (a victim with five neighbours).
POSE = np.array(
    [
        [0.0, 0.0, 0.4],
        [0.8, 0.1, 0.0],
        [-0.2, 0.7, 1.0],
        [-0.6, -0.4, -2.0],
        [0.3, -0.8, 2.5],
        [0.6, 0.6, -1.0],
    ]
)


def _victim(P_nb=None, shift=None):
    """Robot 0's five links with exact readings; neighbour 1's broadcast moved by ``shift``."""
    i = np.zeros(5, int)
    j = np.arange(1, 6)
    z = range_bearing(POSE[i], POSE[j])
    x_nb = POSE[j].copy()
    if shift is not None:
        x_nb[0, :2] += shift
    P_obs = np.tile(np.diag([1e-4, 1e-4, 1e-4]), (5, 1, 1))
    P_nb = np.tile(np.diag([1e-4, 1e-4, 1e-4]), (5, 1, 1)) if P_nb is None else P_nb
    return z, POSE[i], P_obs, x_nb, P_nb, i


def test_group_median_matches_numpy_per_group():
    rng = np.random.default_rng(0)
    values = rng.normal(size=40)
    group = rng.integers(0, 7, 40)
    got = _group_median(values, group)
    for g in np.unique(group):
        np.testing.assert_allclose(got[group == g], np.median(values[group == g]))


def test_position_fix_is_unbiased_and_its_covariance_is_first_order():
    z, x_obs, P_obs, x_nb, P_nb, _ = _victim()
    fix, C = position_fix(z, x_obs, P_obs, x_nb, P_nb[:, :2, :2], R)
    # A noise-free reading lands beyond the truth by the mean shortening a noisy direction
    # has, exp(s2 / 2) - 1 of the range (s2: bearing noise + heading variance).
    grow = np.exp(0.5 * (R[1, 1] + P_obs[:, 2, 2])) - 1.0
    np.testing.assert_allclose(
        np.hypot(*fix.T), grow * np.hypot(*(x_nb - x_obs)[:, :2].T), rtol=1e-9
    )
    # Over the sensor noise the fix is unbiased (the reason for the correction).
    rng = np.random.default_rng(0)
    m = 400_000
    noisy = z[1] + rng.multivariate_normal(np.zeros(2), R, m)
    fixes, _ = position_fix(
        noisy,
        np.repeat(x_obs[1:2], m, 0),
        np.repeat(P_obs[1:2] * 0.0, m, 0),
        np.repeat(x_nb[1:2], m, 0),
        np.repeat(P_nb[1:2, :2, :2], m, 0),
        np.diag([R[0, 0], R[1, 1]]),
    )
    se = fixes.std(axis=0) / np.sqrt(m)
    assert (np.abs(fixes.mean(axis=0)) < 4.0 * se).all()
    # Monte Carlo over the neighbour's position, the observer's heading and the sensor noise.
    rng = np.random.default_rng(1)
    n = 200_000
    row = 2
    dp = rng.multivariate_normal(np.zeros(2), P_nb[row, :2, :2], n)
    dth = rng.normal(0.0, np.sqrt(P_obs[row, 2, 2]), n)
    dz = rng.multivariate_normal(np.zeros(2), R, n)
    a = x_obs[row, 2] + dth + z[row, 1] + dz[:, 1]
    r = z[row, 0] + dz[:, 0]
    sample = x_nb[row, :2] + dp - r[:, None] * np.stack([np.cos(a), np.sin(a)], 1)
    np.testing.assert_allclose(np.cov(sample.T), C[row], rtol=0.03, atol=1e-8)


def test_leave_one_out_reference_excludes_the_row_and_counts_peers():
    fix = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [5.0, 5.0]])
    C = np.tile(np.eye(2), (4, 1, 1))
    i = np.array([0, 0, 0, 1])
    ref, ref_cov, peers = leave_one_out(fix, C, i)
    np.testing.assert_array_equal(peers, [2, 2, 2, 0])
    np.testing.assert_allclose(ref[0], [0.5, 1.0])
    np.testing.assert_allclose(ref[2], [0.5, 0.0])
    np.testing.assert_allclose(ref_cov[1], 0.5 * np.eye(2))
    assert ref_cov[3, 0, 0] > 1e9  # no peer: never judged


PARAMS = CLParams(detector_norm="nis", rho=1e6, redundancy=True)


def test_leave_one_out_alone_would_flag_everyone_exclusion_finds_the_liar():
    z, x_obs, P_obs, x_nb, P_nb, i = _victim(shift=[0.2, 0.0])
    fix, C = position_fix(z, x_obs, P_obs, x_nb, P_nb[:, :2, :2], R)
    ref, ref_cov, _ = leave_one_out(fix, C, i)
    # one pass: the liar's share of the honest rows' references makes them fail with it
    assert (redundancy_statistic(fix, C, ref, ref_cov)[1:] > GATE).any()
    ev = fix_evidence(z, x_obs, P_obs, x_nb, P_nb, i, PARAMS)
    np.testing.assert_array_equal(ev["fix_excluded"], [True, False, False, False, False])
    assert ev["fix_statistic"][0] > GATE and (ev["fix_statistic"][1:] < GATE).all()
    honest = fix_evidence(*_victim(), PARAMS)
    assert not honest["fix_excluded"].any()


def test_exclusion_keeps_min_peers_and_removes_two_liars():
    fix = np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.01], [0.5, 0.0], [0.0, -0.6], [9.0, 9.0]])
    C = np.tile(1e-4 * np.eye(2), (6, 1, 1))
    i = np.array([0, 0, 0, 0, 0, 1])
    excluded, stat = exclude_inconsistent(fix, C, i, GATE, 2.0)
    np.testing.assert_array_equal(excluded, [False, False, False, True, True, False])
    assert np.isnan(stat[5])  # alone: not judged
    # three fixes, min_peers 2: one can go; two disagreeing fixes with one peer: none
    excluded, _ = exclude_inconsistent(fix[[0, 1, 3]], C[:3], i[:3], GATE, 2.0)
    np.testing.assert_array_equal(excluded, [False, False, True])
    excluded, _ = exclude_inconsistent(fix[[0, 3]], C[:2], i[:2], GATE, 2.0)
    assert not excluded.any()


def test_a_tiny_claimed_covariance_buys_no_weight():
    """Two liars agreeing with each other and claiming x0.01 of their covariance would
    outweigh three honest neighbours (the honest ones would be excluded); the cap keeps each
    liar's weight at a typical neighbour's, and the liars are excluded."""
    P_nb = np.tile(np.diag([4e-2, 4e-2, 1e-4]), (5, 1, 1))
    P_nb[:2] *= 0.01
    capped = weight_capped_covariance(P_nb, np.zeros(5, int))
    np.testing.assert_allclose(capped, P_nb[:, :2, :2] * np.r_[100.0, 100, 1, 1, 1][:, None, None])
    z, x_obs, P_obs, x_nb, _, i = _victim()
    x_nb[:2, 0] += 1.5
    ev = fix_evidence(z, x_obs, P_obs, x_nb, P_nb, i, PARAMS)
    np.testing.assert_array_equal(ev["fix_excluded"], [True, True, False, False, False])
    fix, C = position_fix(z, x_obs, P_obs, x_nb, P_nb[:, :2, :2], R)
    excluded, _ = exclude_inconsistent(fix, C, i, GATE, 2.0)
    np.testing.assert_array_equal(excluded, [False, False, True, True, True])


def test_the_stage_reads_the_exclusion_and_needs_its_fields():
    z, x_obs, P_obs, x_nb, P_nb, i = _victim(shift=[0.5, 0.0])
    ev = Evidence(
        np.zeros((5, 2)),
        np.tile(np.eye(2), (5, 1, 1)),
        np.zeros(5),
        i,
        np.arange(1, 6),
        np.zeros(5, bool),
        **fix_evidence(z, x_obs, P_obs, x_nb, P_nb, i, PARAMS),
    )
    np.testing.assert_array_equal(detect(ev, PARAMS, None), [True, False, False, False, False])
    # a row zone trust substituted is fused as the partner's fix: not judged by its reading
    ev.zone_substituted = np.array([True, False, False, False, False])
    assert not DETECTOR_STAGES[2].discard(ev, PARAMS, None).any()
    bare = Evidence(
        np.zeros((1, 2)), np.eye(2)[None], np.zeros(1), i[:1], i[:1] + 1, np.zeros(1, bool)
    )
    with pytest.raises(ValueError, match=r"redundancy.*position fixes"):
        detect(bare, PARAMS, None)
    names = [s.name for s in DETECTOR_STAGES]
    assert names.index("redundancy") == names.index("gate") + 1
    assert DETECTOR_STAGES[names.index("redundancy")].compiled  # kernels_redundancy


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("detector.redundancy", "yes", "expected true or false"),
        ("detector.redundancy_false_alarm", 0.0, "must be greater than 0"),
        ("detector.redundancy_min_peers", 0, "below the minimum 1"),
    ],
)
def test_redundancy_keys_fail_with_one_line(key, value, message):
    with pytest.raises(ConfigError, match=message) as err:
        default_scenario().replace(**{key: value})
    assert "\n" not in str(err.value) and key in str(err.value)


def test_the_defences_switch_it_on():
    base = default_scenario()
    for name in ("full+redundancy", "zone+full+redundancy"):
        params = base.replace(**DEFENCES[name]).cl_params()
        assert params.redundancy and params.recovery and params.robot_cusum
        assert params.redundancy_gate == pytest.approx(13.8155, rel=1e-4)
        assert params.redundancy_min_peers == 2.0
    assert base.replace(**DEFENCES["zone+full+redundancy"]).cl_params().zone_trust


@pytest.mark.parametrize("mode", ["sequential", "summed"])
def test_robot_nodes_reproduce_the_batched_engine_with_redundancy(mode):
    scenario = hot_scenario(15)
    params = replace(
        scenario.replace(**DEFENCES["full+redundancy"]).cl_params(),
        update_mode=mode,
        redundancy_gate=2.0,  # strict: the stage discards in the honest run too
    )
    world, x0, P0, ws_list = simulate(scenario, trials=1, seed=4)
    filt = make_filter("ekf")
    with kernels.use_backend("auto"):
        batched = run_batched(filt, params, world, x0, P0, ws_list)
        by_robot = run_nodes(filt, params, world, x0, P0, ws_list)
        loose = run_batched(filt, replace(params, redundancy=False), world, x0, P0, ws_list)
    # The kernel implements the stage (kernels_redundancy) and both update modes
    # (kernels_summed).
    assert assert_same(batched, by_robot, ws_list, compiled=kernels.backend() == "numba") > 0
    # and the stage acted: the estimates differ from the same run without it
    assert max(np.abs(b[0] - w[0]).max() for b, w in zip(batched, loose, strict=True)) > 1e-6


def _compromised_scene(params):
    """Robot 0 with five neighbours; robot 1 is compromised (the suite's first target is
    robot 5 of a team: ``robots`` = 6 makes robot 5 the liar)."""
    i = np.zeros(5, int)
    j = np.arange(1, 6)
    rng = np.random.default_rng(2)
    z = range_bearing(POSE[i], POSE[j]) + rng.normal(0, [0.005, 0.05], (5, 2)) * 0.3
    x = POSE.copy()
    P = np.tile(np.diag([1e-4, 1e-4, 1e-4]), (6, 1, 1))
    links = LinkBatch.from_predicted(
        i, j, z, x, P, np.ones(5, bool), np.zeros(6), np.zeros(6), np.ones(6)
    )
    step = AttackStep(1, 0.033, POSE, i, j, z, np.zeros(5, bool), 6)
    filt = make_filter("ekf")
    from resloc.cl.fusion_methods import fusion_strategy

    m = fusion_strategy(params.fusion).moments(filt, None, x[i], P[i], x[j], P[j], i, j, params.R)
    return links, step, m.z_hat, m.S


@pytest.mark.parametrize("claimed_cov", [1.0, 0.01])
def test_the_compromised_robots_lie_sits_on_the_redundancy_gate(claimed_cov):
    """A loose NIS gate (so the redundancy test binds): the compromised robot's broadcast is
    moved by the largest shift the victim's redundancy test accepts, not by nothing."""
    params = CLParams(detector_norm="nis", rho=float(np.sqrt(chi2_gate(1e-9))), redundancy=True)
    links, step, z_hat, S = _compromised_scene(params)
    adv = make_attacker("compromised", robots=1, claimed_cov=claimed_cov)
    tampered = adv.attack(links, step, params, None)
    sent = tampered.tamper(np.arange(5), z_hat, S)
    liar = 4  # j = 5
    assert not np.allclose(sent[liar], links.z[liar])
    np.testing.assert_array_equal(sent[:liar], links.z[:liar])
    ev = fix_evidence(
        sent,
        POSE[links.i],
        tampered.neighbours.P[links.i],
        links.x_nb,
        tampered.P_nb,
        links.i,
        params,
    )
    stat = ev["fix_statistic"]
    assert not ev["fix_excluded"].any()
    assert stat[liar] == pytest.approx(params.redundancy_gate, rel=0.02)
    # the victim's detector accepts what was sent, and a little more is rejected
    context = fix_context(tampered, np.array([liar]), params)
    ok = accepted(
        sent[[liar]],
        z_hat[[liar]],
        S[[liar]],
        links.i[[liar]],
        links.j[[liar]],
        params,
        None,
        context=context,
    )
    assert ok.all()
    more = sent[[liar]] + 1.05 * (sent[[liar]] - links.z[[liar]])
    assert not accepted(
        more,
        z_hat[[liar]],
        S[[liar]],
        links.i[[liar]],
        links.j[[liar]],
        params,
        None,
        context=context,
    ).any()
    # and the victim's own correction fuses the row (the verdict agrees with the oracle)
    x, P = tampered.neighbours.x, tampered.neighbours.P
    _, _, out = resloc.cl.step.correct(
        make_filter("ekf"), x, P, tampered, replace(params, trigger=False)
    )
    assert not out.detected.any()


def test_the_oracle_refuses_to_guess_without_the_victims_estimates():
    params = CLParams(detector_norm="nis", rho=3.7, redundancy=True)
    links = _compromised_scene(params)[0]
    fixed = replace(links, neighbours=None, x_nb=links.x_nb, P_nb=links.P_nb)
    with pytest.raises(ValueError, match="victims' estimates"):
        fix_context(fixed, np.array([4]), params)
    assert fix_context(links, np.array([4]), CLParams(detector_norm="nis", rho=3.7)) is None
