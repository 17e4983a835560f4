"""Zone landmarks (cl/detection_landmark.py): a neighbour whose broadcast position is inside
the map is not fused and its fix enters no redundancy reference; the scenario keys; the
compromised robot's oracle knows it (inside the map nothing it sends is accepted, outside
it lies as before)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from resloc.cl.cusum import chi2_gate
from resloc.cl.detection import DETECTOR_STAGES, Evidence, detect
from resloc.cl.detection_landmark import ZoneLandmarks, not_landmarks
from resloc.cl.detection_redundancy import fix_evidence
from resloc.cl.detection_zone import zone_map
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.world.attackers import make_attacker
from resloc.world.attackers.oracle import accepted, fix_context
from test_defence_redundancy import POSE, _compromised_scene

MAP = zone_map([((0.0, 0.0), 1.0)])


def _evidence(x_nb, nu):
    E = len(x_nb)
    S = np.broadcast_to(np.diag([0.01, 0.01]), (E, 2, 2)).copy()
    norm = np.sqrt(np.einsum("ei,ei->e", nu, nu) / 0.01)
    return Evidence(
        nu,
        S,
        norm,
        np.zeros(E, int),
        np.arange(E) + 1,
        np.zeros(E, bool),
        P_obs=np.broadcast_to(np.eye(3) * 1e-2, (E, 3, 3)).copy(),
        x_obs=np.tile([3.0, 0.0, 0.0], (E, 1)),
        x_nb=x_nb,
    )


def test_links_from_neighbours_inside_the_map_are_withheld_from_every_stage():
    assert any(s.name == "zone_landmarks" and s.withholds for s in DETECTOR_STAGES)
    params = CLParams(
        detector_norm="nis",
        rho=3.0,
        recovery=True,
        recovery_after=1.0,
        recovery_inflation_cap=1e6,
        zone_landmarks=True,
        zone_landmarks_map=MAP,
    )
    x_nb = np.array([[0.2, 0.0, 0.0], [0.0, 0.99, 0.0], [1.01, 0.0, 0.0], [2.0, 2.0, 0.0]])
    memory = LinkMemory(10)
    # Honest-looking readings from inside are withheld (not re-admitted by the recovery);
    # a gross reading from outside is still judged by the gate.
    nu = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [5.0, 5.0]])
    np.testing.assert_array_equal(detect(_evidence(x_nb, nu), params, memory), [1, 1, 0, 1])
    off = dataclasses.replace(params, zone_landmarks=False)
    np.testing.assert_array_equal(detect(_evidence(x_nb, nu), off, LinkMemory(10)), [0, 0, 0, 1])
    ev = _evidence(x_nb, nu)
    ev.x_nb = None
    with pytest.raises(ValueError, match="x_nb"):
        ZoneLandmarks().discard(ev, params, memory)


def test_a_withheld_neighbours_fix_is_in_no_redundancy_reference():
    """Robot 0's five fixes; neighbour 5 (inside the map) sends a lie inside the redundancy
    gate: without the stage it pulls the others' references; with it, the others' residuals
    are as if it had not been there."""
    params = CLParams(detector=False, redundancy=True, redundancy_gate=chi2_gate(1e-3))
    links, _, _, _ = _compromised_scene(params)
    x_nb = links.x_nb.copy()
    x_nb[4, 0] += 0.02  # the lie, carried by the broadcast here
    on = dataclasses.replace(
        params, zone_landmarks=True, zone_landmarks_map=zone_map([((0.6, 0.6), 0.2)])
    )
    P = np.tile(np.diag([1e-4, 1e-4, 1e-4]), (5, 1, 1))
    args = (links.z, POSE[links.i], P)
    base = fix_evidence(*args, x_nb, P, links.i, params)
    with_stage = fix_evidence(*args, x_nb, P, links.i, on)
    without_liar = fix_evidence(
        links.z[:4], POSE[links.i[:4]], P[:4], x_nb[:4], P[:4], links.i[:4], params
    )
    np.testing.assert_allclose(
        with_stage["fix_residual"][:4], without_liar["fix_residual"], atol=1e-12
    )
    assert not base["fix_excluded"].any()
    assert np.abs(base["fix_residual"][:4] - without_liar["fix_residual"]).max() > 1e-3
    np.testing.assert_array_equal(not_landmarks(on, x_nb, np.zeros(5, bool)), [0, 0, 0, 0, 1])
    assert not_landmarks(params, x_nb, None) is None


def test_the_scenario_keys_build_the_grown_map_and_the_defence_switches_it_on():
    scenario = default_scenario().replace(**DEFENCES["zone+full+redundancy+sequence+cap+landmarks"])
    p = scenario.cl_params()
    assert p.zone_landmarks and p.redundancy_sequence and p.redundancy_cap_fusion
    (_, _, r), (_, _, r_trust) = p.zone_landmarks_map[0], p.zone_trust_map[0]
    assert r == pytest.approx(r_trust + 0.25)
    clean = scenario.replace(sdz=[]).cl_params()
    assert clean.zone_landmarks_map == ()  # no SDZ: nothing withheld, the clean run unchanged


@pytest.mark.parametrize("claimed_cov", [1.0, 0.01])
def test_the_compromised_robot_knows_a_landmark_inside_the_map_is_not_fused(claimed_cov):
    """The victim's detector with the gate loose (the redundancy test binds). Liar 5 inside
    the map: its oracle finds nothing it sends accepted and sends no lie (its row is out of
    every reference too, so a lie there buys nothing); the victim withholds the row. With
    the map elsewhere its lie is the one without the stage."""
    base = CLParams(detector_norm="nis", rho=float(np.sqrt(chi2_gate(1e-9))), redundancy=True)
    links, step, z_hat, S = _compromised_scene(base)
    adv = make_attacker("compromised", robots=1, claimed_cov=claimed_cov)
    liar = 4  # j = 5, at (0.6, 0.6)
    inside = dataclasses.replace(
        base, zone_landmarks=True, zone_landmarks_map=zone_map([((0.6, 0.6), 0.2)])
    )
    elsewhere = dataclasses.replace(
        base, zone_landmarks=True, zone_landmarks_map=zone_map([((-3.0, -3.0), 0.2)])
    )
    sent = {}
    for name, params in (("off", base), ("inside", inside), ("elsewhere", elsewhere)):
        tampered = adv.attack(links, step, params, None)
        sent[name] = tampered.tamper(np.arange(5), z_hat, S)
        context = fix_context(tampered, np.array([liar]), params)
        ok = accepted(
            sent[name][[liar]],
            z_hat[[liar]],
            S[[liar]],
            links.i[[liar]],
            links.j[[liar]],
            params,
            None,
            context=context,
        )
        assert ok.all() == (name != "inside")
    assert not np.allclose(sent["off"][liar], links.z[liar])
    np.testing.assert_allclose(sent["inside"][liar], links.z[liar], atol=1e-12)
    np.testing.assert_allclose(sent["elsewhere"], sent["off"], atol=1e-12)
