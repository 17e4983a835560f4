"""The sequence test on the redundancy residuals (cl/detection_sequence.py): it catches a
slow lie every per-step gate passes, never locks an honest neighbour out, runs the same in
one robot's process, and the attackers' oracle spends exactly its acceptance region."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from resloc.cl import kernels
from resloc.cl.cusum import chi2_gate
from resloc.cl.detection import DETECTOR_STAGES, Evidence, detect
from resloc.cl.detection_redundancy import fix_evidence
from resloc.cl.detection_sequence import WIDTH, RedundancySequence, held_out, sequence_step
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.errors import ConfigError
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters.base import make_filter
from resloc.models.measurement import range_bearing
from resloc.world.attackers import make_attacker
from test_defence_redundancy import POSE, _compromised_scene
from test_node import assert_same, hot_scenario, run_batched, run_nodes, simulate

NAME = RedundancySequence.name
PARAMS = CLParams(
    detector=False,  # the gate off: only the redundancy stages judge
    redundancy=True,
    redundancy_gate=chi2_gate(1e-3),
    redundancy_sequence=True,
    redundancy_sequence_gate=chi2_gate(1e-6),
    redundancy_sequence_hold=50.0,
)
J = np.arange(1, 6)
P_TINY = np.tile(np.diag([1e-6, 1e-6, 1e-6]), (5, 1, 1))


def _step(rng, memory, params, lead=0.0):
    """One step of robot 0's five links with sensor noise; neighbour 1's broadcast leads
    by ``lead`` m along x. Returns the discards and the evidence."""
    i = np.zeros(5, int)
    z = range_bearing(POSE[i], POSE[J]) + rng.normal(0.0, [0.005, 0.05], (5, 2))
    x_nb = POSE[J].copy()
    x_nb[0, 0] += lead
    fields = fix_evidence(z, POSE[i], P_TINY, x_nb, P_TINY, i, params, J, memory)
    ev = Evidence(
        np.zeros((5, 2)),
        np.tile(np.eye(2), (5, 1, 1)),
        np.zeros(5),
        i,
        J,
        np.zeros(5, bool),
        **fields,
    )
    return detect(ev, params, memory), ev


def _whitened_lead(rng):
    """One standard deviation of neighbour 1's residual along x (m)."""
    _, ev = _step(rng, LinkMemory(6), PARAMS)
    return float(np.sqrt(ev.fix_residual_cov[0, 0, 0]))


def test_a_slow_lead_inside_every_per_step_gate_is_caught():
    rng = np.random.default_rng(0)
    sigma = _whitened_lead(rng)
    memory = LinkMemory(6)
    caught, per_step, steps = None, 0, 300
    for k in range(steps):
        out, ev = _step(rng, memory, PARAMS, lead=1.0 * sigma)
        per_step += bool(ev.fix_excluded[0])
        if out[0] and caught is None:
            caught = k
            assert held_out(PARAMS, memory, np.array([0]), np.array([1]))[0]
            break
        assert not ev.sequence_discard[1:].any()  # the honest links are not held out
    # The per-step test (1e-3 false alarms, gate 13.8 on a statistic near 1 + noise) passes
    # nearly every step; the sum reaches the 1e-6 gate (27.6) after about 28 steps.
    assert per_step <= 0.1 * (caught + 1)
    assert caught is not None and 10 <= caught <= 120
    # Held out, its fix enters no reference: the others' residuals lose the lie's pull.
    _, ev = _step(rng, memory, PARAMS, lead=1.0 * sigma)
    assert ev.fix_excluded[0] and np.isnan(ev.fix_residual[0]).all() is np.False_


def test_without_the_stage_the_same_lead_is_never_discarded():
    rng = np.random.default_rng(0)
    sigma = _whitened_lead(rng)
    params = replace(PARAMS, redundancy_sequence=False)
    discarded = sum(
        bool(_step(rng, LinkMemory(6), params, lead=1.0 * sigma)[0][0]) for _ in range(200)
    )
    assert discarded <= 20  # the per-step test alone: a few noise excursions at most


