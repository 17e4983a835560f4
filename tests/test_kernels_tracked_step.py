"""``tracked``'s commit and end of step from ``M``'s blocks
(:mod:`resloc.cl.kernels_tracked_step`) and the prediction's spare rows, against numpy: the
commit's end of step is the reference's ``finish`` of the dense ``M`` to 1e-12 (not to the
bit: it sums the lower triangle only and mirrors it), ``M`` built from the blocks where read
is the reference's, and the compiled path is asserted to have run (``end_of_step`` set,
then installed by the compiled finish)."""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest

from resloc.cl import kernels
from resloc.cl.tracking import JointCovariance
from resloc.experiments.config import default_scenario

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")


def _kernel_joint(A, Bij, nbr, noise, rows, robots: int):
    """The records as the kernel's ``KernelJoint`` holds them (what the commit takes)."""
    from resloc.cl.kernels_joint import TRACKED, KernelJoint

    empty = np.zeros((0, 3, 3))  # (no gains: the blocks as the commit's products leave them)
    return KernelJoint(
        TRACKED, robots, nbr, np.zeros((0, 0, 0)), noise, A, Bij, empty[None], empty[None],
        empty[None], np.zeros((0, 0), np.bool_), np.zeros((5, 3, 3)), np.zeros((2, 6, 6)),
        empty, rows,
    )  # fmt: skip


def _records(teams: int, robots: int, seed: int):
    """A joint as a step began and a correction's records on it: ``A`` (B, 3, 3), fused
    links' ``B_ij`` (most with a zero third column, as ``-K H_j`` times gains has; some
    without), observers sorted, two links of one robot to the same neighbour and one to
    itself (their blocks add up), unfused links with garbage blocks (never read)."""
    rng = np.random.default_rng(seed)
    B, n3 = teams * robots, 3 * robots
    joint = JointCovariance(np.broadcast_to(0.1 * np.eye(3), (B, 3, 3)).copy(), robots)
    G = rng.normal(size=(teams, n3, n3))
    joint.sigma = G @ np.swapaxes(G, -1, -2) / n3
    obs, nbr = [], []
    for b in range(B):
        team = b // robots
        for _ in range(rng.integers(0, 5)):
            obs.append(b)
            nbr.append(team * robots + rng.integers(0, robots))
    obs += [0, 0, B - 1]
    nbr += [1, 1, B - 1]  # a neighbour twice, a link to itself
    order = np.argsort(obs, kind="stable")
    obs = np.asarray(obs, dtype=np.int64)[order]
    nbr = np.asarray(nbr, dtype=np.int64)[order]
    E = len(obs)
    fused = rng.random(E) < 0.6
    fused[obs == 0] = True
    fused[-1] = True
    Bij = rng.normal(size=(E, 3, 3))
    Bij[rng.random(E) < 0.8, :, 2] = 0.0
    Bij[~fused] = np.nan  # (not fused: never read)
    A = np.eye(3) + 0.3 * rng.normal(size=(B, 3, 3))
    noise = rng.normal(size=(B, 3, 3))
    noise = noise @ np.swapaxes(noise, -1, -2)
    return joint, A, Bij, obs, nbr, fused, noise


def _dense_M(joint, A, Bij, obs, nbr, fused) -> np.ndarray:
    B, N = len(A), joint.N
    M = np.zeros((B, 3, 3 * N))
    for b in range(B):
        M[b, :, 3 * (b % N) : 3 * (b % N) + 3] = A[b]
    for e in np.flatnonzero(fused):
        c = 3 * (nbr[e] % N)
        M[obs[e], :, c : c + 3] += Bij[e]
    return M


@pytest.mark.parametrize("teams, robots", [(1, 5), (2, 17), (3, 6)])
def test_commit_computes_the_reference_end_of_step(teams: int, robots: int) -> None:
    """The commit hands ``M`` by its blocks (the dense ``M`` built where read equals the
    blocks scattered by hand, duplicates added) and computes the end of step from them and
    the rows ``M Sigma``: the compiled finish installs it, and it is the reference's
    ``finish`` on the dense ``M`` to 1e-12 relative; the joint and diagonal symmetric."""
    from resloc.cl.kernels_fusion_step import compiled_tracked_finish
    from resloc.cl.kernels_tracked_step import commit_tracked

    joint, A, Bij, obs, nbr, fused, noise = _records(teams, robots, seed=robots + teams)
    M = _dense_M(joint, A, Bij, obs, nbr, fused)
    n3 = 3 * robots
    rows = (M.reshape(teams, n3, n3) @ joint.sigma).reshape(-1, 3, n3)
    reference = copy.deepcopy(joint)
    reference.M, reference.noise = M.copy(), noise.copy()
    expected = reference.finish()
    state = _kernel_joint(A, Bij, nbr, noise, rows, robots)
    commit_tracked(state, joint, obs, fused)
    assert joint.end_of_step is not None  # computed from the blocks
    assert joint.updates == int(fused.sum())
    np.testing.assert_array_equal(joint.M, M)  # built from the blocks where read
    with kernels.use_backend("numba"):
        out = compiled_tracked_finish(joint)
    assert joint.end_of_step is None and joint.m_sigma is None  # installed, a step begun
    scale = np.abs(reference.sigma).max()
    np.testing.assert_allclose(joint.sigma, reference.sigma, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-12 * scale)
    np.testing.assert_array_equal(joint.sigma, np.swapaxes(joint.sigma, -1, -2))
    np.testing.assert_array_equal(out, joint.diagonal())


