"""The compiled summed update (:mod:`resloc.cl.kernels_summed`).

Each case runs the default scenario (two trials batched, 34 robots) with the full defence
and the summed update through the compiled path and the numpy reference in lockstep, each
with its own estimates and memory, and a compromised robot (a lead on its broadcast
position growing every step, a jump every tenth step, a claimed covariance 100 times too
small) whose victims' measurements the detector discards in runs: the robot CUSUM alarms and
the recovery re-admits measurements with inflated covariances (both asserted). At every step
the compiled summed loop must have run, and the two agree to 1e-9 with identical decisions
(repairs included) and the same detector state."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world, start_states
from resloc.angles import wrap_angle
from resloc.cl import LinkBatch, correct, kernels, predict
from resloc.cl import kernels_rounds as rounds
from resloc.cl.backend import kernel_refusal
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters import make_filter
from test_kernels_defence import assert_same_stage_statistics
from test_kernels_detection import assert_same_statistics
from test_kernels_reciprocal import assert_matches_reference
from test_kernels_redundancy import links_of_one_step
from test_kernels_round_options import _path

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

FILTERS = {
    "ckf": make_filter("ckf"),
    "ukf": make_filter("ukf", 0.8, 2.0, 1.0),
    "ekf": make_filter("ekf"),
}
#: The compromised robot (batch index: one in each of the two trials).
LIARS = (5, 17 + 9)


def _params(defence: str, **changes):
    sc = default_scenario().replace(**DEFENCES[defence], **{"estimator.update_mode": "summed"})
    return replace(sc.cl_params(), **{"recovery_after": 4.0, **changes})


#: name -> (filter, CLParams, world seed). Seeds where no robot's estimate diverges: Algorithm
#: 1's summed update over-counts a robot's information when it fuses several links (every
#: touched covariance is repaired in the first steps), and with the liar some seeds (51, 53
#: for the CKF) drive a victim's covariance to 1e3..1e5, where the paths' rounding, ~1e-16
#: relative, is amplified past 1e-9 absolute (decisions stay identical).
CASES = {
    "ckf-full": ("ckf", _params("full"), 50),
    "ekf-full": ("ekf", _params("full"), 52),
    "ukf-every-stage": ("ukf", _params("full+redundancy+sequence+reciprocal"), 51),
    "ckf-paper": ("ckf", replace(_params("paper"), recovery=False), 54),
    # cached estimates: the first reception triggers, a delivered row is fused with the
    # transmitted estimate, an untriggered one with the cached estimate
    "ckf-cached-full": (
        "ckf",
        _params("full", neighbour_estimate="cached", update_without_transmission=True),
        50,
    ),
    "ukf-cached-last_sent": (
        "ukf",
        _params("paper", neighbour_estimate="cached", threshold_innovation="last_sent"),
        51,
    ),
}


def _lie(k: int, rows: np.ndarray, x_nb: np.ndarray, P_nb: np.ndarray) -> None:
    x_nb[rows, 0] += 0.002 * k + (0.4 if k % 10 == 3 else 0.0)
    P_nb[rows] *= 0.01


def lockstep(filt, params, steps: int, seed: int, start: int = 0, verdicts=None):
    """``steps`` steps through the compiled path and the reference (after ``start`` steps
    of the world alone); checks every step and yields the reference's outcome and memory.
    The compiled path must take the rows' moments in SIMD lanes (``rounds``) for the
    sigma-point filters from ``SUMMED_LANES_MIN_LINKS`` links on, else by its scalar
    moments (``row_order``). ``verdicts``: zone trust's (``test_kernels_zone.Verdicts``),
    the compiled rows' checked against the reference's."""
    from resloc.cl.kernels_summed import SUMMED_RUNS
    from resloc.cl.kernels_summed_lanes import SUMMED_LANES_MIN_LINKS

    world = default_world(2, seed, start)
    state = start_states(world, ("row_order", "numpy"))
    for k in range(steps):
        ws = world.step()
        lied = np.isin(ws.j, LIARS)
        res = {}
        for path, (x, P, memory) in state.items():
            with _path(path):
                xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
                x_nb, P_nb = xp[ws.j].copy(), Pp[ws.j].copy()
                _lie(k, lied, x_nb, P_nb)
                links = LinkBatch(
                    ws.i, ws.j, ws.z, x_nb, P_nb, ws.channel_ok, ws.risk_s, ws.risk_c,
                    ws.lambda2,
                )  # fmt: skip
                before = SUMMED_RUNS["summed"]
                loops = rounds.LOOP_RUNS.copy()
                res[path] = correct(filt, xp, Pp, links, params, memory)
                ran = SUMMED_RUNS["summed"] - before
                loops = rounds.LOOP_RUNS - loops
            assert ran == (path != "numpy"), "the compiled summed loop did not run"
            if path != "numpy":
                lanes = filt is not FILTERS["ekf"] and len(ws.i) >= SUMMED_LANES_MIN_LINKS
                assert loops == {"rounds" if lanes else "row_order": 1}, dict(loops)
            state[path] = (res[path][0], res[path][1], memory)
        assert_matches_reference(res["row_order"], res["numpy"])
        if verdicts is not None:
            assert len(verdicts.compiled) == 1, "the compiled zone stage did not run"
            reference = verdicts.reference_rows(ws.i, ws.j)
            np.testing.assert_array_equal(verdicts.compiled.pop(), reference)
            verdicts.seen.append(reference)
        a, b = state["row_order"][2], state["numpy"][2]
        if verdicts is None:
            assert_same_statistics(a, b)
            assert_same_stage_statistics(a, b)
        else:  # (the kernel's slots of withheld rows hold the 0 the reference never stored)
            from test_kernels_zone import assert_same_stage_state

            assert_same_stage_state(a, b)
        if params.neighbour_estimate == "cached":  # what each robot received
            np.testing.assert_array_equal(a.keys, b.keys)
            for name in ("x", "P", "last_norm"):
                np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-9)
        yield res["numpy"][2], b


@pytest.mark.parametrize("case", list(CASES))
def test_compiled_summed_update_equals_the_reference(case: str) -> None:
    name, params, seed = CASES[case]
    links = links_of_one_step()
    assert kernel_refusal(FILTERS[name], params, links) is None
    detected = fused = stale = 0
    alarmed = readmitted = False
    for out, memory in lockstep(FILTERS[name], params, 60, seed):
        detected += int(out.detected.sum())
        fused += int(out.fused.sum())
        stale += int((out.fused & ~out.delivered).sum())
        if params.robot_cusum:
            g = memory.stage_statistic("robot_cusum").values
            alarmed |= bool((g > params.robot_cusum_h).any())
        if params.recovery:
            readmitted |= bool((memory.stage_statistic("recovery_applied").values > 1.0).any())
    assert fused > 0 and (detected > 0 or not params.detector)
    if params.update_without_transmission:
        assert stale > 0, "no row was fused with a cached estimate"
    if params.robot_cusum:
        assert alarmed, "the robot CUSUM never alarmed"
    if params.recovery:
        assert readmitted, "the recovery never re-admitted a measurement"


def test_summed_with_other_fusions_falls_back_with_a_reason() -> None:
    links = links_of_one_step()
    for changes, word in (({"fusion": "ci"}, "'ci'"), ({"fusion": "split_ci"}, "split_ci")):
        refusal = kernel_refusal(FILTERS["ckf"], replace(_params("full"), **changes), links)
        assert refusal is not None and "summed" in refusal and word in refusal


@pytest.mark.parametrize("name", ["ckf", "ukf"])
def test_summed_lanes_give_every_rows_moments(name: str) -> None:
    """The lanes (:func:`~resloc.cl.kernels_summed_lanes.summed_moments_lanes`) take every
    row of a healthy batch (more rows than a chunk, a partial last chunk) and give the
    filter's moments (``SigmaPointFilter.relative_moments``) to 1e-12; a row whose
    covariance needs jitter is left to the scalar moments."""
    from resloc.cl.backend import filter_kernel_spec
    from resloc.cl.kernels_lanes import CHUNK
    from resloc.cl.kernels_summed_lanes import summed_moments_lanes

    world = default_world(40, 3)
    x, P = world.initial_estimates()
    rng = np.random.default_rng(0)
    x = x + rng.normal(scale=[0.3, 0.3, 0.5], size=x.shape)
    ws = world.step()
    E = len(ws.i)
    assert E > CHUNK and E % CHUNK
    li, lj = ws.i.astype(np.int64), ws.j.astype(np.int64)
    x_nb, P_nb = x[lj].copy(), P[lj].copy()
    P_nb[7] = 0.0  # no factor without jitter
    links = (li, ws.z, x_nb, P_nb, np.arange(E), ws.channel_ok, np.zeros(0), x_nb, P_nb,
             np.zeros(E, np.bool_))  # fmt: skip
    zh, s, done = np.empty((E, 2)), np.empty((E, 3)), np.empty(E, np.bool_)
    Pxz = np.empty((E, 3, 2))
    filt = FILTERS[name]
    summed_moments_lanes(x, P, links, tuple(filter_kernel_spec(filt)), zh, s, Pxz, done)
    assert not done[7] and done[np.arange(E) != 7].all()
    ok = done
    m = filt.relative_moments(x[li][ok], P[li][ok], x_nb[ok], P_nb[ok], np.zeros((2, 2)))
    np.testing.assert_allclose(zh[ok, 0], m.z_hat[:, 0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(wrap_angle(zh[ok, 1] - m.z_hat[:, 1]), 0.0, atol=1e-12)
    np.testing.assert_allclose(s[ok, 0], m.S[:, 0, 0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(s[ok, 1], m.S[:, 0, 1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(s[ok, 2], m.S[:, 1, 1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(Pxz[ok], m.Pxz, rtol=0, atol=1e-12)


#: Zone-aware trust in the summed loop (verdicts and the partners' position fixes at the
#: predicted estimates), from the zone's edge on (``test_kernels_zone.START``); a tight
#: gate and an early recovery re-admit substituted rows with ``f P_i``. Seeds where no
#: covariance diverges (with the tight gate, seeds 41, 42 and 47 drive a robot's to 1e1-1e5
#: within 20 steps, where the paths' rounding, ~1e-11 relative, passes 1e-9 absolute).
ZONE_CASES = {
    "ckf-zone+full+redundancy+sequence": ("ckf", _params("zone+full+redundancy+sequence"), 41),
    "ckf-zone+full-strict": (
        "ckf",
        _params("zone+full", rho=1.0, recovery_after=1.0, recovery_gate=6.0),
        43,
    ),
    "ukf-zone+full": ("ukf", _params("zone+full"), 42),
    "ekf-zone+full": ("ekf", _params("zone+full"), 43),
}


@pytest.mark.parametrize("case", list(ZONE_CASES))
def test_compiled_summed_update_with_zone_trust_equals_the_reference(case, monkeypatch):
    from resloc.cl.kernels_zone_verdicts import SUBSTITUTED, WITHHELD
    from test_kernels_zone import START, Verdicts

    name, params, seed = ZONE_CASES[case]
    assert kernel_refusal(FILTERS[name], params, links_of_one_step()) is None
    verdicts = Verdicts(monkeypatch)
    verdicts.seen = []
    fused_substituted = 0
    for out, _ in lockstep(FILTERS[name], params, 40, seed, START, verdicts):
        fused_substituted += int(out.fused[verdicts.seen[-1] == SUBSTITUTED].sum())
    seen = np.concatenate(verdicts.seen)
    assert (seen == WITHHELD).any(), "no robot inside the map without a partner reading"
    assert fused_substituted > 0, "no partner's position fix fused"
    if params.recovery_after <= 1.0:
        assert verdicts.readmitted_substituted > 0, "no fix re-admitted with f P_i"