def test_an_honest_neighbour_is_never_locked_out():
    rng = np.random.default_rng(1)
    memory = LinkMemory(6)
    # 1500 honest steps: the sequence test never holds a link out at the default 1e-6 gate
    # (the per-step test has its own 1e-3 false alarms, a step at a time).
    for _ in range(1500):
        _, ev = _step(rng, memory, PARAMS)
        assert not ev.sequence_discard.any()
    state = memory.stage_statistic(NAME, width=WIDTH)
    assert np.abs(state.get(np.array([0]), np.array([1]))[0, :5]).sum() > 0.0
    # A false alarm forced by one gross reading holds the link out for `hold` evaluations,
    # then it is re-admitted with its sums reset.
    _, ev = _step(rng, memory, PARAMS, lead=1.0)
    assert ev.sequence_discard[0] and not ev.sequence_discard[1:].any()
    for _ in range(int(PARAMS.redundancy_sequence_hold)):
        out, ev = _step(rng, memory, PARAMS)
        assert out[0] and ev.sequence_discard[0]
    _, ev = _step(rng, memory, PARAMS)
    assert not ev.sequence_discard.any()
    fresh = state.get(np.array([0]), np.array([1]))[0]
    assert fresh[5] == 0.0 and _statistic(fresh[None])[0] < 14.0


def test_sequence_step_discounts_alarms_and_holds():
    state = np.zeros((3, WIDTH))
    d = np.array([[1.0, 0.0], [0.0, 0.0], [5.0, 0.0]])
    C = np.tile(np.eye(2), (3, 1, 1))
    judged = np.array([True, False, True])
    one = np.ones(3)
    out, stat, new = sequence_step(state, d, C, judged, 10.0 * one, 4.0 * one, 0.5 * one)
    np.testing.assert_array_equal(out, [False, False, True])
    assert stat[0] == pytest.approx(1.0) and np.isnan(stat[1])
    np.testing.assert_array_equal(new[1], 0.0)  # not judged: unchanged
    np.testing.assert_array_equal(new[2], [0, 0, 0, 0, 0, 4.0])  # flagged: reset and held
    out, stat, new2 = sequence_step(new, d, C, judged, 10.0 * one, 4.0 * one, 0.5 * one)
    # discount 0.5: s = 0.5 + 1, V = 0.25 + 1
    assert stat[0] == pytest.approx(1.5**2 / 1.25)
    assert out[2] and new2[2, 5] == 3.0


def test_the_stage_needs_the_residuals_and_a_memory():
    i = np.zeros(1, int)
    bare = Evidence(np.zeros((1, 2)), np.eye(2)[None], np.zeros(1), i, i + 1, np.zeros(1, bool))
    stage = RedundancySequence()
    with pytest.raises(ValueError, match="LinkMemory"):
        stage.discard(bare, PARAMS, None)
    with pytest.raises(ValueError, match="residuals"):
        stage.discard(bare, PARAMS, LinkMemory(2))
    names = [s.name for s in DETECTOR_STAGES]
    assert names.index(NAME) == names.index("redundancy") + 1
    assert stage.compiled  # kernels_redundancy


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"detector.redundancy_sequence": "yes"}, "expected true or false"),
        (
            {"detector.redundancy_sequence": True, "detector.redundancy_sequence_hold": 0},
            "below the minimum 1",
        ),
        (
            {"detector.redundancy_sequence": True, "detector.redundancy_sequence_forget": 1.5},
            "redundancy_sequence_forget",
        ),
        ({"detector.redundancy_sequence": True}, "set detector.redundancy = true"),
    ],
)
def test_sequence_keys_fail_with_one_line(changes, message):
    with pytest.raises(ConfigError, match=message) as err:
        default_scenario().replace(**changes)
    assert "\n" not in str(err.value) and "redundancy_sequence" in str(err.value)