def test_non_finite_rows_leave_the_end_of_step_to_the_dense_path() -> None:
    """A non-finite entry in the rows: no end of step from the blocks (``0 * inf`` is
    ``nan`` in the reference's dense product, which the blocks skip); the compiled finish
    takes the dense path and gives the reference's non-finite joint."""
    from resloc.cl.kernels_fusion_step import compiled_tracked_finish
    from resloc.cl.kernels_tracked_step import commit_tracked

    joint, A, Bij, obs, nbr, fused, noise = _records(2, 6, seed=11)
    joint.sigma[1, 4, 7] = joint.sigma[1, 7, 4] = np.inf
    M = _dense_M(joint, A, Bij, obs, nbr, fused)
    with np.errstate(invalid="ignore"):
        rows = (M.reshape(2, 18, 18) @ joint.sigma).reshape(-1, 3, 18)
        reference = copy.deepcopy(joint)
        reference.M, reference.noise = M.copy(), noise.copy()
        reference.finish()
    state = _kernel_joint(A, Bij, nbr, noise, rows, 6)
    commit_tracked(state, joint, obs, fused)
    assert joint.end_of_step is None
    assert joint.updates == int(fused.sum())
    with kernels.use_backend("numba"), np.errstate(invalid="ignore"):
        out = compiled_tracked_finish(joint)
    assert out is not None
    np.testing.assert_array_equal(np.isnan(joint.sigma), np.isnan(reference.sigma))
    finite = np.isfinite(reference.sigma)
    np.testing.assert_allclose(joint.sigma[finite], reference.sigma[finite], atol=1e-12)


def test_a_reference_update_after_the_commit_drops_its_end_of_step() -> None:
    """After a compiled commit, a reference update (a second correction of the step) reads
    ``M`` built from the blocks and drops the commit's end of step: the finish is the
    reference's from the updated ``M``."""
    from resloc.cl.kernels_fusion_step import compiled_tracked_finish
    from resloc.cl.kernels_tracked_step import commit_tracked
    from resloc.filters.base import Moments

    joint, A, Bij, obs, nbr, fused, noise = _records(1, 5, seed=4)
    M = _dense_M(joint, A, Bij, obs, nbr, fused)
    rows = (M.reshape(1, 15, 15) @ joint.sigma).reshape(-1, 3, 15)
    reference = copy.deepcopy(joint)
    reference.M, reference.noise, reference.updates = M.copy(), noise.copy(), 1
    commit_tracked(_kernel_joint(A, Bij, nbr, noise, rows, 5), joint, obs, fused)
    m = Moments(np.zeros((1, 2)), np.eye(2)[None], 0.1 * np.ones((1, 3, 2)))
    x_i, x_j, R = np.array([[0.0, 0.0, 0.1]]), np.array([[1.0, 0.5, 0.0]]), 0.01 * np.eye(2)
    for target in (joint, reference):
        target.update(np.array([2]), np.array([3]), x_i, x_j, m, R)
    assert joint.end_of_step is None and joint.m_sigma is None
    expected = reference.finish()
    with kernels.use_backend("numba"):
        out = compiled_tracked_finish(joint)
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(joint.sigma, reference.sigma, rtol=0, atol=1e-12)


