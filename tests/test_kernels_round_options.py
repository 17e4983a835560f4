"""The estimator options in the link rounds (:mod:`resloc.cl.kernels_round_stages`): CI and
split CI fusion, the link and mean-shift CUSUMs, the robot CUSUM and the recovery (with its
second pass on an inflated covariance), the gauge bookkeeping and the stealthy attacker.

Each case runs the default scenario (two trials batched, 34 robots) through three paths in
lockstep, each with its own estimates and memory: the rounds, the row-order loop and the
numpy reference. At every step the rounds must have run (no fallback), and the three agree
to 1e-9 with identical decisions, and so does every option's state (the CUSUM statistics,
the per-robot stores, split CI's independent parts, the gauge bookkeeping). A fallback in
the middle of a step must leave the stores as the row-order loop then needs them."""

from __future__ import annotations

import copy
from contextlib import contextmanager
from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world, runner_step, start_state, start_states
from resloc.cl import LinkBatch, LinkMemory, correct, kernels, predict
from resloc.cl import kernels_rounds as rounds
from resloc.cl.fusion_methods import fusion_strategy
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters import make_filter
from resloc.world.adversary import StealthKnowledge
from test_engine import assert_equivalent
from test_kernels_defence import assert_same_stage_statistics, readmissions  # noqa: F401
from test_kernels_detection import NIS_RHO, assert_same_statistics
from test_kernels_fusion import ci_weights_seen  # noqa: F401
from test_kernels_rounds import assert_same_loops
from test_kernels_tamper import attacker

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

FILTERS = {"ckf": make_filter("ckf"), "ukf": make_filter("ukf", 0.8, 2.0, 1.0)}
PATHS = ("rounds", "row_order", "numpy")
#: A tight gate and an early, generous recovery: rejection runs, then re-admissions with an
#: inflated covariance, within a short run.
STRICT = dict(rho=1.2, recovery_after=2.0, recovery_gate=3.0)
CUSUMS = dict(detector_norm="nis", rho=NIS_RHO, cusum=True, cusum_k=2.5, cusum_h=6.0,
              mean_cusum=True, mean_cusum_h=3.0)  # fmt: skip


def _params(defence: str | None = None, **changes):
    sc = default_scenario()
    if defence is not None:
        sc = sc.replace(**DEFENCES[defence])
    return replace(sc.cl_params(), **changes)


#: name -> (filter, CLParams, stealthy attacker's knowledge or None)
CASES = {
    "ci-trace": ("ckf", _params(fusion="ci"), None),
    "ci-det": ("ukf", _params(fusion="ci", ci_criterion="det"), None),
    "split_ci": ("ckf", _params(fusion="split_ci"), None),
    "cusums": ("ukf", _params(**CUSUMS), None),
    "full-strict": ("ckf", _params("full", **STRICT), None),
    "full-strict-ci": ("ckf", _params("full", fusion="ci", **STRICT), None),
    "full-strict-split_ci": ("ckf", _params("full", fusion="split_ci", **STRICT), None),
    "gauge": ("ckf", _params(fusion="gauge"), None),
    "gauge-full-strict": ("ukf", _params("full", fusion="gauge", **STRICT), None),
    "stealthy-cusums": ("ckf", _params(**CUSUMS), StealthKnowledge.FULL),
    "resilient-full": ("ckf", _params("full", fusion="gauge", **CUSUMS), StealthKnowledge.FULL),
    # cached neighbour estimates (kernels_round_cached): the first pass with j's last
    # received estimate, a delivered link's second pass with the transmitted one
    "cached": ("ckf", _params(neighbour_estimate="cached"), None),
    "cached-uwt-full-strict": (
        "ckf",
        _params("full", neighbour_estimate="cached", update_without_transmission=True, **STRICT),
        None,
    ),
    "cached-last_sent-split_ci": (
        "ukf",
        _params(neighbour_estimate="cached", threshold_innovation="last_sent", fusion="split_ci"),
        None,
    ),
    "cached-ci-stealthy": (
        "ckf",
        _params(neighbour_estimate="cached", fusion="ci", **CUSUMS),
        StealthKnowledge.FULL,
    ),
}


@contextmanager
def _path(path: str):
    """The compiled correction by the rounds or the row-order loop (whatever the number of
    links), or the numpy reference."""
    saved = rounds.ROUNDS_MIN_LINKS
    rounds.ROUNDS_MIN_LINKS = 1 if path == "rounds" else 10**18
    try:
        with kernels.use_backend("numpy" if path == "numpy" else "numba"):
            yield
    finally:
        rounds.ROUNDS_MIN_LINKS = saved