def test_the_defences_switch_it_on():
    base = default_scenario()
    for name in ("full+redundancy+sequence", "zone+full+redundancy+sequence"):
        params = base.replace(**DEFENCES[name]).cl_params()
        assert params.redundancy and params.redundancy_sequence and params.recovery
        assert params.redundancy_sequence_gate == pytest.approx(27.631, rel=1e-4)
        assert params.redundancy_sequence_hold == 100.0
        assert params.redundancy_sequence_forget == 1.0


@pytest.mark.parametrize(("mode", "cap"), [("sequential", False), ("summed", True)])
def test_robot_nodes_reproduce_the_batched_engine_with_the_sequence_test(mode, cap):
    scenario = hot_scenario(15)
    params = replace(
        scenario.replace(**DEFENCES["full+redundancy+sequence"]).cl_params(),
        update_mode=mode,
        redundancy_cap_fusion=cap,
        redundancy_sequence_gate=1.0,  # strict: links are held out in the honest run too
        redundancy_sequence_hold=3.0,
    )
    world, x0, P0, ws_list = simulate(scenario, trials=1, seed=4)
    filt = make_filter("ekf")
    with kernels.use_backend("auto"):
        batched = run_batched(filt, params, world, x0, P0, ws_list)
        by_robot = run_nodes(filt, params, world, x0, P0, ws_list)
        without = run_batched(
            filt, replace(params, redundancy_sequence=False), world, x0, P0, ws_list
        )
    # The kernel implements the stage (kernels_redundancy) and both update modes
    # (kernels_summed).
    assert assert_same(batched, by_robot, ws_list, compiled=kernels.backend() == "numba") > 0
    assert max(np.abs(b[0] - w[0]).max() for b, w in zip(batched, without, strict=True)) > 1e-6


def _statistic(state):
    """``s^T V^-1 s`` of link states, shape (E, 6) -> (E,)."""
    s0, s1, a, b, c = state[:, :5].T
    with np.errstate(divide="ignore", invalid="ignore"):  # a reset link: 0 / 0
        return (c * s0 * s0 - 2.0 * b * s0 * s1 + a * s1 * s1) / (a * c - b * b)


def _sent_statistic(params, memory, sent, links, tampered):
    """The sequence verdict and statistic of every link after the victim judges ``sent``."""
    fields = fix_evidence(
        sent,
        POSE[links.i],
        tampered.neighbours.P[links.i],
        links.x_nb,
        tampered.P_nb,
        links.i,
        params,
        links.j,
        memory,
    )
    return fields["sequence_discard"], _statistic(fields["sequence_state"])


