"""The ``tracked`` and ``factorized`` joints in the link rounds
(:mod:`resloc.cl.kernels_joint_rounds`) against the numpy reference: same estimates,
covariances, decisions and method state to 1e-9, with the rounds asserted to have run
(:data:`resloc.cl.kernels_rounds.LOOP_RUNS`), and a fall back to the row-order loop
after some rounds recorded updates starting from the joint as the step began."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from resloc.cl import LinkMemory, kernels
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.kernels_joint import warm_up_joint_form
from resloc.cl.kernels_plain import plain
from resloc.cl.kernels_rounds import LOOP_RUNS
from resloc.experiments.config import default_scenario
from test_engine import assert_equivalent, random_batch, run_both
from test_kernels_joint import FILTERS, assert_same_state, lockstep

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

JOINTS = ["tracked", "factorized"]


@pytest.mark.parametrize("name", ["ckf", "ukf"])
@pytest.mark.parametrize("method", JOINTS)
def test_joint_rounds_match_the_reference_over_a_run(method: str, name: str) -> None:
    """Two teams of the default scenario: every correction of the compiled side ran the
    joints' rounds (none fell back, none ran in row order)."""
    params = replace(default_scenario().cl_params(), fusion=method)
    warm_up_joint_form()  # (its corrections are not the run's)
    before = dict(LOOP_RUNS)
    steps = 40
    fused, _ = lockstep(method, FILTERS[name], params, steps, seed=21)
    assert fused > 0
    ran = {k: LOOP_RUNS[k] - before.get(k, 0) for k in LOOP_RUNS}
    assert ran.get("joint_rounds", 0) == steps
    assert ran.get("rounds_fallback", 0) == 0 and ran.get("row_order", 0) == 0


@pytest.mark.parametrize("method", JOINTS)
def test_joint_rounds_with_the_cusums_and_jamming(method: str) -> None:
    """A tight NIS gate with the link, mean-shift and robot CUSUMs (stages of the rounds;
    the recovery is not) and a third of the channels jammed."""
    base = default_scenario().cl_params()
    params = replace(
        base, fusion=method, detector_norm="nis", rho=1.2, cusum=True, mean_cusum=True,
        robot_cusum=True,
    )  # fmt: skip
    warm_up_joint_form()
    before = LOOP_RUNS["joint_rounds"]
    fused, detected = lockstep(method, FILTERS["ckf"], params, 60, seed=22, jam=0.35)
    assert fused > 0 and detected > 0
    assert LOOP_RUNS["joint_rounds"] - before == 60


@pytest.mark.parametrize("method", JOINTS)
def test_a_fall_back_after_recorded_rounds_starts_from_the_step_s_joint(method: str) -> None:
    """A measured bearing out of ``(-2 pi, 2 pi)`` on a robot's third link makes the rounds
    give way to the row-order loop after two rounds recorded updates: the row-order loop
    must start from the joint's working copies as the step began."""
    x, P, links = random_batch(5, outliers=0.0, fail=0.0)
    counts = np.bincount(links.i, minlength=len(x))
    robot = int(np.flatnonzero(counts >= 3)[0])
    row = int(np.flatnonzero(links.i == robot)[2])
    z = links.z.copy()
    z[row, 1] += 4.0 * np.pi  # the same direction, out of the rounds' range
    links = replace(links, z=z)
    params = replace(default_scenario().cl_params(), fusion=method)
    memories = []
    for _ in range(2):
        memory = LinkMemory(len(x))
        fusion_strategy(method).init(memory, x, P, len(x))
        memories.append(memory)
    warm_up_joint_form()
    before = dict(LOOP_RUNS)
    fast, ref = run_both(FILTERS["ckf"], x, P, links, params, tuple(memories))
    assert LOOP_RUNS["rounds_fallback"] - before.get("rounds_fallback", 0) == 1
    assert LOOP_RUNS["row_order"] - before.get("row_order", 0) == 1
    assert_equivalent(fast, ref)
    assert_same_state(method, *memories)


