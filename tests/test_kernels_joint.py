"""The compiled ``tracked``, ``factorized`` (:mod:`resloc.cl.kernels_joint`) and ``split_ci``
(:mod:`resloc.cl.kernels_fusion`) fusion against the numpy reference over multi-step runs:
same estimates, covariances and decisions to 1e-9 at every step with the compiled path
asserted, and the same method state (the tracked joint, the factors, the independent
parts) after every step; for the CKF, UKF and EKF, with the detector stages and recovery,
with jamming, and with ``cached`` neighbour estimates where the method allows them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world, runner_step, start_states
from resloc.cl import LinkBatch, LinkMemory, correct, kernels
from resloc.cl import fusion as cl_fusion
from resloc.cl.backend import kernel_refusal
from resloc.cl.fusion_methods import fusion_strategy
from resloc.experiments.config import default_scenario
from resloc.filters import make_filter
from test_engine import assert_equivalent, random_batch

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

FILTERS = {
    "ckf": make_filter("ckf"),
    "ukf": make_filter("ukf", 0.8, 2.0, 1.0),
    "ekf": make_filter("ekf"),
}


def assert_same_state(method: str, fast: LinkMemory, ref: LinkMemory) -> None:
    """The method's state after a step is the same on both paths."""
    if method == "split_ci":
        np.testing.assert_allclose(fast.independent, ref.independent, rtol=0, atol=1e-9)
    elif method == "tracked":
        np.testing.assert_allclose(fast.joint.sigma, ref.joint.sigma, rtol=0, atol=1e-9)
    elif method == "factorized":
        for name in ("sig", "A", "Bm"):
            a, b = getattr(fast.joint, name), getattr(ref.joint, name)
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-9, err_msg=name)
        np.testing.assert_array_equal(fast.joint.fused, ref.joint.fused)


def lockstep(method, filt, params, steps: int, seed: int, trials: int = 2, jam=None):
    """The default scenario (``trials`` batched) through both paths side by side, as the
    runner steps it (the method's prediction and transmitted fields included); ``jam``:
    the share of channels jammed at random. Returns the counts of fused links and of links
    the detector rejected."""
    world = default_world(trials, seed)
    rng = np.random.default_rng(seed)
    fusion = fusion_strategy(method)
    state = start_states(world, ("numba", "numpy"), fusion)
    fused = detected = 0
    for _ in range(steps):
        ws = world.step()
        channel_ok = ws.channel_ok
        if jam is not None:
            channel_ok = channel_ok & (rng.random(len(channel_ok)) >= jam)
        res = {}
        for backend, (x, P, memory) in state.items():
            with kernels.use_backend(backend):
                res[backend] = runner_step(
                    filt, x, P, ws, world.dt, params, fusion, memory, channel_ok
                )
            state[backend] = (res[backend][0], res[backend][1], memory)
        assert_equivalent(res["numba"], res["numpy"])
        assert_same_state(method, state["numba"][2], state["numpy"][2])
        fused += int(res["numpy"][2].fused.sum())
        detected += int(res["numpy"][2].detected.sum())
    return fused, detected


METHODS = ["tracked", "factorized", "split_ci"]


def transmitted(method: str) -> LinkBatch:
    """A batch of links with what the method's transmissions carry (split CI: the
    independent parts)."""
    links = random_batch(0)[2]
    return replace(links, **fusion_strategy(method).link_fields(_independent(links), links.j))


def _independent(links: LinkBatch) -> LinkMemory:
    memory = LinkMemory(40)
    memory.independent = np.broadcast_to(1e-3 * np.eye(3), (40, 3, 3)).copy()
    return memory


@pytest.mark.parametrize("name", list(FILTERS))
@pytest.mark.parametrize("method", METHODS)
def test_compiled_method_matches_reference_over_a_run(method: str, name: str) -> None:
    params = replace(default_scenario().cl_params(), fusion=method)
    assert kernel_refusal(FILTERS[name], params, transmitted(method)) is None
    fused, _ = lockstep(method, FILTERS[name], params, 150, seed=11)
    assert fused > 0


