"""The compiled ``gauge`` fusion (the kernel's update plus the gauge bookkeeping of
:mod:`resloc.cl.kernels_gauge`) against the numpy reference over multi-step runs: same
estimates and decisions to 1e-9, same gauge covariance ``G`` and reported covariances."""

from __future__ import annotations

import pickle
from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world, runner_step, start_states
from resloc.cl import LinkMemory, correct, kernels
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.kernels_bookkeeping import COMPILED_BOOKKEEPING
from resloc.experiments.config import default_scenario
from resloc.filters import make_filter
from test_engine import assert_equivalent

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

FILTERS = {
    "ckf": make_filter("ckf"),
    "ukf": make_filter("ukf", 0.8, 2.0, 1.0),
    "ekf": make_filter("ekf"),
}


def run_gauge(
    filt, params, steps: int, seed: int, trials: int = 2, rounds=None, pickle_at=None
) -> None:
    """The default scenario (``trials`` batched) with gauge fusion by both paths; compares the
    correction, ``G`` as every robot knows it and the reported covariances at every step
    (``pickle_at``: the compiled path's memory goes through a pickle after that step)."""
    world = default_world(trials, seed)
    fusion = fusion_strategy("gauge")
    state = start_states(world, ("numba", "numpy"), fusion, rounds=rounds)
    fused = 0
    for k in range(steps):
        if k == pickle_at:  # the compiled step arrays are views of one array: kept as such
            x, P, memory = state["numba"]
            state["numba"] = (x, P, pickle.loads(pickle.dumps(memory)))
        ws = world.step()
        res = {}
        for backend, (x, P, memory) in state.items():
            with kernels.use_backend(backend):
                res[backend] = runner_step(filt, x, P, ws, world.dt, params, fusion, memory)
            state[backend] = (res[backend][0], res[backend][1], memory)
        assert_equivalent(res["numba"], res["numpy"])
        fast, ref = state["numba"][2].joint, state["numpy"][2].joint
        np.testing.assert_allclose(fast.robot_G(), ref.robot_G(), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(fast.A, ref.A, rtol=0, atol=1e-9)
        np.testing.assert_allclose(fast.noise, ref.noise, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(fast.acks()[0], ref.acks()[0])
        np.testing.assert_allclose(fast.acks()[1], ref.acks()[1], rtol=0, atol=1e-9)
        x_f, x_r = state["numba"][0], state["numpy"][0]
        np.testing.assert_allclose(  # compiled (the strategy's dispatch) against the spec
            fusion.reported(state["numba"][2], x_f, state["numba"][1]),
            ref.reported(x_r, state["numpy"][1]),
            rtol=1e-9,
            atol=1e-12,
        )
        fused += int(res["numpy"][2].fused.sum())
    assert fused > 0
    assert np.abs(state["numpy"][2].joint.robot_G()).max() > 0
    # The once-per-step parts: compiled (prediction and finish of every step) with exact sums.
    assert state["numpy"][2].joint.compiled_steps == 0
    assert state["numba"][2].joint.compiled_steps == (2 * steps if rounds is None else 0)
    assert state["numba"][2].joint.compiled_reports == steps  # consensus sums too
    assert state["numpy"][2].joint.compiled_reports == 0


@pytest.mark.parametrize("name", list(FILTERS))
def test_compiled_gauge_matches_reference_over_a_run(name: str) -> None:
    params = replace(default_scenario().cl_params(), fusion="gauge")
    run_gauge(FILTERS[name], params, 40, seed=7)


def test_compiled_gauge_continues_exactly_after_a_pickle() -> None:
    params = replace(default_scenario().cl_params(), fusion="gauge")
    run_gauge(FILTERS["ckf"], params, 12, seed=3, trials=1, pickle_at=5)


@pytest.mark.parametrize("seed", [1, 2])
def test_compiled_gauge_with_consensus_sums_and_cusums(seed: int) -> None:
    """Per-robot ``G`` by consensus, with the NIS gate and both CUSUMs (the resilient
    configuration's estimator), several seeds."""
    params = replace(
        default_scenario().cl_params(), fusion="gauge", detector_norm="nis", rho=3.03,
        cusum=True, mean_cusum=True,
    )  # fmt: skip
    run_gauge(FILTERS["ckf"], params, 40, seed=seed, trials=1, rounds=3)


def test_every_compiled_fusion_method_has_its_bookkeeping() -> None:
    from resloc.cl.fusion_methods import FUSION_STRATEGIES
    from resloc.cl.kernels_fusion import KERNEL_UPDATES

    compiled = [s for s in FUSION_STRATEGIES.values() if s.compiled]
    assert {s.kernel_bookkeeping for s in compiled} <= set(COMPILED_BOOKKEEPING)
    assert {s.kernel_update for s in compiled} <= set(KERNEL_UPDATES)


def test_gauge_without_bookkeeping_goes_to_the_reference_which_raises() -> None:
    from test_engine import random_batch

    x, P, links = random_batch(3)
    params = replace(default_scenario().cl_params(), fusion="gauge")
    with kernels.use_backend("numba"):
        assert kernels.fast_correct(FILTERS["ckf"], x, P, links, params, LinkMemory(40)) is None
        with pytest.raises(ValueError, match=r"memory\.joint"):
            correct(FILTERS["ckf"], x, P, links, params, LinkMemory(40))