def test_cholesky_lanes_match_numpy_and_flag_what_needs_jitter() -> None:
    """:func:`~resloc.cl.kernels_joint_rounds.chol6_lanes` (the first level of ``chol6``
    over lanes) equals numpy's factor of every positive definite lane and flags the lanes
    that are not (singular, indefinite, not finite) for the jitter's levels."""
    from resloc.cl.kernels_joint_lanes import LANE_STRIDE, chol6_lanes

    rng = np.random.default_rng(3)
    n = 40
    A = rng.normal(size=(n, 6, 6))
    M = A @ np.swapaxes(A, -1, -2) + 1e-3 * np.eye(6)
    M[5] = np.outer(A[5, 0], A[5, 0])  # rank one
    M[6, 2, 2] = -1.0  # indefinite
    M[7, 4, 1] = M[7, 1, 4] = np.inf
    M[8, 5, 5] = 0.0  # only the last pivot fails
    rows, cols = np.tril_indices(6)
    J = np.zeros((21, LANE_STRIDE))
    J[:, :n] = M[:, rows, cols].T
    L = np.zeros((21, LANE_STRIDE))
    ok = np.zeros(LANE_STRIDE)
    chol6_lanes(J, n, L, ok)
    bad = [5, 6, 7, 8]
    assert (ok[:n][bad] == 0.0).all()
    good = np.setdiff1d(np.arange(n), bad)
    assert (ok[good] == 1.0).all()
    expected = np.linalg.cholesky(M[good])[:, rows, cols].T
    np.testing.assert_allclose(L[:, good], expected, rtol=1e-12, atol=1e-12)


def test_factorized_lanes_that_need_the_shrink_take_the_full_cross() -> None:
    """Factors whose product is a correlation above the cap on some of the first round's
    links: those lanes take ``factorized_cross`` itself (the shrink), the others the
    certified scalar cross, and the correction equals the reference."""
    from resloc.cl.factorized import valid_cross

    x, P, links = random_batch(6, outliers=0.0, fail=0.0)
    B = len(x)
    rng = np.random.default_rng(6)
    sig = rng.normal(size=(B, B, 3, 3)) * 0.05
    memories = []
    for _ in range(2):
        memory = LinkMemory(B)
        fusion_strategy("factorized").init(memory, x, P, B)
        memory.joint.sig = sig.copy()
        memory.joint.sig_pred = sig.copy()
        memories.append(memory)
    first = np.flatnonzero(np.r_[True, links.i[1:] != links.i[:-1]])
    i, j = links.i[first], links.j[first]
    C = sig[i, j] @ np.swapaxes(sig[j, i], -1, -2)  # A_i = I at a robot's first link
    shrunk = ~np.all(valid_cross(P[i], P[j], C) == C, axis=(1, 2))
    assert 0 < shrunk.sum() < len(first)
    params = replace(default_scenario().cl_params(), fusion="factorized")
    warm_up_joint_form()
    before = LOOP_RUNS["joint_rounds"]
    fast, ref = run_both(FILTERS["ckf"], x, P, links, params, tuple(memories))
    assert LOOP_RUNS["joint_rounds"] - before == 1
    assert_equivalent(fast, ref)
    assert_same_state("factorized", *memories)


