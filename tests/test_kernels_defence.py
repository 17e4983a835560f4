"""The compiled per-robot detector stages (robot CUSUM, recovery after rejection runs) against
the numpy reference, over multi-step runs: same estimates and decisions to 1e-9 at every
step, the compiled path asserted, and the same per-robot statistics after every step;
re-admissions with an inflated covariance (the kernel's second pass) occur in the runs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world
from resloc.cl import LinkMemory, correct, kernels
from resloc.cl.backend import kernel_refusal
from resloc.cl.detection_recovery import RejectionRecovery
from resloc.errors import NumericalError
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters import make_filter
from test_engine import lockstep_both_backends, random_batch
from test_kernels_detection import assert_same_statistics

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

FILTERS = {
    "ckf": make_filter("ckf"),
    "ukf": make_filter("ukf", 0.8, 2.0, 1.0),
    "ekf": make_filter("ekf"),
}
STAGE_STORES = ("robot_cusum", "recovery", "recovery_spread", "recovery_applied")


def full_defence(**changes):
    """The ``full`` defence of ``resloc compare`` on the default scenario, with ``changes``."""
    params = default_scenario().replace(**DEFENCES["full"]).cl_params()
    return replace(params, **changes)


#: Strict gates so that rejection runs (hence recoveries) happen within a short run.
CASES = {
    "full": {},
    "strict-recovery": dict(rho=1.2, recovery_after=2.0, recovery_gate=3.0, robot_cusum_h=5.0),
    "recovery-only": dict(rho=1.0, cusum=False, mean_cusum=False, robot_cusum=False,
                          recovery_after=3.0, recovery_gate=2.0, recovery_inflation_cap=8.0),
    "robot-cusum-euclidean": dict(detector_norm="euclidean", rho=0.5, recovery=False,
                                  robot_cusum_k=2.0, robot_cusum_h=4.0),
    "gauge-strict": dict(fusion="gauge", rho=1.2, recovery_after=2.0, recovery_gate=3.0,
                         robot_cusum_h=5.0),
}  # fmt: skip


def assert_same_stage_statistics(fast: LinkMemory, ref: LinkMemory) -> None:
    """Equal values for every key either path stored (a key the kernel inserted at 0 reads
    as the reference's 0 for a robot it has not stored)."""
    for name in STAGE_STORES:
        a, b = fast.stage_statistic(name), ref.stage_statistic(name)
        keys = np.union1d(a.keys, b.keys)
        i, j = keys // a.n_nodes, keys % a.n_nodes
        np.testing.assert_allclose(a.get(i, j), b.get(i, j), rtol=0, atol=1e-9, err_msg=name)
        assert set(b.keys) <= set(a.keys), name


@pytest.fixture
def readmissions(monkeypatch):
    """Counts the reference's re-admissions with an inflated covariance (f > 1), and those
    on top of an earlier one since the robot's last ordinary acceptance (``A_i > f``: the
    inflations the total cap multiplies)."""
    count = {"inflated": 0, "readmitted": 0, "repeated": 0}
    discard = RejectionRecovery.discard

    def counted(self, evidence, params, memory):
        detected = discard(self, evidence, params, memory)
        if evidence.inflation is not None:
            count["readmitted"] += int((evidence.detected & ~detected).sum())
            inflated = (evidence.inflation > 1.0) & ~detected
            count["inflated"] += int(inflated.sum())
            applied = memory.stage_statistic("recovery_applied").get(evidence.i, evidence.i)
            count["repeated"] += int((inflated & (applied > evidence.inflation * 1.000001)).sum())
        return detected

    monkeypatch.setattr(RejectionRecovery, "discard", counted)
    return count


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("name", list(FILTERS))
def test_compiled_defence_stages_match_reference_over_a_run(name, case, readmissions):
    params = full_defence(**CASES[case])
    assert kernel_refusal(FILTERS[name], params, random_batch(0)[2]) is None
    world = default_world(2, 3 + list(CASES).index(case))
    detected = robot_cusum_active = 0
    for res, memories in lockstep_both_backends(world, FILTERS[name], params, 100):
        assert_same_statistics(memories["numba"], memories["numpy"])
        assert_same_stage_statistics(memories["numba"], memories["numpy"])
        detected += int(res["numpy"][2].detected.sum())
        robot_cusum_active += int(
            (memories["numpy"].stage_statistic("robot_cusum").values > 0).any()
        )
    assert detected > 0
    if case in ("full", "robot-cusum-euclidean"):  # strict gates pass only NIS < k
        assert robot_cusum_active > 0
    if case in ("strict-recovery", "recovery-only", "gauge-strict"):
        assert readmissions["inflated"] > 0, "no re-admission with an inflated covariance"
        assert readmissions["repeated"] > 0, "no re-admission on top of an inflated one"


def test_the_defence_stages_are_declared_compiled():
    from resloc.cl.detection import active_stages

    stages = active_stages(full_defence())
    assert [s.name for s in stages] == ["gate", "cusum", "mean_cusum", "robot_cusum", "recovery"]
    assert all(s.compiled for s in stages)


def test_resilient_example_with_the_full_defence_runs_compiled():
    """``examples/beyond/resilient.toml`` (gauge, NIS gate, CUSUMs, stealthy attacker) with the
    robot CUSUM and the recovery: no part of its correction is left to the numpy path."""
    from pathlib import Path

    from resloc.experiments.config_parse import load_scenario

    path = Path(__file__).parent.parent / "examples" / "beyond" / "resilient.toml"
    if not path.exists():
        pytest.skip("examples/ not shipped")
    sc = load_scenario(path)
    params = replace(sc.cl_params(), robot_cusum=True, recovery=True)
    assert kernel_refusal(FILTERS["ckf"], params, random_batch(0)[2]) is None


def test_a_failed_kernel_step_leaves_the_robot_statistics_untouched():
    """On a covariance that is not positive definite the kernel gives up; the per-robot
    stores must be what the reference then starts from (the reference raises here)."""
    params = full_defence(range_std=0.02, bearing_std=0.03, rho=1.0, recovery_after=1.0)
    memory = LinkMemory(40)
    x, P, links = random_batch(4, outliers=0.5)
    with kernels.use_backend("numba"):
        for _ in range(3):
            assert correct(FILTERS["ckf"], x, P, links, params, memory)[2].compiled
        before = {
            n: (memory.stage_statistic(n).keys.copy(), memory.stage_statistic(n).values.copy())
            for n in STAGE_STORES
        }
        x2, P2, links2 = random_batch(5)  # other observers: the kernel would insert slots
        P2[links2.i[-1]] = np.nan
        assert kernels.fast_correct(FILTERS["ckf"], x2, P2, links2, params, memory) is None
        P[links.i[-1]] = np.nan  # the same observers: slots updated in place, then restored
        assert kernels.fast_correct(FILTERS["ckf"], x, P, links, params, memory) is None
        with pytest.raises(NumericalError):
            correct(FILTERS["ckf"], x, P, links, params, memory)
    for n, (keys, values) in before.items():
        np.testing.assert_array_equal(memory.stage_statistic(n).keys, keys, err_msg=n)
        np.testing.assert_array_equal(memory.stage_statistic(n).values, values, err_msg=n)


def test_defence_without_memory_goes_to_the_reference_which_raises():
    x, P, links = random_batch(6)
    with kernels.use_backend("numba"):
        for stage in ({"recovery": True}, {"robot_cusum": True}):
            params = replace(full_defence(cusum=False, mean_cusum=False, recovery=False), **stage)
            assert kernels.fast_correct(FILTERS["ckf"], x, P, links, params) is None
            with pytest.raises(ValueError, match="LinkMemory"):
                correct(FILTERS["ckf"], x, P, links, params)
