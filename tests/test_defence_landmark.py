"""Zone landmarks (cl/detection_landmark.py): a neighbour whose broadcast position is inside
the map is weighed with its claimed covariance inflated, in the tests and in the fusion;
the scenario keys; the compiled path runs it as the reference does; the compromised
robot's oracle knows it (its lie
sits on the redundancy gate of the inflated covariance, 5% more is rejected)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import resloc.cl.step
from resloc.cl.backend import kernel_refusal
from resloc.cl.cusum import chi2_gate
from resloc.cl.detection import DETECTOR_STAGES
from resloc.cl.detection_landmark import landmark_claims
from resloc.cl.detection_redundancy import fix_evidence
from resloc.cl.detection_zone import zone_map
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.params import CLParams
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters.base import make_filter
from resloc.world.attackers import make_attacker
from resloc.world.attackers.oracle import accepted, fix_context
from test_defence_redundancy import POSE, _compromised_scene

#: A disc around robot 5 (at (0.6, 0.6)), the compromised robot of the scene.
AROUND_5 = zone_map([((0.6, 0.6), 0.2)])


def test_claims_inside_the_map_are_inflated_and_no_others():
    params = CLParams(
        zone_landmarks=True, zone_landmarks_map=AROUND_5, zone_landmarks_inflation=7.0
    )
    P = np.tile(np.diag([1e-4, 2e-4, 3e-4]), (6, 1, 1))
    i = np.zeros(6, int)
    out = landmark_claims(params, POSE, P, i)
    np.testing.assert_array_equal(out[5], 7.0 * P[5])
    np.testing.assert_array_equal(out[:5], P[:5])
    # A tiny claim is raised to the median claim first (then inflated).
    tiny = P.copy()
    tiny[5] *= 0.01
    np.testing.assert_allclose(landmark_claims(params, POSE, tiny, i)[5], 7.0 * P[5])
    assert landmark_claims(dataclasses.replace(params, zone_landmarks_map=()), POSE, P, i) is P
    assert landmark_claims(dataclasses.replace(params, zone_landmarks=False), POSE, P, i) is P


@pytest.mark.parametrize("redundancy", [False, True])
def test_the_compiled_path_fuses_the_weakened_claims_as_the_reference(redundancy):
    """Neighbour 5 (inside the map) broadcasts 2 cm off: the compiled correction (the claims
    weakened before its kernel, between the redundancy cap and the hook) equals the
    reference to 1e-9, and differs from the run without the stage."""
    from resloc.cl import kernels

    (stage,) = [s for s in DETECTOR_STAGES if s.name == "zone_landmarks"]
    assert stage.compiled
    params = CLParams(
        detector_norm="nis",
        trigger=False,  # every estimate sent
        zone_landmarks=True,
        zone_landmarks_map=AROUND_5,
        redundancy=redundancy,
        redundancy_cap_fusion=redundancy,
    )
    links, *_ = _compromised_scene(params)
    x_nb = links.x_nb.copy()
    x_nb[4, 0] += 0.02
    links = dataclasses.replace(links, x_nb=x_nb, neighbours=None)
    x, P = POSE.copy(), np.tile(np.diag([1e-4, 1e-4, 1e-4]), (6, 1, 1))
    filt = make_filter("ckf")
    if not kernels.HAVE_NUMBA:
        pytest.skip("numba is not installed")
    assert kernel_refusal(filt, params, links) is None
    runs = {}
    for name, p, backend in (
        ("compiled", params, "numba"),
        ("reference", params, "numpy"),
        ("without", dataclasses.replace(params, zone_landmarks=False), "numba"),
    ):
        with kernels.use_backend(backend):
            runs[name] = resloc.cl.step.correct(filt, x, P, links, p)
    assert runs["compiled"][2].compiled and not runs["reference"][2].compiled
    np.testing.assert_allclose(runs["compiled"][0], runs["reference"][0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(runs["compiled"][1], runs["reference"][1], rtol=0, atol=1e-9)
    assert np.abs(runs["compiled"][0] - runs["without"][0]).max() > 1e-4


def test_a_neighbour_inside_the_map_moves_the_victim_less():
    """Robot 0 fuses its five neighbours; neighbour 5 broadcasts 2 cm off along x. With
    the map around 5 the victim follows it about ten times less (inflation 10)."""
    base = CLParams(detector=False, trigger=False)
    links, *_ = _compromised_scene(base)
    x_nb = links.x_nb.copy()
    x_nb[4, 0] += 0.02
    lied = dataclasses.replace(links, x_nb=x_nb, neighbours=None)
    x, P = POSE.copy(), np.tile(np.diag([1e-4, 1e-4, 1e-4]), (6, 1, 1))
    filt = make_filter("ekf")

    def moved(params):
        honest, _, _ = resloc.cl.step.correct(
            filt, x, P, dataclasses.replace(lied, x_nb=links.x_nb), params
        )
        out, _, _ = resloc.cl.step.correct(filt, x, P, lied, params)
        return out[0, 0] - honest[0, 0]

    off = moved(base)
    on = moved(dataclasses.replace(base, zone_landmarks=True, zone_landmarks_map=AROUND_5))
    assert off > 1e-3
    assert 0.0 < on < 0.25 * off


def test_the_scenario_keys_build_the_grown_map_and_the_defence_switches_it_on():
    scenario = default_scenario().replace(**DEFENCES["zone+full+redundancy+sequence+cap+landmarks"])
    p = scenario.cl_params()
    assert p.zone_landmarks and p.redundancy_sequence and p.redundancy_cap_fusion
    assert p.zone_landmarks_inflation == 10.0
    (_, _, r), (_, _, r_trust) = p.zone_landmarks_map[0], p.zone_trust_map[0]
    assert r == pytest.approx(r_trust + 0.25)
    clean = scenario.replace(sdz=[]).cl_params()
    assert clean.zone_landmarks_map == ()  # no SDZ: nothing inflated, the clean run unchanged


@pytest.mark.parametrize("claimed_cov", [1.0, 0.01])
def test_the_compromised_robot_inside_the_map_sits_on_the_gate_of_the_inflated_claim(
    claimed_cov,
):
    """A loose NIS gate (the redundancy test binds). Liar 5 inside the map: the victim's
    test weighs it with its claim inflated; the lie sent puts the statistic on the gate
    (within 2%), 5% more is rejected, and it is larger than the lie without the stage."""
    base = CLParams(detector_norm="nis", rho=float(np.sqrt(chi2_gate(1e-9))), redundancy=True)
    params = dataclasses.replace(base, zone_landmarks=True, zone_landmarks_map=AROUND_5)
    liar = 4  # j = 5
    adv = make_attacker("compromised", robots=1, claimed_cov=claimed_cov)
    sent, lie = {}, {}
    for name, p in (("off", base), ("on", params)):
        links, step, _, _ = _compromised_scene(p)
        tampered = adv.attack(links, step, p, None)
        # The victim's prediction with the claims as its step weighs them.
        P_nb = landmark_claims(p, tampered.x_nb, tampered.P_nb, links.i)
        m = fusion_strategy(p.fusion).moments(
            make_filter("ekf"),
            None,
            POSE[links.i],
            tampered.neighbours.P[links.i],
            tampered.x_nb,
            P_nb,
            links.i,
            links.j,
            p.R,
        )
        sent[name] = tampered.tamper(np.arange(5), m.z_hat, m.S)
        lie[name] = np.abs(sent[name][liar] - links.z[liar]).sum()
        ev = fix_evidence(
            sent[name],
            POSE[links.i],
            tampered.neighbours.P[links.i],
            links.x_nb,
            P_nb,
            links.i,
            p,
        )
        assert not ev["fix_excluded"].any()
        assert ev["fix_statistic"][liar] == pytest.approx(p.redundancy_gate, rel=0.02)
        context = fix_context(tampered, np.array([liar]), p, tampered.P_nb)
        more = sent[name][[liar]] + 0.05 * (sent[name][[liar]] - links.z[[liar]])
        args = (m.z_hat[[liar]], m.S[[liar]], links.i[[liar]], links.j[[liar]], p, None)
        assert accepted(sent[name][[liar]], *args, context=context).all()
        assert not accepted(more, *args, context=context).any()
    assert lie["on"] > 1.5 * lie["off"]


@pytest.mark.parametrize(("mode", "cap"), [("sequential", True), ("summed", False)])
def test_robot_nodes_reproduce_the_batched_engine_with_zone_landmarks(mode, cap):
    """The SDZ on the team's start (zone trust off here: the nodes' helper sends no partner
    readings), neighbours inside the map inflated: one robot's process (its own rows'
    median claim) equals the batched engine to 1e-9, and the stage changes the estimates."""
    from resloc.cl import kernels
    from test_node import assert_same, hot_scenario, run_batched, run_nodes, simulate

    scenario = hot_scenario(15)
    params = dataclasses.replace(
        scenario.replace(
            **DEFENCES["full+redundancy+sequence"], **{"detector.zone_landmarks": True}
        ).cl_params(),
        update_mode=mode,
        redundancy_cap_fusion=cap,
    )
    assert params.zone_landmarks_map
    world, x0, P0, ws_list = simulate(scenario, trials=1, seed=4)
    filt = make_filter("ekf")
    with kernels.use_backend("auto"):
        batched = run_batched(filt, params, world, x0, P0, ws_list)
        by_robot = run_nodes(filt, params, world, x0, P0, ws_list)
        without = run_batched(
            filt, dataclasses.replace(params, zone_landmarks=False), world, x0, P0, ws_list
        )
    assert assert_same(batched, by_robot, ws_list, compiled=kernels.HAVE_NUMBA) > 0
    assert max(np.abs(b[0] - w[0]).max() for b, w in zip(batched, without, strict=True)) > 1e-6
