"""The reciprocal range check (cl/detection_reciprocal.py) and the two-ended attacker
(world/attackers/reciprocal.py): a one-ended liar is caught, honest links are never locked
out, one robot's process runs it as the batched engine does, bad keys fail in one line, and
the two-ended attacker gets through the check alone (the check's blind spot, by design)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from resloc.cl import kernels
from resloc.cl.cusum import chi2_gate
from resloc.cl.detection import DETECTOR_STAGES, Evidence, detect
from resloc.cl.detection_reciprocal import (
    STATE_WIDTH,
    ReciprocalCheck,
    judged_pairs,
    reciprocal_evidence,
    reciprocal_step,
)
from resloc.cl.detection_zone import reciprocal_rows
from resloc.cl.links import LinkBatch
from resloc.cl.memory import LinkMemory
from resloc.cl.node import RobotNode
from resloc.cl.params import CLParams
from resloc.cl.step import correct, predict
from resloc.errors import ConfigError
from resloc.experiments.config import default_scenario
from resloc.experiments.config_dump import toml_value
from resloc.experiments.defences import DEFENCES
from resloc.filters.base import make_filter
from resloc.models.measurement import range_bearing
from resloc.world.attackers import AttackStep, make_attacker
from resloc.world.attackers.oracle import accepted, fix_context
from test_node import FLAGS, TOL, hot_scenario, simulate

NAME = ReciprocalCheck.name
#: Only the reciprocal check judges (the gate off).
PARAMS = CLParams(
    detector=False,
    reciprocal=True,
    reciprocal_gate=chi2_gate(1e-3, dof=1),
    reciprocal_sequence_gate=chi2_gate(1e-6, dof=1),
    reciprocal_hold=40.0,
)
SIGMA = PARAMS.range_std
#: Robot 0's links to 1..4 and their reverse links.
OBS = np.array([0, 0, 0, 0, 1, 2, 3, 4])
NB = np.array([1, 2, 3, 4, 0, 0, 0, 0])
POSE = np.array(
    [[0.0, 0.0, 0.4], [0.8, 0.1, 0.0], [-0.2, 0.7, 1.0], [-0.6, -0.4, -2.0], [0.3, -0.8, 2.5]]
)


def _step(rng, memory, params=PARAMS, bias=0.0):
    """One step of the eight links with range noise; robot 0's reading of robot 1 is
    lengthened by ``bias`` (a one-ended liar). Returns the discards."""
    z = range_bearing(POSE[OBS], POSE[NB]) + rng.normal(0.0, [SIGMA, 0.05], (len(OBS), 2))
    z[0, 0] += bias
    partner = z[reciprocal_rows(OBS, NB)]
    fields = reciprocal_evidence(z, partner, OBS, NB, params, memory)
    E = len(OBS)
    ev = Evidence(
        np.zeros((E, 2)),
        np.tile(np.eye(2), (E, 1, 1)),
        np.zeros(E),
        OBS,
        NB,
        np.zeros(E, bool),
        **fields,
    )
    return detect(ev, params, memory)


def test_a_gross_one_ended_lie_is_discarded_at_once_on_both_ends_and_held():
    rng = np.random.default_rng(0)
    memory = LinkMemory(5)
    out = _step(rng, memory, bias=0.05)  # 10 sigma_r: over the one-step gate and the sum
    np.testing.assert_array_equal(out, [True, False, False, False, True, False, False, False])
    state = memory.stage_statistic(NAME, width=STATE_WIDTH).get(np.array([0, 1]), np.array([1, 0]))
    np.testing.assert_array_equal(state[:, 2], PARAMS.reciprocal_hold)  # both links held


def test_a_liar_under_the_one_step_gate_is_caught_by_the_sum_in_bounded_steps():
    rng = np.random.default_rng(1)
    memory = LinkMemory(5)
    bias = 1.0 * np.sqrt(2.0) * SIGMA  # one standard deviation of d per step
    caught = None
    one_step = 0
    for k in range(300):
        out = _step(rng, memory, bias=bias)
        if out[0]:
            state = memory.stage_statistic(NAME, width=STATE_WIDTH).get(
                np.array([0]), np.array([1])
            )
            if state[0, 2] > 0:  # held: the sum alarmed
                caught = k
                break
            one_step += 1
    # The sum reaches the 1e-6 gate (23.9) after about 24 steps of a 1-sigma lead; the
    # one-step gate (10.8) passes nearly every one of those steps.
    assert caught is not None and 5 <= caught <= 120, caught
    assert one_step <= 0.2 * (caught + 1)
    # without the sum, the same liar is discarded only on the one-step gate's excursions
    no_sum = replace(PARAMS, reciprocal_sequence_gate=np.inf)
    memory = LinkMemory(5)
    discarded = sum(bool(_step(rng, memory, no_sum, bias=bias)[0]) for _ in range(200))
    assert discarded <= 20


def test_1500_honest_steps_hold_nothing_and_a_held_link_is_readmitted():
    rng = np.random.default_rng(2)
    memory = LinkMemory(5)
    store = memory.stage_statistic(NAME, width=STATE_WIDTH)
    one_step = 0
    for _ in range(1500):
        out = _step(rng, memory)
        assert not (store.values[:, 2] > 0).any()  # no hold: the sum never alarms
        one_step += int(out.sum())
    # the one-step gate's own false alarms: 1e-3 per link and step
    assert one_step <= 0.004 * 1500 * len(OBS)
    assert np.abs(store.get(np.array([0]), np.array([1]))[0, :2]).sum() > 0.0
    # A false alarm forced by one gross reading: held for `hold` evaluations, then
    # re-admitted with its sums reset.
    assert _step(rng, memory, bias=1.0)[0]
    hold = int(PARAMS.reciprocal_hold)
    for _ in range(hold):
        assert _step(rng, memory)[0]
    out = _step(rng, memory)
    assert not out[0]
    fresh = store.get(np.array([0]), np.array([1]))[0]
    assert fresh[2] == 0.0 and fresh[1] == pytest.approx(2.0 * SIGMA**2)


def test_reciprocal_step_discounts_and_holds():
    state = np.zeros((3, STATE_WIDTH))
    d = np.array([0.01, 0.0, 1.0])
    judged = np.array([True, False, True])
    one = np.ones(3)
    out, stat, new = reciprocal_step(
        state, d, judged, 1e-4, 1e9 * one, 1e3 * one, 4 * one, 0.5 * one
    )
    np.testing.assert_array_equal(out, [False, False, True])
    assert stat[0] == pytest.approx(1.0) and np.isnan(stat[1])
    np.testing.assert_array_equal(new[1], 0.0)  # not judged: unchanged
    np.testing.assert_array_equal(new[2], [0.0, 0.0, 4.0])  # flagged: reset and held
    out, stat, new2 = reciprocal_step(
        new, d, judged, 1e-4, 1e9 * one, 1e3 * one, 4 * one, 0.5 * one
    )
    assert stat[0] == pytest.approx(0.015**2 / 1.25e-4)  # s = 0.5 s + d, V = 0.25 V + var
    assert out[2] and new2[2, 2] == 3.0


def test_the_map_leaves_a_pair_with_one_end_inside_to_zone_trust():
    params = replace(PARAMS, zone_trust=True, zone_trust_map=((0.0, 0.0, 0.5),))
    x_obs = np.array([[2.0, 0.0, 0.0], [0.1, 0.0, 0.0], [2.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    x_nb = np.array([[0.1, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.2, 0.0, 0.0]])
    z_rec = np.ones((4, 2))
    np.testing.assert_array_equal(judged_pairs(z_rec, x_obs, x_nb, params), [0, 0, 1, 1])
    z_rec[2] = np.nan
    np.testing.assert_array_equal(judged_pairs(z_rec, x_obs, x_nb, PARAMS), [1, 1, 0, 1])


def test_the_stage_needs_its_evidence_and_a_memory():
    i = np.zeros(1, int)
    bare = Evidence(np.zeros((1, 2)), np.eye(2)[None], np.zeros(1), i, i + 1, np.zeros(1, bool))
    stage = ReciprocalCheck()
    with pytest.raises(ValueError, match="LinkMemory"):
        stage.discard(bare, PARAMS, None)
    with pytest.raises(ValueError, match="partners' readings"):
        stage.discard(bare, PARAMS, LinkMemory(2))
    assert NAME in [s.name for s in DETECTOR_STAGES] and stage.compiled


def test_robot_nodes_reproduce_the_batched_engine_with_the_reciprocal_check():
    """Each node gets its neighbours' readings of it (z_reciprocal): the same estimates,
    covariances and verdicts as the batched engine to 1e-9 (both compiled when numba is
    installed: the nodes' partner readings given, the batch's found in it); a strict gate
    makes it discard and hold in the honest run."""
    scenario = hot_scenario(25)
    params = replace(
        scenario.replace(**DEFENCES["full+redundancy+sequence+reciprocal"]).cl_params(),
        reciprocal_gate=1.0,
        reciprocal_sequence_gate=2.0,
        reciprocal_hold=3.0,
    )
    world, x0, P0, ws_list = simulate(scenario, trials=1, seed=4)
    filt = make_filter("ekf")
    discarded = 0
    with kernels.use_backend("auto"):
        x, P = x0.copy(), P0.copy()
        memory = LinkMemory(world.B)
        nodes = [RobotNode(b, filt, params, x0[b], P0[b], n_ids=world.B) for b in range(world.B)]
        for ws in ws_list:
            xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
            links = LinkBatch(
                ws.i,
                ws.j,
                ws.z,
                xp[ws.j],
                Pp[ws.j],
                ws.channel_ok,
                ws.risk_s,
                ws.risk_c,
                ws.lambda2,
            )
            x, P, out = correct(filt, xp, Pp, links, params, memory)
            assert out.compiled == (kernels.backend() == "numba")
            reverse = reciprocal_rows(ws.i, ws.j)
            for node, u in zip(nodes, ws.u_meas, strict=True):
                node.predict(u, world.dt)
            sent = [node.estimate for node in nodes]
            for b, node in enumerate(nodes):
                rows = np.flatnonzero(ws.i == b)
                nb = ws.j[rows]
                got = node.correct(
                    nb,
                    ws.z[rows],
                    np.array([sent[j][0] for j in nb]).reshape(-1, 3),
                    np.array([sent[j][1] for j in nb]).reshape(-1, 3, 3),
                    ws.channel_ok[rows],
                    ws.risk_s[b],
                    ws.risk_c[b],
                    ws.lambda2[b],
                    z_reciprocal=np.where(
                        (reverse[rows] >= 0)[:, None], ws.z[np.maximum(reverse[rows], 0)], np.nan
                    ),
                )
                for name in FLAGS:
                    np.testing.assert_array_equal(getattr(got, name), getattr(out, name)[rows])
            xn = np.concatenate([node.x for node in nodes])
            Pn = np.concatenate([node.P for node in nodes])
            assert np.abs(xn - x).max() <= TOL and np.abs(Pn - P).max() <= TOL
            discarded += int(out.detected.sum())
    assert discarded > 10


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"detector.reciprocal": "yes"}, "expected true or false"),
        ({"detector.reciprocal": True, "detector.reciprocal_hold": 0}, "below the minimum 1"),
        ({"detector.reciprocal": True, "detector.reciprocal_forget": 1.5}, "reciprocal_forget"),
        (
            {"detector.reciprocal": True, "detector.reciprocal_sequence_false_alarm": 0.01},
            "set it <= reciprocal_false_alarm",
        ),
    ],
)
def test_reciprocal_keys_fail_with_one_line(changes, message, tmp_path):
    with pytest.raises(ConfigError, match=message) as err:
        default_scenario().replace(**changes)
    assert "\n" not in str(err.value) and "reciprocal" in str(err.value)
    # the same through the command line: one line, exit 2, nothing written
    from resloc.cli.app import app

    lines = ["[detector]", *(f"{k.split('.')[1]} = {toml_value(v)}" for k, v in changes.items())]
    path = tmp_path / "bad.toml"
    path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["run", str(path), "--out", str(out), "--no-plots"])
    text = (res.stderr or res.output).strip()
    assert res.exit_code == 2 and "detector.reciprocal" in text and "Traceback" not in text
    assert len(text.splitlines()) == 1 and not out.exists()


def test_the_runtime_runs_the_reciprocal_check_and_refuses_it_only_with_pulled_estimates():
    from resloc.runtime.team import check_supported

    scenario = default_scenario().replace(**{"detector.reciprocal": True, "run.trials": 1})
    check_supported(scenario)  # the readings ride on the estimates
    pulled = scenario.replace(**{"estimator.neighbour_estimate": "cached"})
    with pytest.raises(ConfigError, match=r"detector\.reciprocal: pulled estimates") as err:
        check_supported(pulled)
    assert "\n" not in str(err.value)


def _pair_scene(params):
    """Robots 0..4 all seeing each other (every pair both ways), honest readings."""
    i, j = np.nonzero(~np.eye(5, dtype=bool))
    rng = np.random.default_rng(3)
    z = range_bearing(POSE[i], POSE[j]) + rng.normal(0, [SIGMA, 0.05], (len(i), 2))
    P = np.tile(np.diag([1e-4, 1e-4, 1e-4]), (5, 1, 1))
    links = LinkBatch.from_predicted(
        i, j, z, POSE.copy(), P, np.ones(len(i), bool), np.zeros(5), np.zeros(5), np.ones(5)
    )
    from resloc.cl.fusion_methods import fusion_strategy

    m = fusion_strategy(params.fusion).moments(
        make_filter("ekf"), None, POSE[i], P[i], POSE[j], P[j], i, j, params.R
    )
    return links, i, j, z, m.z_hat, m.S


def _sent(adv, params, links, attacked, z_hat, S, memory=None):
    i, j = links.i, links.j
    step = AttackStep(1, 0.033, POSE, i, j, links.z, attacked, 5)
    tampered = adv.attack(links, step, params, memory)
    return tampered.tamper(np.arange(len(i)), z_hat, S)


def test_the_two_ended_attacker_gets_through_the_check_alone_and_spends_its_slack():
    """Against the reciprocal check alone, robot 0 compromised (lies about its own
    readings; the sensors that see it falsified): both ends move by the whole 0.5 m lie,
    nothing is discarded, and one end of each pair carries the check's one-step slack on
    top (its statistic on the gate). The same lie on one end only is discarded."""
    params = CLParams(detector=False, reciprocal=True)
    links, i, j, z, z_hat, S = _pair_scene(params)
    attacked = (i == 0) | (j == 0)
    adv = make_attacker("two_ended", size=0.5, target=0)
    sent = _sent(adv, params, links, attacked, z_hat, S, LinkMemory(5))
    lie = sent[:, 0] - z[:, 0]
    assert np.all(lie[~attacked] == 0.0)
    assert np.all(lie[attacked] >= 0.5 - 1e-9)
    rows = np.flatnonzero(attacked)
    context = fix_context(links, rows, params, z=sent)
    ok = accepted(
        sent[rows], z_hat[rows], S[rows], i[rows], j[rows], params, LinkMemory(5), context=context
    )
    assert ok.all()
    d = sent[:, 0] - sent[reciprocal_rows(i, j), 0]
    t = d * d / (2 * SIGMA**2)
    spent = attacked & (lie > 0.5 + 1e-6)
    assert spent.sum() == 4  # one end of each of robot 0's four pairs
    assert np.all(t[spent] == pytest.approx(params.reciprocal_gate, rel=0.02))
    # a one-ended liar with the same 0.5 m is discarded on both ends of its pair
    one_ended = z.copy()
    one_ended[0, 0] += 0.5
    partner = one_ended[reciprocal_rows(i, j)]
    fields = reciprocal_evidence(one_ended, partner, i, j, params, LinkMemory(5))
    assert (
        fields["reciprocal_discard"][0] and fields["reciprocal_discard"][reciprocal_rows(i, j)[0]]
    )


def test_the_defences_switch_it_on_and_the_suite_has_the_attacker():
    base = default_scenario()
    for name in ("full+redundancy+sequence+reciprocal", "zone+full+redundancy+sequence+reciprocal"):
        params = base.replace(**DEFENCES[name]).cl_params()
        assert params.reciprocal and params.redundancy_sequence and params.recovery
        assert params.reciprocal_gate == pytest.approx(10.828, rel=1e-4)
        assert params.reciprocal_sequence_gate == pytest.approx(23.928, rel=1e-4)
    from resloc.world.attackers import ATTACKERS, variants

    assert "two_ended" in ATTACKERS
    assert [a.label for a in variants("two_ended")] == [
        "two_ended[size=0.5,target=-1]",
        "two_ended[size=2,target=-1]",
        "two_ended[size=2,target=5]",
    ]


def test_against_the_combination_in_a_short_run():
    """A short run (robot 5 of the team compromised, both ends of its links falsified):
    the reciprocal check alone is left blind (it discards nearly none of the falsified
    links) and the lie costs; the whole combination is judged by its own numbers (the study
    in docs/attack/reciprocal.md), here only run end to end."""
    from resloc.experiments.attack import run_attack_study

    scenario = default_scenario().replace(**{"run.steps": 25})
    defences = {
        "reciprocal only": {"detector.enabled": False, "detector.reciprocal": True},
        "combination": DEFENCES["full+redundancy+sequence+reciprocal"],
    }
    result = run_attack_study(scenario, defences, [("two_ended", {"target": 5})], seeds=2)
    rows = {(r["defence"], r["family"]): r for r in result.table}
    alone = rows["reciprocal only", "two_ended"]
    assert alone["tpr"]["mean"] < 0.05
    assert alone["msle_ratio"]["mean"] > 3.0
    combined = rows["combination", "two_ended"]
    assert np.isfinite(combined["msle_ratio"]["mean"])


def test_the_compromised_robot_reports_its_own_reading_to_match_its_lie():
    """The compromised robot's lie is in its broadcast estimate (the victim's reading is
    honest); the hook injects it as an equivalent reading, so with the reciprocal check on
    the liar moves its own reported reading by the same range: the pair's difference stays
    the honest one and the check is not credited with seeing a lie it physically cannot."""
    params = CLParams(detector_norm="nis", rho=float(np.sqrt(chi2_gate(1e-3))), reciprocal=True)
    links, i, j, z, z_hat, S = _pair_scene(params)
    adv = make_attacker("compromised", robots=1)
    liar = 2  # the suite's first compromised robot in a team of 5
    i_, j_ = links.i, links.j
    step = AttackStep(1, 0.033, POSE, i_, j_, links.z, j == liar, 5)
    tampered = adv.attack(links, step, params, LinkMemory(5))
    sent = tampered.tamper(np.arange(len(i)), z_hat, S)
    reverse = reciprocal_rows(i, j)
    victims = np.flatnonzero(j == liar)
    assert np.abs(sent[victims] - z[victims]).max() > 1e-3  # it lies
    partner = tampered.tamper.reported(sent[reverse])
    # the victims compare their (lie-carrying) rows with the liar's matching report
    d_sent = sent[victims, 0] - partner[victims, 0]
    np.testing.assert_allclose(d_sent, z[victims, 0] - z[reverse[victims], 0], atol=1e-12)
    # the liar fuses its honest readings and receives the victims' physical readings
    own = reverse[victims]
    np.testing.assert_array_equal(sent[own], z[own])
    np.testing.assert_allclose(partner[own, 0], z[victims, 0], atol=1e-12)
    untouched = (j != liar) & (i != liar)
    np.testing.assert_array_equal(sent[untouched], z[untouched])
