"""The lock-out floor: a robot whose detector discards most of its links raises its covariance."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from resloc.cl.detection_lockout import (
    Lockout,
    applied_lockout_factors,
    discard_share,
    lockout_floor,
    record_lockout,
)
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.errors import ConfigError

PARAMS = CLParams(lockout_share=0.5, lockout_window=4.0, lockout_floor_std=0.01)
N = 4
X = np.zeros((N, 3))


class _Batch(SimpleNamespace):
    def __len__(self):
        return len(self.i)


def _batch(channel_ok=None):
    """Robot 0 observes 1, 2, 3; robot 1 observes 0 and 2; robot 3 only sends."""
    i, j = np.array([0, 0, 0, 1, 1]), np.array([1, 2, 3, 0, 2])
    ok = np.ones(len(i), bool) if channel_ok is None else np.asarray(channel_ok, bool)
    return _Batch(i=i, j=j, channel_ok=ok)


def _P():
    """Robot 0 at 2 mm, robot 1 at 30 mm (wider than the floor), robots 2-3 at 1 mm."""
    P = np.tile(np.eye(3) * 1e-4, (N, 1, 1))
    P[0, :2, :2] = np.diag([0.002**2, 0.001**2])
    P[1, :2, :2] = np.eye(2) * 0.03**2
    P[2:, :2, :2] = np.eye(2) * 0.001**2
    return P


def _outcome(detected):
    return SimpleNamespace(detected=np.asarray(detected, bool))


def test_the_share_is_per_observer_over_its_judged_links():
    robots, share = discard_share(
        np.array([0, 0, 0, 1, 1, 2]),
        np.array([1, 1, 0, 0, 1, 1], bool),
        np.array([1, 1, 1, 1, 0, 0], bool),
    )
    assert robots.tolist() == [0, 1]  # robot 2's only link was not judged
    assert share == pytest.approx([2 / 3, 0.0])


def test_a_robot_discarding_most_of_its_links_is_raised_to_the_floor_then_released():
    """Robot 0 discards two of its three links for eight steps, then none: its weighted
    share (weight 1/4) climbs to 2/3 (1 - 0.75^k), above 0.5 from the fifth step; its prior
    is raised to 10 mm while the share is above, and released once it has fallen back."""
    memory = LinkMemory(N)
    factors, shares = [], []
    weight = 1.0 / PARAMS.lockout_window
    expected = 0.0
    for k in range(14):
        P = _P()
        used = lockout_floor(PARAMS, memory, _batch(), P)
        factors.append(used[:, 0, 0] / P[:, 0, 0])
        if used is not P:
            # the whole 3 x 3 block by one factor, the larger diagonal at the floor
            assert np.allclose(used[0], P[0] * factors[-1][0])
            assert max(used[0, 0, 0], used[0, 1, 1]) == pytest.approx(0.01**2)
        bad = k < 8
        record_lockout(PARAMS, memory, _batch(), _outcome([bad, bad, False, False, False]), X)
        expected = (1 - weight) * expected + weight * (2 / 3 if bad else 0.0)
        state = memory.stage_statistic("lockout", width=2)
        shares.append(state.get(np.array([0]), np.array([0]))[0, 0])
        assert shares[-1] == pytest.approx(expected)
    factors = np.array(factors)
    above = np.array([0.0, *shares[:-1]]) > 0.5  # the floor reads the share before the step
    assert above.any() and not above.all()
    assert factors[above, 0] == pytest.approx(25.0)  # (10 mm / 2 mm)^2
    assert (factors[~above, 0] == 1.0).all()
    assert (factors[:, 1:] == 1.0).all()  # robot 1 fuses everything; 2, 3 do not observe


def test_jammed_links_are_no_verdict():
    memory = LinkMemory(N)
    for _ in range(30):
        # robot 0's two discarded links are jammed: its judged link passes
        record_lockout(PARAMS, memory, _batch([0, 0, 1, 1, 1]), _outcome([1, 1, 0, 0, 0]), X)
    P = _P()
    assert lockout_floor(PARAMS, memory, _batch(), P) is P


def test_off_by_default_and_without_memory():
    P = _P()
    memory = LinkMemory(N)
    record_lockout(CLParams(), memory, _batch(), _outcome([1, 1, 1, 1, 1]), X)
    assert lockout_floor(CLParams(), memory, _batch(), P) is P
    assert lockout_floor(PARAMS, None, _batch(), P) is P
    assert not Lockout().active(CLParams()) and Lockout().active(PARAMS)


def test_the_attacker_sees_the_raised_covariances():
    from resloc.world.attackers.outvoted import widened

    for params in (PARAMS, replace(PARAMS, startup_steps=2), replace(PARAMS, witness=True)):
        memory = LinkMemory(N)
        raised = []
        for _ in range(12):
            P = _P()
            used = lockout_floor(params, memory, _batch(), P)
            assert np.allclose(widened(P, memory, params), used)
            raised.append(bool((applied_lockout_factors(memory, N) > 1.0).any()))
            record_lockout(params, memory, _batch(), _outcome([1, 1, 1, 0, 0]), X)
        assert raised[0] is False and raised[-1] is True


def test_the_compiled_path_takes_the_stage():
    from resloc.cl.backend import _params_refusal

    assert Lockout.compiled
    assert _params_refusal(PARAMS) is None


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("detector.lockout_share", -0.1),
        ("detector.lockout_share", 1.5),
        ("detector.lockout_window", 0.5),
        ("detector.lockout_floor_std", 0.0),
    ],
)
def test_bad_options_are_one_line_errors(field, value):
    from resloc.experiments.config import default_scenario

    with pytest.raises(ConfigError) as err:
        default_scenario().replace(**{field: value})
    assert field in str(err.value) and "\n" not in str(err.value)
    sc = default_scenario().replace(**{"detector.lockout_share": 0.5})
    assert sc.cl_params().lockout_share == 0.5


def _displaced_run(params, backend, steps=25):
    """Robot 0 of the six-robot scene believes itself 30 mm off with a 1 mm covariance (a
    robot the liars pulled, then shrank); its five neighbours are honest and exact. Its
    NIS gate discards them all; the run corrects it ``steps`` times (no motion)."""
    import dataclasses

    import resloc.cl.step
    from resloc.cl import kernels
    from resloc.cl.links import LinkBatch
    from resloc.filters.base import make_filter
    from resloc.models.measurement import range_bearing
    from test_defence_redundancy import POSE

    i, j = np.zeros(5, int), np.arange(1, 6)
    z = range_bearing(POSE[i], POSE[j])
    x = POSE.copy()
    x[0, :2] += [0.03, 0.0]
    P = np.tile(np.diag([1e-6, 1e-6, 1e-4]), (6, 1, 1))
    memory = LinkMemory(6)
    filt = make_filter("ckf")
    compiled = []
    for _ in range(steps):
        links = LinkBatch.from_predicted(
            i, j, z, x, P, np.ones(5, bool), np.zeros(6), np.zeros(6), np.ones(6)
        )
        links = dataclasses.replace(links, neighbours=None)
        with kernels.use_backend(backend):
            x_new, P_new, out = resloc.cl.step.correct(filt, x, P, links, params, memory)
        compiled.append(out.compiled)
        x, P = x_new.copy(), P_new.copy()
        P[1:] = np.diag([1e-6, 1e-6, 1e-4])  # the neighbours stay as they are
        x[1:] = POSE[1:]
    return x, P, compiled


def test_a_locked_out_robot_is_pulled_back_on_both_paths():
    """Without the stage the displaced robot's gate discards most honest neighbours and it
    stays more than 25 mm off; with it, its share passes the threshold, its prior is raised
    to 10 mm, its neighbours are admitted and pull it back. The compiled path gives the reference's
    estimates (1e-9), and ran."""
    from resloc.cl import kernels

    gate = CLParams(trigger=False, detector_norm="nis", rho=float(np.sqrt(13.8)))
    on = replace(gate, lockout_share=0.5, lockout_window=4.0, lockout_floor_std=0.01)
    x_off, _, _ = _displaced_run(gate, "numpy")
    x_on, P_on, _ = _displaced_run(on, "numpy")
    # robot 0's true position is the origin: one neighbour's bearing-poor link passes now
    # and then (a partial lock-out), the others never
    assert np.hypot(*x_off[0, :2]) > 0.025
    assert np.hypot(*x_on[0, :2]) < 0.001  # pulled back
    if kernels.HAVE_NUMBA:
        x_fast, P_fast, compiled = _displaced_run(on, "numba")
        assert all(compiled)
        np.testing.assert_allclose(x_fast, x_on, rtol=0, atol=1e-9)
        np.testing.assert_allclose(P_fast, P_on, rtol=0, atol=1e-9)


def test_the_liars_answer_keeps_a_victim_under_the_threshold():
    """``under``: a liar sends its honest estimate to a victim whose share has reached
    ``under`` (read from the stage's store), and its largest accepted lie to the others."""
    from resloc.cl.cusum import chi2_gate
    from resloc.world.attackers import make_attacker
    from test_defence_redundancy import _compromised_scene

    params = CLParams(detector_norm="nis", rho=float(np.sqrt(chi2_gate(1e-3))), lockout_share=0.5)
    links, step, z_hat, S = _compromised_scene(params)
    liar = 4  # robot 5 -> robot 0
    adv = make_attacker("compromised", robots=1, under=0.4)
    for share, lies in ((0.1, True), (0.45, False)):
        memory = LinkMemory(6)
        memory.stage_statistic("lockout", width=2).set(
            np.array([0]), np.array([0]), np.array([[share, 1.0]])
        )
        sent = adv.attack(links, step, params, memory).tamper(np.arange(5), z_hat, S)
        assert (not np.allclose(sent[liar], links.z[liar])) == lies
        np.testing.assert_array_equal(sent[:liar], links.z[:liar])
    # off (the default), the lie goes out whatever the share
    memory = LinkMemory(6)
    memory.stage_statistic("lockout", width=2).set(
        np.array([0]), np.array([0]), np.array([[0.9, 1.0]])
    )
    sent = make_attacker("compromised", robots=1).attack(links, step, params, memory)
    assert not np.allclose(sent.tamper(np.arange(5), z_hat, S)[liar], links.z[liar])
    with pytest.raises(ValueError, match="parameter under"):
        make_attacker("compromised", under=1.5)


def test_readings_zone_trust_withholds_are_no_verdict():
    """Robot 0's estimate is inside the zone map: its withheld readings do not raise its
    share (counted, every robot crossing a zone would raise its floor); robot 1 is outside
    and its discards count."""
    params = replace(PARAMS, zone_trust=True, zone_trust_map=((0.0, 0.0, 1.0),))
    x = np.zeros((N, 3))
    x[1, :2] = [5.0, 0.0]
    memory = LinkMemory(N)
    for _ in range(10):
        record_lockout(params, memory, _batch(), _outcome([1, 1, 1, 1, 1]), x)
    shares = memory.stage_statistic("lockout", width=2).get(np.arange(2), np.arange(2))[:, 0]
    assert shares[0] == 0.0 and shares[1] > 0.5


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_robot_nodes_reproduce_the_batched_engine_with_the_stage(backend):
    """In one robot's process the stage keeps its own share from its own links: the nodes
    give the batched engine's estimates and decisions, floors raised on the way."""
    from resloc.cl import kernels
    from resloc.filters.base import make_filter
    from test_node import assert_same, hot_scenario, run_batched, run_nodes, simulate

    if backend == "numba" and not kernels.HAVE_NUMBA:
        pytest.skip("numba not installed")
    scenario = hot_scenario(30)
    params = replace(
        scenario.cl_params(),
        detector_norm="nis",
        rho=2.0,  # a tight gate: many discards, so floors rise
        lockout_share=0.3,
        lockout_window=2.0,
    )
    world, x0, P0, ws_list = simulate(scenario, trials=1, seed=3)
    filt = make_filter("ckf")
    raised = []
    original = lockout_floor

    def spy(params, memory, links, P):
        out = original(params, memory, links, P)
        raised.append(out is not P)
        return out

    import resloc.cl.step as step_module

    step_module.lockout_floor = spy
    try:
        with kernels.use_backend(backend):
            batched = run_batched(filt, params, world, x0, P0, ws_list)
            by_robot = run_nodes(filt, params, world, x0, P0, ws_list)
    finally:
        step_module.lockout_floor = original
    assert assert_same(batched, by_robot, ws_list, compiled=backend == "numba") > 0
    assert any(raised)


def test_the_liars_do_not_floor_themselves():
    """A compromised robot runs its own software: the attacker marks its robots and no
    stage widens their covariance (a floor would widen their claims and weaken their lies);
    what the attacker reads of the step's covariances says so."""
    from resloc.cl.detection_widening import keep_exempt
    from resloc.world.attackers import make_attacker
    from resloc.world.attackers.outvoted import widened
    from test_defence_redundancy import _compromised_scene

    params = replace(PARAMS, startup_steps=3)
    memory = LinkMemory(N)
    for _ in range(10):
        record_lockout(params, memory, _batch(), _outcome([1, 1, 1, 1, 1]), X)
    P = _P()
    floored = lockout_floor(params, memory, _batch(), P)
    assert floored[0, 0, 0] > P[0, 0, 0]
    exempt = np.array([True, False, False, False])
    kept = keep_exempt(floored, P, exempt)
    np.testing.assert_array_equal(kept[0], P[0])
    np.testing.assert_array_equal(kept[1:], floored[1:])
    assert keep_exempt(floored, P, None) is floored
    assert keep_exempt(P, P, exempt) is P
    memory.exempt = exempt
    np.testing.assert_array_equal(widened(P, memory, params), kept)
    # the compromised attacker marks its robots (robot 5 of a team of six)
    scene_params = replace(PARAMS, detector_norm="nis", rho=3.7)
    links, step, _, _ = _compromised_scene(scene_params)
    memory = LinkMemory(6)
    make_attacker("compromised", robots=1).attack(links, step, scene_params, memory)
    assert memory.exempt.tolist() == [False] * 5 + [True]


def test_the_correction_skips_the_stages_for_exempt_robots():
    """Robot 0 fuses five neighbours with a start-up floor on: marked exempt, its posterior
    is the one without the stage (on both paths)."""
    import dataclasses

    import resloc.cl.step
    from resloc.cl import kernels
    from resloc.filters.base import make_filter
    from test_defence_redundancy import POSE, _compromised_scene

    base = CLParams(trigger=False, detector=False)
    links, *_ = _compromised_scene(base)
    links = dataclasses.replace(links, neighbours=None)
    P = np.tile(np.diag([1e-6, 1e-6, 1e-4]), (6, 1, 1))
    filt = make_filter("ckf")
    on = replace(base, startup_steps=3, startup_floor_std=0.01)
    backends = ("numpy", "numba") if kernels.HAVE_NUMBA else ("numpy",)
    for backend in backends:
        with kernels.use_backend(backend):
            off = resloc.cl.step.correct(filt, POSE.copy(), P, links, base, LinkMemory(6))
            memory = LinkMemory(6)
            memory.exempt = np.array([True] + [False] * 5)
            skipped = resloc.cl.step.correct(filt, POSE.copy(), P, links, on, memory)
            floored = resloc.cl.step.correct(filt, POSE.copy(), P, links, on, LinkMemory(6))
        np.testing.assert_allclose(skipped[1], off[1], rtol=0, atol=1e-15)
        assert floored[1][0, 0, 0] > 5.0 * off[1][0, 0, 0]
