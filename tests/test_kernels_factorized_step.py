"""The compiled once-per-step parts of ``factorized`` fusion
(:mod:`resloc.cl.kernels_factorized_step`) against their numpy twins, the methods of
:class:`~resloc.cl.factorized.FactorizedCovariance`: the prediction (the factors and their
copy in one loop), the commit that writes the factors as ``finish`` leaves them (pairs
that fused in one direction or both; entries large or non-finite enough that a skipped
zero term would not be zero), the finish in place after a reference update, and two
corrections in one step over a run (the first compiled, the second the reference's)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world, start_states
from resloc.cl import LinkBatch, LinkMemory, correct, kernels, predict
from resloc.cl.factorized import FactorizedCovariance
from resloc.cl.fusion_methods import fusion_strategy
from resloc.experiments.config import default_scenario
from resloc.filters import make_filter
from test_engine import assert_equivalent

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")


def _spd(rng, n: int) -> np.ndarray:
    M = rng.normal(size=(n, 3, 3))
    return M @ np.swapaxes(M, -1, -2) + 0.1 * np.eye(3)


def _records(rng, T: int, N: int, share: float):
    """A step's records for T teams of N robots: each robot's links to some teammates
    (sorted by observer), a random share of them fused, their gains and ``-K H_j``."""
    obs, nbr = [], []
    for b in range(T * N):
        team = b - b % N
        others = [team + m for m in range(N) if team + m != b]
        for c in sorted(rng.choice(others, rng.integers(0, N), replace=False)):
            obs.append(b)
            nbr.append(c)
    obs, nbr = np.array(obs, np.int64), np.array(nbr, np.int64)
    E = len(obs)
    link_fused = rng.random(E) < share
    gains = np.eye(3) + 0.3 * rng.normal(size=(E, 3, 3))
    Bij = 0.5 * rng.normal(size=(E, 3, 3))
    return obs, nbr, link_fused, gains, Bij


def _reference(joint: FactorizedCovariance, obs, nbr, link_fused, gains, Bij):
    """``FactorizedCovariance.update`` with the records, one link at a time, then its
    ``finish``: the state the compiled commit must leave."""
    for e in range(len(obs)):
        if not link_fused[e]:
            continue
        i, lj = obs[e], nbr[e] % joint.N
        joint.sig[i] = gains[e] @ joint.sig[i]
        joint.Bm[i] = gains[e] @ joint.Bm[i]
        joint.Bm[i, lj] += Bij[e]
        joint.A[i] = gains[e] @ joint.A[i]
        joint.fused[i, lj] = True
    joint.finish(None)
    return joint


def _kernel_state(joint: FactorizedCovariance, obs, nbr, link_fused, gains, Bij):
    """The records as the link loop leaves them in the kernel's state: ``A`` (the product
    of each robot's gains), ``-K H_j`` and ``G`` per link, the pairs that fused."""
    from resloc.cl.kernels_joint import FACTORIZED, joint_state

    memory = LinkMemory(joint.B)
    memory.joint = joint
    state = joint_state(FACTORIZED, memory, obs, nbr)
    assert state is not None
    for e in range(len(obs)):
        if link_fused[e]:
            state.A[obs[e]] = gains[e] @ state.A[obs[e]]
            state.gains[e] = gains[e]
            state.Bij[e] = Bij[e]
            state.fused[obs[e], nbr[e] % joint.N] = True
    return memory, state


def _started(rng, T: int, N: int, scale: float = 1.0) -> FactorizedCovariance:
    joint = FactorizedCovariance(T * N, N)
    joint.sig = scale * rng.normal(size=(T * N, N, 3, 3))
    joint.start_step(_spd(rng, T * N))
    return joint