@pytest.mark.parametrize("method", ["tracked", "factorized", "split_ci"])
def test_compiled_prediction_and_end_of_step_ran(method: str, monkeypatch) -> None:
    """The lockstep's numba side ran the compiled prediction and end of step of the
    method every step (their numpy twins are the other side; split CI's compiled end of
    step, ``kernels_split.compiled_independent_finish``, is counted by its own tests)."""
    from resloc.cl import kernels_fusion_step as step_kernels
    from resloc.cl.kernels_joint import warm_up_joint_form

    warm_up_joint_form()  # (once per process; its corrections are not the lockstep's)
    ran: dict[str, int] = {}
    names = {
        "tracked": ("compiled_tracked_predict", "compiled_tracked_finish"),
        "factorized": ("compiled_factorized_predict", "compiled_factorized_finish"),
        "split_ci": ("compiled_independent_predict",),
    }[method]
    for name in names:
        original = getattr(step_kernels, name)

        def counted(*args, _original=original, _name=name, **kwargs):
            out = _original(*args, **kwargs)
            done = out is not None and out is not False
            ran[_name] = ran.get(_name, 0) + done
            return out

        monkeypatch.setattr(step_kernels, name, counted)
    params = replace(default_scenario().cl_params(), fusion=method)
    steps = 20
    fused, _ = lockstep(method, FILTERS["ckf"], params, steps, seed=14)
    assert fused > 0
    assert ran == dict.fromkeys(names, steps)


@pytest.mark.parametrize("method", METHODS)
def test_compiled_method_with_the_detector_recovery_and_jamming(method: str) -> None:
    """A tight NIS gate with the CUSUMs and the recovery stage (re-admissions on an
    inflated covariance), and a third of the channels jammed."""
    from resloc.experiments.defences import DEFENCES

    base = default_scenario().replace(**DEFENCES["full"]).cl_params()
    params = replace(base, fusion=method, rho=1.2, recovery_after=2.0, recovery_gate=3.0)
    fused, detected = lockstep(method, FILTERS["ckf"], params, 80, seed=12, jam=0.35)
    assert fused > 0 and detected > 0


@pytest.mark.parametrize("name", ["ckf", "ekf"])
def test_compiled_split_ci_with_cached_neighbour_estimates(name: str) -> None:
    """``split_ci`` allows ``cached`` neighbour estimates (``tracked`` and ``factorized``
    refuse them): moments from j's last received estimate, a delivered link fused with the
    fresh one."""
    params = replace(default_scenario().cl_params(), fusion="split_ci", neighbour_estimate="cached")
    assert kernel_refusal(FILTERS[name], params, transmitted("split_ci")) is None
    fused, _ = lockstep("split_ci", FILTERS[name], params, 80, seed=13, jam=0.2)
    assert fused > 0


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_compiled_split_ci_runs_both_weight_branches(criterion: str, monkeypatch) -> None:
    """Links fused with a weight below 1 and links whose weight is 1 (the prior and its
    independent part kept), for both weight criteria."""
    seen: list[np.ndarray] = []
    weights = cl_fusion.ci_weights

    def recorded(*args, **kwargs):
        w = weights(*args, **kwargs)
        seen.append(w)
        return w

    monkeypatch.setattr(cl_fusion, "ci_weights", recorded)
    params = replace(default_scenario().cl_params(), fusion="split_ci", ci_criterion=criterion)
    lockstep("split_ci", FILTERS["ukf"], params, 80, seed=14)
    w = np.concatenate(seen)
    assert (w < 1.0).any() and (w == 1.0).any(), "both CI branches must run"