def test_the_prediction_leaves_the_corrections_rows() -> None:
    """The compiled prediction keeps a copy of the new joint, which the next correction's
    ``joint_state`` takes as its rows of ``M Sigma`` (equal to the joint's rows, not its
    memory; taken once); a joint reassigned since is copied anew."""
    from resloc.cl.kernels_fusion_step import compiled_tracked_predict
    from resloc.cl.kernels_joint import TRACKED, joint_state
    from resloc.cl.memory import LinkMemory

    joint, *_ = _records(2, 5, seed=2)
    rng = np.random.default_rng(0)
    x, u = rng.normal(size=(10, 3)), rng.normal(size=(10, 2))
    params = default_scenario().cl_params()
    memory = LinkMemory(10)
    memory.joint = joint
    i, j = np.array([0, 1, 5]), np.array([1, 2, 9])
    for reassigned in (False, True):
        with kernels.use_backend("numba"):
            assert compiled_tracked_predict(joint, x, u, 0.1, params) is not None
        if reassigned:
            joint.sigma = 2.0 * joint.sigma
        state = joint_state(TRACKED, memory, i, j)
        np.testing.assert_array_equal(state.rows, joint.sigma.reshape(10, 3, 15))
        assert not np.shares_memory(state.rows, joint.sigma)
        again = joint_state(TRACKED, memory, i, j)  # (the spare is used once)
        assert not np.shares_memory(again.rows, state.rows)


def test_later_gains_are_the_records_products() -> None:
    """``apply_later_gains`` (the joints' rounds defer each record's left products of the
    robot's earlier ``B_ij`` to the end of the step) equals the row-order records' products
    one link at a time (``B_ir <- G_e B_ir`` for every earlier fused ``r`` of the robot) to
    1e-12 relative: robots with zero, one and several fused links among unfused ones, most
    ``B_ij`` with a zero third column (which stays exactly zero), some without."""
    from resloc.cl.kernels_tracked_step import apply_later_gains

    rng = np.random.default_rng(5)
    obs = np.sort(rng.integers(0, 9, 80)).astype(np.int64)
    fused = rng.random(80) < 0.6
    fused[obs == 3] = False  # a robot with no fused link
    Bij = rng.normal(size=(80, 3, 3))
    zero = rng.random(80) < 0.8
    Bij[zero, :, 2] = 0.0
    gains = np.eye(3) + 0.4 * rng.normal(size=(80, 3, 3))
    expected = Bij.copy()
    for e in range(80):  # the row-order records: each gain on the robot's earlier fused B
        if fused[e]:
            for r in range(e):
                if fused[r] and obs[r] == obs[e]:
                    expected[r] = gains[e] @ expected[r]
    assert (np.bincount(obs[fused]) > 2).any()
    got = Bij.copy()
    apply_later_gains(got, gains, obs, fused)
    scale = np.abs(expected).max()
    np.testing.assert_allclose(got[fused], expected[fused], rtol=0, atol=1e-12 * scale)
    np.testing.assert_array_equal(got[~fused], Bij[~fused])  # unfused: not touched
    assert np.all(got[zero & fused][:, :, 2] == 0.0)


@pytest.mark.parametrize("name", ["ckf", "ekf"])
def test_the_commit_applies_the_gains_the_records_deferred(name: str, monkeypatch) -> None:
    """Two teams of the default scenario in lockstep with the reference (1e-9, the lockstep
    of ``test_kernels_joint``), the CKF through the joints' rounds and the EKF through the
    row-order loop: at every commit the records had kept each fused link's gain and left
    the robots' earlier ``B_ij`` as their own record wrote them (``-K H_j``, a zero third
    column); the commit's products changed exactly the blocks of fused links with a later
    fused link of their robot, and its end of step was installed."""
    from resloc.cl import kernels_joint
    from resloc.cl.kernels_joint import warm_up_joint_form
    from resloc.cl.kernels_rounds import LOOP_RUNS
    from test_kernels_joint import FILTERS, lockstep

    warm_up_joint_form()  # (its corrections are not the lockstep's)
    original = kernels_joint.commit_tracked
    seen = []

    def spy(state, joint, obs, fused):
        before = state.Bij.copy()
        original(state, joint, obs, fused)
        later = np.zeros(len(obs), dtype=bool)  # a fused link with a later fused one
        for e in np.flatnonzero(fused):
            later[e] = bool(np.any(fused[e + 1 :] & (obs[e + 1 :] == obs[e])))
        changed = np.any(state.Bij != before, axis=(1, 2))
        assert np.all(before[fused][:, :, 2] == 0.0)  # as each record wrote it
        np.testing.assert_array_equal(changed[fused], later[fused])
        seen.append((int(later.sum()), joint.end_of_step is not None))

    monkeypatch.setattr(kernels_joint, "commit_tracked", spy)
    params = replace(default_scenario().cl_params(), fusion="tracked")
    before = dict(LOOP_RUNS)
    steps = 20
    fused, _ = lockstep("tracked", FILTERS[name], params, steps, seed=23)
    assert fused > 0 and len(seen) == steps
    assert sum(n for n, _ in seen) > 0 and all(done for _, done in seen)
    loop = "joint_rounds" if name == "ckf" else "row_order"
    assert LOOP_RUNS[loop] - before[loop] >= steps