@pytest.mark.parametrize("share", [0.2, 0.6, 1.0])
def test_commit_leaves_the_factors_as_update_and_finish(share: float) -> None:
    """The commit's one pass: ``A``, ``B``, the pairs, and the factors of the pairs that
    fused in one direction (its zero ``B`` terms skipped) or both closed as ``finish``
    closes them; the compiled finish then has nothing left to do."""
    from resloc.cl.kernels_factorized_step import compiled_factorized_finish
    from resloc.cl.kernels_joint import joint_commit

    rng = np.random.default_rng(int(10 * share))
    joint = _started(rng, 2, 6)
    records = _records(rng, 2, 6, share)
    ref = _reference(_copy(joint), *records)
    memory, state = _kernel_state(joint, *records)
    with kernels.use_backend("numba"):
        joint_commit(state, memory, records[0], records[2])
        assert joint.pairs_closed  # the compiled commit closed the pairs
        closed = joint.sig.copy()
        assert compiled_factorized_finish(joint)
    np.testing.assert_array_equal(joint.sig, closed)  # nothing left to do
    _assert_same(joint, ref)
    pairs = ref.fused | np.swapaxes(ref.fused.reshape(2, 6, 6), 1, 2).reshape(12, 6)
    one_way = ref.fused != np.swapaxes(ref.fused.reshape(2, 6, 6), 1, 2).reshape(12, 6)
    assert one_way.any()  # (the skipped terms)
    assert share < 0.5 or (pairs & ~one_way).any()  # (and the full sum)


@pytest.mark.parametrize(("value", "gain"), [(np.inf, 1.0), (np.nan, 1.0), (1e300, 1e10)])
def test_commit_keeps_the_terms_a_zero_block_makes_non_finite(value: float, gain: float) -> None:
    """A pair that fused one way has a zero ``B``: its terms are skipped only where they are
    exactly zero; with an infinite or NaN entry, or products that overflow, the
    reference's ``0 * inf = nan`` is kept."""
    from resloc.cl.kernels_joint import joint_commit

    rng = np.random.default_rng(7)
    joint = _started(rng, 1, 5)
    obs, nbr = np.array([0, 1], np.int64), np.array([1, 2], np.int64)  # 0 -> 1, 1 -> 2
    gains = np.eye(3) + 0.1 * rng.normal(size=(2, 3, 3))
    gains[0] *= gain
    records = (obs, nbr, np.array([True, True]), gains, rng.normal(size=(2, 3, 3)))
    joint.P_pred[0, :2, :2] = value  # P_a of pair (0, 1), fused by 0 only: A_0 P_0 B_10^T
    joint.sig_pred[1, 2, 1, 1] = value  # P_ac of pair (1, 2), fused by 1 only
    with np.errstate(invalid="ignore", over="ignore"):
        ref = _reference(_copy(joint), *records)
    memory, state = _kernel_state(joint, *records)
    with kernels.use_backend("numba"):
        joint_commit(state, memory, obs, records[2])
    assert joint.pairs_closed  # the compiled commit ran
    assert np.isnan(ref.sig[0, 1]).any()
    _assert_same(joint, ref)


def test_finish_after_a_reference_update_closes_in_place() -> None:
    """A reference update after the compiled commit (a second correction of the step)
    clears ``pairs_closed``: the compiled finish closes the pairs again, as ``finish``."""
    from resloc.cl.kernels_factorized_step import compiled_factorized_finish

    rng = np.random.default_rng(5)
    joint = _started(rng, 2, 4)
    obs, nbr, link_fused, gains, Bij = _records(rng, 2, 4, 0.7)
    others = obs != 0  # robot 0 fuses one link, 0 -> 1, after the others' commit
    obs, nbr = np.r_[0, obs[others]], np.r_[1, nbr[others]]
    link_fused, gains, Bij = (
        np.r_[True, link_fused[others]],
        gains[[0, *np.flatnonzero(others)]],
        Bij[[0, *np.flatnonzero(others)]],
    )
    ref = _reference(_copy(joint), obs, nbr, link_fused, gains, Bij)
    joint = _reference(joint, obs, nbr, np.r_[False, link_fused[1:]], gains, Bij)
    joint.pairs_closed = True  # as a compiled commit leaves the others' records
    _reference_update(joint, obs[0], nbr[0], gains[0], Bij[0])
    assert not joint.pairs_closed
    with kernels.use_backend("numba"):
        assert compiled_factorized_finish(joint)
    _assert_same(joint, ref)