def test_a_second_correction_in_a_step_goes_to_the_reference() -> None:
    """``factorized`` records a step's updates until the next prediction and ``tracked``
    until its ``finish``: a correction that finds records it did not make is the
    reference's (the kernel would not see them)."""
    from resloc.cl.kernels_fusion import fusion_state

    x, P, links = random_batch(3)
    memory = LinkMemory(40)
    fusion_strategy("factorized").init(memory, x, P, 40)
    assert fusion_state("factorized", "trace", memory, links, len(links)) is not None
    memory.joint.fused[0, 1] = True
    assert fusion_state("factorized", "trace", memory, links, len(links)) is None
    tracked = LinkMemory(40)
    fusion_strategy("tracked").init(tracked, x, P, 40)
    assert fusion_state("tracked", "trace", tracked, links, len(links)) is not None
    tracked.joint.updates = 1  # an update recorded by the reference path
    assert fusion_state("tracked", "trace", tracked, links, len(links)) is None


@pytest.mark.parametrize("method", METHODS)
def test_without_the_method_state_the_reference_raises(method: str) -> None:
    x, P, links = random_batch(3)
    params = replace(default_scenario().cl_params(), fusion=method)
    with kernels.use_backend("numba"):
        assert kernels.fast_correct(FILTERS["ckf"], x, P, links, params, LinkMemory(40)) is None
        with pytest.raises(ValueError, match=r"split_ci needs|memory\.joint"):
            correct(FILTERS["ckf"], x, P, links, params, LinkMemory(40))


def _random_spd(rng, n: int) -> np.ndarray:
    A = rng.normal(size=(n, 3, 3)) * rng.uniform(0.05, 2.0, (n, 1, 1))
    return A @ np.swapaxes(A, -1, -2) + 1e-3 * np.eye(3)


def test_compiled_valid_cross_shrinks_like_the_reference() -> None:
    """The factors' cross-covariance shrunk to a valid joint (``valid_cross``): rows with
    a correlation above the cap (shrunk) and below it (kept), one matrix at a time in the
    kernel's twin. The runs above rarely need the shrink, so it is checked here."""
    from resloc.cl.factorized import valid_cross
    from resloc.cl.kernels_joint_links import _valid_cross
    from resloc.linalg import JITTER_LEVELS

    rng = np.random.default_rng(3)
    Pi, Pj = _random_spd(rng, 300), _random_spd(rng, 300)
    C = rng.normal(size=(300, 3, 3)) * rng.uniform(0.01, 3.0, (300, 1, 1))
    ref = valid_cross(Pi, Pj, C)
    shrunk = ~np.all(ref == C, axis=(1, 2))
    assert 0 < shrunk.sum() < len(C)
    jitter = np.asarray(JITTER_LEVELS, dtype=float)
    for e in range(len(C)):
        got = C[e].copy()
        scratch = [np.zeros((3, 3)) for _ in range(4)]
        assert _valid_cross(Pi[e], Pj[e], got, *scratch, jitter)
        np.testing.assert_allclose(got, ref[e], rtol=1e-11, atol=1e-13)


def test_compiled_clip_of_independent_parts_like_the_reference() -> None:
    """Split CI's independent part clipped to its covariance (``clip_independent``): parts
    inside ``0 < P_ind < P`` (kept), above it (scaled) and indefinite (projected)."""
    from resloc.cl.fusion import clip_independent
    from resloc.cl.kernels_split import _clip_independent
    from resloc.linalg import JITTER_LEVELS

    rng = np.random.default_rng(4)
    P = _random_spd(rng, 300)
    P_ind = P * rng.uniform(0.1, 1.6, (300, 1, 1))
    w, V = np.linalg.eigh(P_ind[:60])
    w[:, 0] = -np.abs(w[:, 0]) * 0.1  # indefinite
    P_ind[:60] = np.einsum("bij,bj,bkj->bik", V, w, V)
    P_ind = 0.5 * (P_ind + np.swapaxes(P_ind, -1, -2))
    ref = clip_independent(P, P_ind)
    jitter = np.asarray(JITTER_LEVELS, dtype=float)
    kept = np.all(np.abs(ref - P_ind) <= 1e-15 * np.abs(P_ind).max(), axis=(1, 2))
    assert 0 < kept.sum() < len(P)
    for e in range(len(P)):
        out = np.zeros((3, 3))
        scratch = [np.zeros((3, 3)) for _ in range(3)]
        assert _clip_independent(P[e], P_ind[e], out, *scratch, jitter)
        np.testing.assert_allclose(out, ref[e], rtol=0, atol=1e-11 * np.abs(ref[e]).max())