@pytest.mark.parametrize("n", [5, 17, 30])
def test_factorized_cross_lanes_are_the_certified_scalar_cross(n: int) -> None:
    """:func:`~resloc.cl.kernels_joint_lanes.factorized_cross_lanes` (SIMD over lanes)
    against the row-order loop's ``factorized_cross`` lane by lane: where it certifies a
    lane, the blocks and the joint's lower triangle are ``factorized_cross``'s to the bit
    (no shrink); it leaves to ``factorized_cross`` exactly the lanes with a correlation at
    or above the cap (the shrink), a covariance whose factor needs jitter, a non-finite
    entry. ``n`` below one block of lanes, not a multiple of it, and above."""
    from resloc.cl.kernels_joint import joint_state
    from resloc.cl.kernels_joint_lanes import (
        CROSS_INPUT_ROWS,
        LANE_STRIDE,
        factorized_cross_lanes,
    )
    from resloc.cl.kernels_joint_links import CROSS_CAP, factorized_cross
    from resloc.cl.kernels_lanes import CHUNK
    from resloc.linalg import JITTER_LEVELS

    rng = np.random.default_rng(40 + n)
    B = n + 3
    A = rng.normal(size=(B, 3, 3))
    P = A @ np.swapaxes(A, -1, -2) + 0.05 * np.eye(3)
    P_ref = P[rng.permutation(B)].copy()
    memory = LinkMemory(B)
    fusion_strategy("factorized").init(memory, np.zeros((B, 3)), P, B)
    memory.joint.sig = rng.normal(size=(B, B, 3, 3)) * 0.12
    memory.joint.sig_pred = rng.normal(size=(B, B, 3, 3)) * 0.12
    obs = rng.permutation(B)[:n].astype(np.int64)
    nbr = (obs + 1 + rng.integers(0, B - 1, n)) % B
    joint = joint_state(2, memory, obs, nbr)  # FACTORIZED
    joint.A[:] = np.eye(3) + 0.1 * rng.normal(size=(B, 3, 3))  # earlier updates' A_i
    src = rng.integers(0, B, n).astype(np.int64)
    P[obs[1], 2, 2] = -1.0  # no factor without jitter
    P_ref[src[2]] = 1e-4 * np.eye(3)  # a small P_j: a correlation above the cap
    P[obs[3], 0, 1] = np.nan
    lane_e = np.zeros(CHUNK, np.int64)
    lane_e[:n] = np.arange(n)
    o = np.zeros(CHUNK, np.int64)
    o[:n] = obs
    s = np.zeros(CHUNK, np.int64)
    s[:n] = src
    blocks = np.zeros((27, LANE_STRIDE))
    J = np.zeros((21, LANE_STRIDE))
    ok = np.full(CHUNK, -1.0)
    inputs = np.zeros((CROSS_INPUT_ROWS, LANE_STRIDE))
    # plain(joint): the loops' form (a KernelJoint would compile another specialization)
    full = factorized_cross_lanes(plain(joint), P, P_ref, lane_e, o, s, n, inputs, blocks, J, ok)
    rows, cols = np.tril_indices(6)
    expected_ok = np.zeros(n, bool)
    for c in range(n):
        i, j = obs[c], nbr[c]
        Pi, Pj = P[i], P_ref[src[c]]
        C = (joint.A[i] @ joint.sig[i, j]) @ joint.sig_pred[j, i].T
        finite = np.isfinite(Pi).all() and np.isfinite(Pj).all()
        if finite and np.linalg.eigvalsh(Pi)[0] > 0 and np.linalg.eigvalsh(Pj)[0] > 0:
            Li, Lj = np.linalg.cholesky(Pi), np.linalg.cholesky(Pj)
            corr = np.linalg.solve(Li, np.linalg.solve(Lj, C.T).T)
            expected_ok[c] = np.linalg.norm(corr, 2) < CROSS_CAP
        if not expected_ok[c]:
            continue
        work = joint.work
        assert factorized_cross(joint, c, i, Pi, Pj, JITTER_LEVELS)
        np.testing.assert_array_equal(blocks[:, c], work[:3].reshape(27))
        joint6 = np.block([[work[0], work[1]], [work[1].T, work[2]]])
        np.testing.assert_array_equal(J[:, c], (0.5 * (joint6 + joint6.T))[rows, cols])
    assert not expected_ok[[1, 2, 3]].any() and expected_ok.sum() >= n - 5
    np.testing.assert_array_equal(ok[:n], expected_ok.astype(float))
    assert full == n - expected_ok.sum()