def _reference_update(joint, i, j, G, B_ij) -> None:
    """``FactorizedCovariance.update`` of one link with the gain ``G`` and ``-K H_j``
    given (its own gain map needs the filter's moments)."""
    from resloc.cl import factorized

    original = factorized.update_map
    factorized.update_map = lambda m, x_i, x_j: (None, G[None], -B_ij[None])
    try:
        joint.update(np.array([i]), np.array([j]), None, None, None, None, None)
    finally:
        factorized.update_map = original


def test_compiled_prediction_like_the_reference() -> None:
    """The factors and their copy ``sig_pred`` in one loop, the step's records started."""
    from resloc.cl.kernels_factorized_step import compiled_factorized_predict

    rng = np.random.default_rng(2)
    joint = _started(rng, 3, 4)
    joint.fused[0, 1] = True
    joint.pairs_closed = True
    ref = _copy(joint)
    x = rng.normal(size=(12, 3))
    u = rng.normal(size=(12, 2))
    P_pred = _spd(rng, 12)
    expected = ref.predict(x, u, 0.1, None, P_pred)
    with kernels.use_backend("numba"):
        got = compiled_factorized_predict(joint, x, u, 0.1, P_pred)
    assert got is P_pred and expected is P_pred
    _assert_same(joint, ref)
    np.testing.assert_allclose(joint.sig_pred, ref.sig_pred, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(joint.P_pred, P_pred)
    assert joint.sig_pred is not joint.sig and joint.P_pred is not P_pred
    assert not joint.pairs_closed
    with kernels.use_backend("numpy"):
        assert compiled_factorized_predict(joint, x, u, 0.1, P_pred) is None


def test_two_corrections_in_a_step_over_a_run() -> None:
    """The first correction of each step compiled (its commit closes the pairs), a second
    one the reference's (its update reopens them, the compiled finish closes them again):
    the same estimates and factors as the reference path at every step."""
    params = replace(default_scenario().cl_params(), fusion="factorized")
    filt = make_filter("ckf")
    world = default_world(1, 21)
    fusion = fusion_strategy("factorized")
    state = start_states(world, ("numba", "numpy"), fusion)
    second_fused = 0
    for _ in range(40):
        ws = world.step()
        res = {}
        for backend, (x, P, memory) in state.items():
            with kernels.use_backend(backend):
                xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
                Pp = fusion.predict(memory, x, ws.u_meas, world.dt, params, Pp)
                links = LinkBatch(
                    ws.i, ws.j, ws.z, xp[ws.j], Pp[ws.j], ws.channel_ok,
                    ws.risk_s, ws.risk_c, ws.lambda2, **fusion.link_fields(memory, ws.j),
                )  # fmt: skip
                first = correct(filt, xp, Pp, links, params, memory)
                half = slice(0, len(ws.i) // 2)
                again = LinkBatch(
                    ws.i[half], ws.j[half], ws.z[half], first[0][ws.j[half]],
                    first[1][ws.j[half]], ws.channel_ok[half], ws.risk_s, ws.risk_c,
                    ws.lambda2, **fusion.link_fields(memory, ws.j[half]),
                )  # fmt: skip
                res[backend] = (first, correct(filt, first[0], first[1], again, params, memory))
            state[backend] = (res[backend][1][0], res[backend][1][1], memory)
        assert_equivalent(res["numba"][0], res["numpy"][0])
        (x2, P2, o2), (x2r, P2r, o2r) = res["numba"][1], res["numpy"][1]
        assert not o2r.compiled
        np.testing.assert_allclose(x2, x2r, rtol=0, atol=1e-9)
        np.testing.assert_allclose(P2, P2r, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(o2.fused, o2r.fused)
        _assert_same(state["numba"][2].joint, state["numpy"][2].joint, tol=1e-9)
        if not o2.compiled and res["numba"][0][2].fused.any():  # (the case under test)
            second_fused += int(o2.fused.sum())
    assert second_fused > 0


def _copy(joint: FactorizedCovariance) -> FactorizedCovariance:
    import copy

    return copy.deepcopy(joint)


def _assert_same(a: FactorizedCovariance, b: FactorizedCovariance, tol: float = 1e-12) -> None:
    for name in ("sig", "A", "Bm"):
        np.testing.assert_allclose(
            getattr(a, name), getattr(b, name), rtol=tol, atol=tol, err_msg=name
        )
    np.testing.assert_array_equal(a.fused, b.fused)