def test_sylvester_certificate_of_eigenvalues_below_a_bound() -> None:
    """``scaled_unit_minus_is_pd(M, c)`` certifies every eigenvalue of ``M`` below ``c``
    (it decides when the kernels skip an eigenvalue computation): never wrongly."""
    from resloc.cl.kernels_joint_links import scaled_unit_minus_is_pd

    rng = np.random.default_rng(5)
    M = _random_spd(rng, 500)
    top = np.linalg.eigvalsh(M)[:, -1]
    for c in (0.5, 1.0, 3.0):
        got = np.array([scaled_unit_minus_is_pd(m, c) for m in M])
        assert not (got & (top >= c)).any()
        assert (got == (top < c * (1 - 1e-12))).mean() > 0.99


@pytest.mark.parametrize("method", ["tracked", "factorized"])
def test_links_across_teams_or_out_of_range_go_to_the_reference(method: str) -> None:
    """The kernel state is refused (None: the reference decides) for a link across teams
    or an index outside the batch, and built for links within a team."""
    from resloc.cl.factorized import FactorizedCovariance
    from resloc.cl.kernels_joint import FACTORIZED, TRACKED, joint_state
    from resloc.cl.tracking import JointCovariance

    memory = LinkMemory(6)  # two teams of three robots
    P0 = np.broadcast_to(1e-2 * np.eye(3), (6, 3, 3)).copy()
    if method == "tracked":
        memory.joint, code = JointCovariance(P0, 3), TRACKED
    else:
        memory.joint, code = FactorizedCovariance(6, 3), FACTORIZED
    within = joint_state(code, memory, np.array([0, 0, 4]), np.array([1, 2, 5]))
    assert within is not None and within.code == code
    np.testing.assert_array_equal(within.A, np.broadcast_to(np.eye(3), (6, 3, 3)))
    assert joint_state(code, memory, np.array([0, 2]), np.array([1, 3])) is None
    assert joint_state(code, memory, np.array([0]), np.array([6])) is None
    assert joint_state(code, memory, np.array([0]), np.array([-1])) is None
    one_team = LinkMemory(3)  # B == N: the check without the team's division
    if method == "tracked":
        one_team.joint = JointCovariance(P0[:3], 3)
    else:
        one_team.joint = FactorizedCovariance(3, 3)
    assert joint_state(code, one_team, np.array([0, 2]), np.array([2, 1])) is not None
    assert joint_state(code, one_team, np.array([0]), np.array([3])) is None
    assert joint_state(code, one_team, np.array([-1]), np.array([0])) is None


def test_tracked_scratch_is_kept_per_joint_and_goes_with_its_memory() -> None:
    """``fusion_state`` of ``tracked`` takes the kernel's scratch from the memory's joint
    (:func:`~resloc.cl.kernels_joint.kernel_scratch`): the same arrays every step of that
    joint, other arrays for another memory's joint, and none kept once the memory is gone."""
    import gc
    import weakref

    from resloc.cl.fusion import CICriterion
    from resloc.cl.kernels_fusion import fusion_state
    from resloc.cl.kernels_inputs import pair_warm_up_batch
    from resloc.cl.tracking import JointCovariance

    _, P, links = pair_warm_up_batch()

    def scratch(memory):
        state = fusion_state("tracked", CICriterion.TRACE, memory, links, 2)
        return state.joint.work, state.joint.J6, state.work, state.costs

    memories = [LinkMemory(2), LinkMemory(2)]
    for memory in memories:
        memory.joint = JointCovariance(P, 2)
    first, again, other = scratch(memories[0]), scratch(memories[0]), scratch(memories[1])
    assert all(a is b for a, b in zip(first, again, strict=True))
    assert not any(np.shares_memory(a, b) for a in first for b in other)
    gone = weakref.ref(memories[0]), weakref.ref(memories[0].joint)
    del memories[0], first, again
    gc.collect()
    assert gone[0]() is None and gone[1]() is None