def test_the_compromised_robot_spends_the_sequence_tests_budget_and_no_more():
    """Per-step gates opened wide (the sequence test binds): with a link's sums already
    near the gate, the compromised robot's lie is cut to what keeps the sum inside it."""
    params = CLParams(
        detector_norm="nis",
        rho=float(np.sqrt(chi2_gate(1e-12))),
        redundancy=True,
        redundancy_gate=chi2_gate(1e-12),
        redundancy_sequence=True,
        redundancy_sequence_gate=chi2_gate(1e-6),
    )
    links, step, z_hat, S = _compromised_scene(params)
    adv = make_attacker("compromised", robots=1, claimed_cov=1.0)
    liar = 4  # j = 5
    fresh = adv.attack(links, step, params, LinkMemory(6))
    sent_fresh = fresh.tamper(np.arange(5), z_hat, S)
    # A history: the liar's sums already lead along +x at 80% of the gate.
    memory = LinkMemory(6)
    _, stat0 = _sent_statistic(params, LinkMemory(6), links.z, links, fresh)
    fields = fix_evidence(
        links.z,
        POSE[links.i],
        fresh.neighbours.P[links.i],
        links.x_nb,
        fresh.P_nb,
        links.i,
        params,
        links.j,
        LinkMemory(6),
    )
    Cd = fields["fix_residual_cov"][liar]
    V = 20.0 * Cd
    # A history along the fresh lie's own residual, s^T V^-1 s = 0.8 gate exactly.
    lead = fix_evidence(
        sent_fresh,
        POSE[links.i],
        fresh.neighbours.P[links.i],
        links.x_nb,
        fresh.P_nb,
        links.i,
        params,
        links.j,
        LinkMemory(6),
    )["fix_residual"][liar]
    s = lead * np.sqrt(0.8 * params.redundancy_sequence_gate / (lead @ np.linalg.solve(V, lead)))
    memory.stage_statistic(NAME, width=WIDTH).set(
        np.array([0]), np.array([5]), np.array([[s[0], s[1], V[0, 0], V[0, 1], V[1, 1], 0.0]])
    )
    tampered = adv.attack(links, step, params, memory)
    sent = tampered.tamper(np.arange(5), z_hat, S)
    lie_fresh = np.abs(sent_fresh[liar] - links.z[liar]).sum()
    lie = np.abs(sent[liar] - links.z[liar]).sum()
    assert 0.0 < lie < 0.9 * lie_fresh
    out, stat = _sent_statistic(params, memory, sent, links, tampered)
    assert not out.any()
    assert stat[liar] == pytest.approx(params.redundancy_sequence_gate, rel=0.02)
    more = sent.copy()
    more[liar] = sent[liar] + 0.1 * (sent[liar] - links.z[liar])
    out, _ = _sent_statistic(params, memory, more, links, tampered)
    assert out[liar]
    assert np.isfinite(stat0).all()


def test_capped_claims_scale_the_whole_covariance_as_the_test_caps_it():
    from resloc.cl.detection_redundancy_fixes import capped_claims, weight_capped_covariance

    P = np.tile(np.diag([1e-4, 1e-4, 1e-5]), (4, 1, 1))
    P[1] *= 0.01  # a neighbour claiming x0.01
    P[3] *= 10.0
    i = np.array([0, 0, 0, 1])
    out = capped_claims(P, i)
    np.testing.assert_allclose(out[:, :2, :2], weight_capped_covariance(P, i))
    np.testing.assert_allclose(out[1], P[0])  # raised to the median, heading block too
    np.testing.assert_allclose(out[[0, 2, 3]], P[[0, 2, 3]])  # at or above it: as claimed


def test_the_cap_in_fusion_changes_what_a_tiny_claim_buys():
    """A victim of one neighbour claiming x0.01 of its covariance: with the cap in fusion
    the neighbour pulls the estimate no more than a typical one."""
    import resloc

    params = CLParams(detector=False, trigger=False, redundancy=True)
    links, _, _, _ = _compromised_scene(params)
    liar = 4
    P_nb = links.P_nb.copy()
    P_nb[liar] *= 0.01
    x = links.neighbours.x.copy()
    x_nb = links.x_nb.copy()
    x_nb[liar, 0] += 0.05  # the claim comes with a false position
    lied = replace(links, P_nb=P_nb, x_nb=x_nb)
    P = links.neighbours.P
    moved = {}
    for cap in (False, True):
        p = replace(params, redundancy_cap_fusion=cap)
        xc, _, _ = resloc.cl.step.correct(make_filter("ekf"), x, P, lied, p)
        moved[cap] = abs(xc[0, 0] - x[0, 0])
    assert moved[True] < 0.5 * moved[False]
    with pytest.raises(ConfigError, match=r"set detector\.redundancy = true"):
        default_scenario().replace(**{"detector.redundancy_cap_fusion": True})
    assert (
        default_scenario()
        .replace(**DEFENCES["zone+full+redundancy+sequence+cap"])
        .cl_params()
        .redundancy_cap_fusion
    )