def assert_same_state(params, a: LinkMemory, b: LinkMemory) -> None:
    """Every option's state after a step is the same in ``a`` and ``b``."""
    assert_same_statistics(a, b)
    assert_same_stage_statistics(a, b)
    if params.neighbour_estimate == "cached" or params.threshold_innovation == "last_sent":
        np.testing.assert_array_equal(a.keys, b.keys)
        np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.P, b.P, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.last_norm, b.last_norm, rtol=0, atol=1e-9)
    if params.fusion == "split_ci":
        np.testing.assert_allclose(a.independent, b.independent, rtol=0, atol=1e-9)
    if params.fusion == "gauge":
        ga, gb = a.joint, b.joint
        np.testing.assert_allclose(ga.robot_G(), gb.robot_G(), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(ga.A, gb.A, rtol=0, atol=1e-9)
        np.testing.assert_allclose(ga.noise, gb.noise, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(ga.acks()[0], gb.acks()[0])
        np.testing.assert_allclose(ga.acks()[1], gb.acks()[1], rtol=0, atol=1e-9)


def lockstep_three_paths(filt, params, steps: int, seed: int, knowledge=None):
    """``steps`` steps of the default scenario through the rounds, the row-order loop and
    the reference side by side (with the stealthy attacker on 40% of the links when
    ``knowledge`` is given); checks every step (see the module docstring) and yields the
    reference's outcome and the hit links."""
    world = default_world(2, seed)
    rng = np.random.default_rng(seed)
    fusion = fusion_strategy(params.fusion)
    state = start_states(world, PATHS, fusion)
    for _ in range(steps):
        ws = world.step()
        hit = rng.random(len(ws.i)) < 0.4
        res = {}
        for path, (x, P, memory) in state.items():
            with _path(path):
                xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
                Pp = fusion.predict(memory, x, ws.u_meas, world.dt, params, Pp)
                tamper = None
                if knowledge is not None:
                    tamper = attacker(ws, params, (1.0, 0.0), knowledge, hit)
                links = LinkBatch(
                    ws.i, ws.j, ws.z, xp[ws.j], Pp[ws.j], ws.channel_ok, ws.risk_s,
                    ws.risk_c, ws.lambda2, tamper=tamper, **fusion.link_fields(memory, ws.j),
                )  # fmt: skip
                before = rounds.LOOP_RUNS.copy()
                res[path] = correct(filt, xp, Pp, links, params, memory)
                ran = rounds.LOOP_RUNS - before
                fusion.exchange(memory, ws.i, ws.j)
            if path != "numpy":
                assert ran == {path: 1}, f"expected the {path} loop, ran {dict(ran)}"
            state[path] = (res[path][0], res[path][1], memory)
        assert_same_loops(res["rounds"], res["row_order"])
        assert_equivalent(res["rounds"], res["numpy"])
        memories = {path: s[2] for path, s in state.items()}
        assert_same_state(params, memories["rounds"], memories["row_order"])
        assert_same_state(params, memories["rounds"], memories["numpy"])
        yield res["numpy"][2], hit


@pytest.mark.parametrize("case", list(CASES))
def test_rounds_run_every_option_as_the_row_order_loop_and_the_reference(
    case, readmissions, ci_weights_seen  # noqa: F811
):  # fmt: skip
    name, params, knowledge = CASES[case]
    fused = detected = moved = stale = 0
    seed = 21 + list(CASES).index(case)
    for out, hit in lockstep_three_paths(FILTERS[name], params, 60, seed, knowledge):
        fused += int(out.fused.sum())
        detected += int(out.detected.sum())
        moved += int(out.fused[hit].sum())
        stale += int((out.fused & ~out.delivered).sum())
    assert fused > 0
    if params.update_without_transmission:
        assert stale > 0, "no link was fused with a cached estimate"
    if params.detector:
        assert detected > 0, "no measurement was rejected"
    if params.fusion in ("ci", "split_ci"):
        w = np.concatenate(ci_weights_seen)
        assert (w < 1.0).any() and (w == 1.0).any(), "both CI weight branches must run"
    if params.recovery and params.rho == STRICT["rho"]:
        assert readmissions["inflated"] > 0, "no re-admission with an inflated covariance"
    if knowledge is not None:
        assert moved > 0, "no falsified measurement was fused"


def _late_link(i: np.ndarray) -> int:
    """The row of the link with the highest rank among its observer's links (the rounds
    reach it last, after the options' stores have changed)."""
    rank = np.arange(len(i)) - np.searchsorted(i, i, side="left")
    return int(np.argmax(rank))


@pytest.mark.parametrize("fusion", ["gauge", "split_ci"])
def test_a_fallback_puts_the_options_stores_back(fusion: str) -> None:
    """A measured bearing out of range in the last round: the rounds give way to the
    row-order loop after the earlier rounds wrote the stores. The result and every store
    must be those of the row-order loop alone, from the same memory."""
    params = _params("full", fusion=fusion, **STRICT)
    filt = FILTERS["ckf"]
    world = default_world(2, 5)
    strategy = fusion_strategy(fusion)
    x, P, memory = start_state(world, strategy)
    with _path("rounds"):
        for _ in range(25):  # statistics away from zero
            ws = world.step()
            x, P, _ = runner_step(filt, x, P, ws, world.dt, params, strategy, memory)
        ws = world.step()
        xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
        Pp = strategy.predict(memory, x, ws.u_meas, world.dt, params, Pp)
    z = ws.z.copy()
    z[_late_link(ws.i), 1] = 7.5
    assert (memory.cusum.values > 0).any()
    results = {}
    for path in ("rounds", "row_order"):
        mem = copy.deepcopy(memory)
        links = LinkBatch(
            ws.i, ws.j, z, xp[ws.j], Pp[ws.j], ws.channel_ok, ws.risk_s, ws.risk_c,
            ws.lambda2, **strategy.link_fields(mem, ws.j),
        )  # fmt: skip
        before = rounds.LOOP_RUNS.copy()
        with _path(path):
            results[path] = (correct(filt, xp, Pp, links, params, mem), mem)
        ran = rounds.LOOP_RUNS - before
        expected = {"rounds_fallback": 1, "row_order": 1} if path == "rounds" else {path: 1}
        assert ran == expected, dict(ran)
    (fell_back, mem_a), (row_order, mem_b) = results["rounds"], results["row_order"]
    assert_same_loops(fell_back, row_order, tol=0.0)
    assert_same_state(params, mem_a, mem_b)
