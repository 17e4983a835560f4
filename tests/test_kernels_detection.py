"""The compiled detector stages with per-link state (NIS gate, NIS CUSUM, mean-shift CUSUM)
against the numpy reference, over multi-step runs: same estimates and decisions to 1e-9 at
every step, and the same per-link memory (the CUSUM statistics) after every step."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world
from resloc.cl import CLParams, LinkMemory, correct, kernels
from resloc.cl.backend import kernel_refusal
from resloc.errors import NumericalError
from resloc.experiments.config import default_scenario
from resloc.filters import make_filter
from test_engine import assert_equivalent, lockstep_both_backends, random_batch, run_both

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

FILTERS = {
    "ckf": make_filter("ckf"),
    "ukf": make_filter("ukf", 0.8, 2.0, 1.0),
    "ekf": make_filter("ekf"),
}
NIS_RHO = 3.0348542587702925  # sqrt(chi2.isf(0.01, 2))

DETECTOR_CASES = {
    "nis-gate": dict(detector_norm="nis", rho=NIS_RHO),
    "cusum": dict(detector_norm="nis", rho=NIS_RHO, cusum=True, cusum_k=2.5, cusum_h=6.0),
    "cusum-euclidean-capped": dict(rho=1.0, cusum=True, cusum_k=2.5, cusum_h=4.0, cusum_cap=5.0),
    "mean-cusum": dict(detector_norm="nis", rho=NIS_RHO, mean_cusum=True, mean_cusum_h=3.0),
    "mean-cusum-no-gate": dict(detector=False, mean_cusum=True, mean_cusum_h=3.0),
    "all": dict(
        detector_norm="nis", rho=NIS_RHO, cusum=True, cusum_k=2.5, cusum_h=6.0,
        mean_cusum=True, mean_cusum_h=3.0,
    ),
}  # fmt: skip


def assert_same_statistics(fast: LinkMemory, ref: LinkMemory) -> None:
    for name in ("cusum", "mean_cusum"):
        a, b = getattr(fast, name), getattr(ref, name)
        np.testing.assert_array_equal(a.keys, b.keys, err_msg=name)
        np.testing.assert_allclose(a.values, b.values, rtol=0, atol=1e-9, err_msg=name)


def run_scenario(filt, params, steps: int, seed: int):
    """``steps`` steps of the default scenario (two trials batched, its SDZ attacks) by both
    paths, each carrying its own estimates and memory; compares every step. Returns the
    reference's detections per step and the final memories."""
    world = default_world(2, seed)
    detected, memories = 0, {}
    for res, memories in lockstep_both_backends(world, filt, params, steps):
        assert_same_statistics(memories["numba"], memories["numpy"])
        detected += int(res["numpy"][2].detected.sum())
    return detected, memories["numba"], memories["numpy"]


@pytest.mark.parametrize("case", list(DETECTOR_CASES))
@pytest.mark.parametrize("name", list(FILTERS))
def test_compiled_detector_stages_match_reference_over_a_run(name: str, case: str) -> None:
    base = default_scenario().cl_params()
    params = replace(base, **DETECTOR_CASES[case])
    assert kernel_refusal(FILTERS[name], params, random_batch(0)[2]) is None
    seed = 1 + list(DETECTOR_CASES).index(case)
    detected, _, ref = run_scenario(FILTERS[name], params, 120, seed)
    if params.cusum:
        assert (ref.cusum.values > 0).any()
    if params.mean_cusum:
        assert (ref.mean_cusum.values > 0).any()
    assert detected > 0


def test_the_cusums_discard_beyond_the_gate() -> None:
    """The multi-step cases exercise the alarms, not only the statistics: with the CUSUMs the
    detector discards more than the gate alone on the same run."""
    base = replace(default_scenario().cl_params(), **DETECTOR_CASES["nis-gate"])
    gate_only, _, _ = run_scenario(FILTERS["ckf"], base, 120, 3)
    with_cusums, _, _ = run_scenario(FILTERS["ckf"], replace(base, **DETECTOR_CASES["all"]), 120, 3)
    assert with_cusums > gate_only


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_per_robot_cusum_gains_over_repeated_steps(seed: int) -> None:
    """Per-robot CUSUM gains, outlier-heavy random batches, the same links for 25 steps (the
    statistics accumulate and alarm); the estimates feed back from each step."""
    x, P, links = random_batch(seed, outliers=0.3)
    rng = np.random.default_rng(seed)
    B = len(x)
    params = CLParams(
        range_std=0.02, bearing_std=0.03, rho=1.0, alpha=0.05, cusum=True,
        cusum_k=rng.uniform(1.5, 3.0, B), cusum_h=rng.uniform(2.0, 8.0, B), mean_cusum=True,
        mean_cusum_k=rng.uniform(0.3, 0.8, B), mean_cusum_h=rng.uniform(1.0, 4.0, B),
    )  # fmt: skip
    memories = (LinkMemory(B), LinkMemory(B))
    xs = {"numba": (x, P), "numpy": (x, P)}
    discarded = 0
    for _ in range(25):
        z = links.z + rng.normal(size=links.z.shape) * [0.05, 0.05]
        step = replace(links, z=z)
        fast, ref = run_both(FILTERS["ckf"], *xs["numpy"], step, params, memories)
        assert_equivalent(fast, ref)
        assert_same_statistics(*memories)
        discarded += int((ref[2].detected & ~(ref[2].norm > 1.0)).sum())
        xs = {"numba": fast[:2], "numpy": ref[:2]}
    assert discarded > 0, "no CUSUM discarded a measurement the gate passed"


def test_a_failed_kernel_step_leaves_the_statistics_untouched() -> None:
    """On a covariance that is not positive definite the kernel gives up; the memory must be
    what the reference then starts from (the reference raises here)."""
    params = CLParams(range_std=0.02, bearing_std=0.03, rho=1.0, cusum=True, mean_cusum=True)
    memory = LinkMemory(40)
    x, P, links = random_batch(4)
    with kernels.use_backend("numba"):
        assert correct(FILTERS["ckf"], x, P, links, params, memory)[2].compiled
        keys = memory.cusum.keys.copy(), memory.mean_cusum.keys.copy()
        values = memory.cusum.values.copy(), memory.mean_cusum.values.copy()
        x2, P2, links2 = random_batch(5)  # new links: the kernel would insert slots
        P2[links2.i[-1]] = np.nan  # the last observer fails after the others were processed
        assert kernels.fast_correct(FILTERS["ckf"], x2, P2, links2, params, memory) is None
        P[links.i[-1]] = np.nan  # the same links: slots updated in place, then restored
        assert kernels.fast_correct(FILTERS["ckf"], x, P, links, params, memory) is None
        with pytest.raises(NumericalError):
            correct(FILTERS["ckf"], x, P, links, params, memory)
    np.testing.assert_array_equal(memory.cusum.keys, keys[0])
    np.testing.assert_array_equal(memory.mean_cusum.keys, keys[1])
    np.testing.assert_array_equal(memory.cusum.values, values[0])
    np.testing.assert_array_equal(memory.mean_cusum.values, values[1])


def test_cusum_without_memory_goes_to_the_reference_which_raises() -> None:
    x, P, links = random_batch(6)
    params = CLParams(range_std=0.02, bearing_std=0.03, cusum=True)
    with kernels.use_backend("numba"):
        assert kernels.fast_correct(FILTERS["ckf"], x, P, links, params) is None
        with pytest.raises(ValueError, match="LinkMemory"):
            correct(FILTERS["ckf"], x, P, links, params)
