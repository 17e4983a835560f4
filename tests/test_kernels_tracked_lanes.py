"""``tracked``'s records and end of step compiled: the records keep each robot's rows of
``M Sigma`` (the cross of its later links, :func:`resloc.cl.kernels_joint_records.tracked_record`),
the commit's end of step takes them as its first product and forms ``M U^T`` over ``M``'s
blocks (:mod:`resloc.cl.kernels_tracked_step`; the dense paths of
:func:`resloc.cl.kernels_fusion_step.compiled_tracked_finish` without it). Against numpy: the
rows are ``M Sigma`` of the reference's dense ``M``, and the end of step from the rows, from
the products over blocks and the reference's ``finish`` agree to 1e-12, with the joints'
rounds and the compiled end of step asserted to have run."""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest

from resloc.cl import kernels
from resloc.cl.kernels_inputs import KernelOutputs
from resloc.cl.kernels_plain import plain
from resloc.cl.kernels_rounds import LOOP_RUNS
from resloc.cl.tracking import JointCovariance
from resloc.experiments.config import default_scenario

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")


def _dense_products(joint: JointCovariance) -> np.ndarray:
    n3 = 3 * joint.N
    M = joint.M.reshape(joint.T, n3, n3)
    return (M @ joint.sigma).reshape(-1, 3, n3)


@pytest.mark.parametrize("name", ["ckf", "ukf"])
def test_records_keep_m_sigma_and_the_end_of_step_takes_it(name: str, monkeypatch) -> None:
    """Two teams of the default scenario in lockstep with the reference (1e-9, as
    ``test_kernels_joint``): at every compiled end of step the correction's commit left
    ``m_sigma``, which is ``M Sigma`` of the dense ``M`` to 1e-12, and the end of step
    from it equals the one that forms both products and the reference's ``finish``."""
    from resloc.cl import kernels_fusion_step as step_kernels
    from resloc.cl.backend import backend
    from resloc.cl.kernels_joint import warm_up_joint_form
    from test_kernels_joint import FILTERS, lockstep

    warm_up_joint_form()  # (its corrections are not the lockstep's)
    original = step_kernels.compiled_tracked_finish
    seen = []

    def checked(joint):
        if backend() != "numba":  # the lockstep's reference side
            return original(joint)
        assert joint.m_sigma is not None  # the records' rows were handed over
        assert joint.end_of_step is not None  # and the commit's end of step from M's blocks
        np.testing.assert_allclose(joint.m_sigma, _dense_products(joint), rtol=0, atol=1e-12)
        with_rows = copy.deepcopy(joint)  # the dense paths: from the rows, from products
        with_rows.end_of_step = None
        without_rows = copy.deepcopy(with_rows)
        without_rows.m_sigma = None
        reference = copy.deepcopy(joint)
        from_rows = original(with_rows)
        by_blocks = original(without_rows)
        expected = reference.finish()
        out = original(joint)
        for got, ran in ((out, joint), (from_rows, with_rows), (by_blocks, without_rows)):
            np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
            np.testing.assert_allclose(ran.sigma, reference.sigma, rtol=0, atol=1e-12)
        assert joint.m_sigma is None and joint.end_of_step is None  # the next step starts anew
        seen.append(True)
        return out

    monkeypatch.setattr(step_kernels, "compiled_tracked_finish", checked)
    params = replace(default_scenario().cl_params(), fusion="tracked")
    before = LOOP_RUNS["joint_rounds"]
    steps = 25
    fused, _ = lockstep("tracked", FILTERS[name], params, steps, seed=31)
    assert fused > 0
    assert LOOP_RUNS["joint_rounds"] - before == steps
    assert len(seen) == steps


@pytest.mark.parametrize("teams, robots", [(1, 5), (2, 17), (3, 6)])
def test_end_of_step_over_blocks_is_the_dense_product(teams: int, robots: int) -> None:
    """The compiled end of step forms ``M Sigma M^T`` over the non-zero blocks of a random
    block-sparse ``M`` (blocks with a zero first entry, blocks zero but one entry), with
    ``M Sigma`` given (the records' rows) or not: the reference's ``finish`` to 1e-12; a
    non-finite entry of ``Sigma`` takes the dense products (``0 * inf`` is ``nan``), as the
    reference."""
    from resloc.cl.kernels_fusion_step import compiled_tracked_finish

    rng = np.random.default_rng(7 * teams + robots)
    B, n3 = teams * robots, 3 * robots
    P0 = np.broadcast_to(0.1 * np.eye(3), (B, 3, 3)).copy()
    joint = JointCovariance(P0, robots)
    G = rng.normal(size=(teams, n3, n3))
    joint.sigma = G @ np.swapaxes(G, -1, -2) / n3
    M = np.zeros((B, 3, n3))
    for b in range(B):
        for c in range(robots):
            kind = rng.integers(0, 4)
            block = rng.normal(size=(3, 3))
            if c == b % robots or kind == 0:
                M[b, :, 3 * c : 3 * c + 3] = block
            elif kind == 1:
                block[0, 0] = 0.0
                M[b, :, 3 * c : 3 * c + 3] = block
            elif kind == 2:
                M[b, rng.integers(0, 3), 3 * c + rng.integers(0, 3)] = rng.normal()
    noise = rng.normal(size=(B, 3, 3))
    joint.M, joint.noise, joint.updates = M, noise @ np.swapaxes(noise, -1, -2), 1
    for broken, rows in ((False, False), (False, True), (True, False), (True, True)):
        if broken:
            joint.sigma[0, 1, 4] = joint.sigma[0, 4, 1] = np.inf
        reference = copy.deepcopy(joint)
        compiled = copy.deepcopy(joint)
        if rows:  # the first product given, as a compiled correction's commit leaves it
            with np.errstate(invalid="ignore"):
                compiled.m_sigma = _dense_products(compiled)
        with np.errstate(invalid="ignore"):
            expected = reference.finish()
        with kernels.use_backend("numba"):
            out = compiled_tracked_finish(compiled)
        assert out is not None
        np.testing.assert_allclose(out, expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(compiled.sigma, reference.sigma, rtol=0, atol=1e-12)
        if broken:
            assert np.isnan(compiled.sigma).any()


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=float).view(np.int64)


@pytest.mark.parametrize("n", [5, 17, 30])
def test_tracked_record_lanes_are_the_scalar_record(n: int) -> None:
    """:func:`~resloc.cl.kernels_tracked_lanes.tracked_record_lanes` (the arithmetic over the
    fused lanes in SIMD) against the scalar record (the ``tracked`` branch of
    ``joint_record_lanes``, ``tracked_record`` lane by lane) on the same round: the joint's
    ``A``, ``B_ij`` (the earlier rows left to the commit by both), the fused lanes' gains,
    noise and rows of ``M Sigma``, ``P``, ``now`` and the repaired flags the same to the
    bit. Each lane has three earlier rows (some fused), some lanes are not fused (left
    alone), one lane's robots are closer than the minimum range, and the
    random blocks give posteriors that need the repair. ``n`` below one block of lanes,
    not a multiple of it, and above."""
    from resloc.cl.kernels_joint import joint_state
    from resloc.cl.kernels_joint_lanes import LANE_STRIDE
    from resloc.cl.kernels_joint_rounds import joint_record_lanes
    from resloc.cl.kernels_lanes import CHUNK
    from resloc.cl.kernels_link_stages import UPDATE_ROWS
    from resloc.cl.kernels_round_stages import link_scratch
    from resloc.cl.kernels_tracked_lanes import (
        RECORD_INPUT_ROWS,
        RECORD_OUTPUT_ROWS,
        tracked_record_lanes,
    )
    from resloc.cl.memory import LinkMemory

    rng = np.random.default_rng(90 + n)
    B = n + 3
    rows_per_lane = 4
    E = n * rows_per_lane
    obs = rng.permutation(B)[:n].astype(np.int64)
    li = np.repeat(obs, rows_per_lane)
    lj = (li + 1 + rng.integers(0, B - 1, E)) % B
    memory = LinkMemory(B)
    G = rng.normal(size=(3 * B, 3 * B))
    memory.joint = JointCovariance(np.broadcast_to(np.eye(3), (B, 3, 3)).copy(), B)
    memory.joint.sigma = (G @ G.T / (3 * B))[None]
    joint = joint_state(1, memory, li, lj)  # TRACKED
    joint.A[:] = np.eye(3) + 0.2 * rng.normal(size=(B, 3, 3))  # earlier updates' records
    N0 = rng.normal(size=(B, 3, 3))
    joint.noise[:] = 0.01 * N0 @ np.swapaxes(N0, -1, -2)
    joint.Bij[:] = 0.3 * rng.normal(size=(E, 3, 3))
    joint.rows[:] += 0.1 * rng.normal(size=joint.rows.shape)
    lane_e = np.zeros(CHUNK, np.int64)
    lane_first = np.zeros(CHUNK, np.int64)
    lane_e[:n] = np.arange(n) * rows_per_lane + rows_per_lane - 1
    lane_first[:n] = np.arange(n) * rows_per_lane
    o = np.zeros(CHUNK, np.int64)
    o[:n] = obs
    flags = np.zeros((5, E), dtype=np.bool_)
    flags[3] = rng.random(E) < 0.5  # the earlier rows that fused
    decision = np.zeros((4, CHUNK))
    decision[3, :n] = (rng.random(n) < 0.75).astype(float)
    decision[3, 0] = decision[3, n - 1] = 1.0
    decision[3, 1] = 0.0
    flags[3, lane_e[:n]] = decision[3, :n] == 1.0
    xi = rng.uniform(-5, 5, size=(3, CHUNK))
    xr = rng.uniform(-5, 5, size=(2, CHUNK))
    xr[:, 2] = xi[:2, 2] + 1e-9  # closer than the minimum range
    update = np.zeros((UPDATE_ROWS, CHUNK))
    update[16:22] = 0.3 * rng.normal(size=(6, CHUNK))
    blocks = np.zeros((27, LANE_STRIDE))
    for c in range(n):
        J = rng.normal(size=(6, 6))
        J = 0.05 * J @ J.T + (0.5 * np.eye(6) if c % 3 else 0.0)
        J[:3, 3:] += rng.normal(size=(3, 3)) * (0.3 if c % 4 == 0 else 0.0)  # not a joint
        J += 1e-3 * rng.normal(size=(6, 6))  # (not exactly symmetric: a transpose shows)
        blocks[:9, c] = J[:3, :3].ravel()
        blocks[9:18, c] = J[:3, 3:].ravel()
        blocks[18:, c] = J[3:, 3:].ravel()
    blocks[:, 3] = 0.0
    blocks[[0, 4, 8], 3] = -1.0  # P_i negative definite: the posterior needs the repair
    decision[3, 3] = 1.0
    flags[3, lane_e[3]] = True
    R = np.diag([0.01, 0.002])
    P = np.broadcast_to(0.1 * np.eye(3), (B, 3, 3)).copy()
    now = rng.normal(size=(B, 3, 3))
    state = [
        (copy.deepcopy(joint), P.copy(), now.copy(), flags.copy()) for _ in range(2)
    ]  # scalar, lanes
    j0, P0, now0, flags0 = state[0]
    # the loops' own structures (plain(joint), KernelOutputs): another form of either would
    # compile another specialization of the stages
    out = KernelOutputs(np.zeros(E), np.zeros(E), flags0)
    joint_record_lanes(
        plain(j0), P0, lane_e, lane_first, o, np.int64(n), xi, xr, update, decision, R, out,
        link_scratch(), now0, blocks,
    )  # fmt: skip
    j1, P1, now1, flags1 = state[1]
    fused = tracked_record_lanes(
        plain(j1), P1, lane_e, o, np.int64(n), xi, xr, update, decision, R, flags1, now1, blocks,
        np.zeros(CHUNK, np.int64), np.zeros((RECORD_INPUT_ROWS, LANE_STRIDE)),
        np.zeros((RECORD_OUTPUT_ROWS, LANE_STRIDE)), np.zeros((3, 3)), np.zeros((3, 3)),
        np.zeros((3, 3)),
    )  # fmt: skip
    assert fused == int(decision[3, :n].sum())
    lanes = lane_e[:n][decision[3, :n] == 1.0]
    np.testing.assert_array_equal(_bits(j1.gains[lanes]), _bits(j0.gains[lanes]))
    for name in ("A", "Bij", "noise", "rows"):
        np.testing.assert_array_equal(
            _bits(getattr(j1, name)), _bits(getattr(j0, name)), err_msg=name
        )
    np.testing.assert_array_equal(_bits(P1), _bits(P0))
    np.testing.assert_array_equal(_bits(now1), _bits(now0))
    np.testing.assert_array_equal(flags1, flags0)
    repaired = flags0[4, lane_e[:n]]
    assert repaired.any() and not repaired.all()
    assert not np.array_equal(j0.A, joint.A)  # the records ran
    np.testing.assert_array_equal(j0.A[obs[1]], joint.A[obs[1]])  # lane 1 did not fuse


@pytest.mark.parametrize("n", [5, 17, 30])
def test_tracked_cross_lanes_are_the_scalar_cross(n: int) -> None:
    """:func:`~resloc.cl.kernels_tracked_lanes.tracked_cross_lanes` against the scalar pieces
    it replaced (``tracked_cross`` and ``_joint_into_lane``, lane by lane): the blocks, the
    joint's lower triangle and ``now`` the same to the bit, for lanes at a robot's first
    link (``Sigma_ii``, not exactly symmetric here) and later ones (``now[i]``), two teams."""
    from resloc.cl.kernels_joint import joint_state
    from resloc.cl.kernels_joint_lanes import LANE_STRIDE
    from resloc.cl.kernels_joint_links import tracked_cross
    from resloc.cl.kernels_joint_rounds import _joint_into_lane
    from resloc.cl.kernels_lanes import CHUNK
    from resloc.cl.kernels_tracked_lanes import tracked_cross_lanes
    from resloc.cl.memory import LinkMemory

    rng = np.random.default_rng(60 + n)
    N = n + 2
    B = 2 * N
    obs = rng.permutation(B)[:n].astype(np.int64)
    nbr = (obs // N) * N + (obs % N + 1 + rng.integers(0, N - 1, n)) % N  # teammates
    E = 2 * n  # each lane's row and an earlier one of its robot
    li = np.repeat(obs, 2)
    lj = np.repeat(nbr, 2)
    memory = LinkMemory(B)
    memory.joint = JointCovariance(np.broadcast_to(np.eye(3), (B, 3, 3)).copy(), N)
    memory.joint.sigma = rng.normal(size=(2, 3 * N, 3 * N))  # (not symmetric: the sym shows)
    joint = joint_state(1, memory, li, lj)  # TRACKED
    joint.rows[:] = rng.normal(size=joint.rows.shape)
    lane_e = np.zeros(CHUNK, np.int64)
    lane_first = np.zeros(CHUNK, np.int64)
    lane_e[:n] = 2 * np.arange(n) + 1
    first = rng.random(n) < 0.5
    lane_first[:n] = np.where(first, lane_e[:n], lane_e[:n] - 1)
    o = np.zeros(CHUNK, np.int64)
    o[:n] = obs
    now = rng.normal(size=(B, 3, 3))
    fused = np.zeros(E, dtype=np.bool_)
    blocks_ref = np.zeros((27, LANE_STRIDE))
    J_ref = np.zeros((21, LANE_STRIDE))
    now_ref = now.copy()
    for c in range(n):  # the scalar pieces, as joint_factor_lanes ran them
        i = obs[c]
        if not first[c]:
            joint.work[4] = now_ref[i]
        tracked_cross(joint, lane_e[c], lane_first[c], fused, i)
        now_ref[i] = joint.work[4]
        _joint_into_lane(joint.work, joint.J6, blocks_ref, J_ref, c)
    blocks = np.zeros((27, LANE_STRIDE))
    J = np.zeros((21, LANE_STRIDE))
    tracked_cross_lanes(plain(joint), lane_e, lane_first, o, np.int64(n), now, blocks, J)
    np.testing.assert_array_equal(_bits(blocks[:, :n]), _bits(blocks_ref[:, :n]))
    np.testing.assert_array_equal(_bits(J[:, :n]), _bits(J_ref[:, :n]))
    np.testing.assert_array_equal(_bits(now), _bits(now_ref))
    assert first.any() and not first.all()


def _random_joint(teams: int, robots: int, seed: int) -> JointCovariance:
    rng = np.random.default_rng(seed)
    B, n3 = teams * robots, 3 * robots
    joint = JointCovariance(np.broadcast_to(0.1 * np.eye(3), (B, 3, 3)).copy(), robots)
    G = rng.normal(size=(teams, n3, n3))
    joint.sigma = G @ np.swapaxes(G, -1, -2) / n3
    return joint


@pytest.mark.parametrize("teams, robots", [(1, 5), (2, 17)])
def test_compiled_prediction_leaves_the_joint_it_started_from(teams: int, robots: int) -> None:
    """The compiled prediction writes the propagated joint into a new array in its first
    pass (no copy of the joint first): the reference's prediction to 1e-12, its diagonal
    blocks returned, and the array the joint held before (a caller may keep it, as the
    reference's new array leaves it) unchanged to the bit."""
    from resloc.cl.kernels_fusion_step import compiled_tracked_predict
    from resloc.models.motion import process_noise

    rng = np.random.default_rng(robots)
    joint = _random_joint(teams, robots, seed=3 * robots)
    B = teams * robots
    x = rng.normal(size=(B, 3))
    u = np.column_stack([rng.uniform(0.1, 1.0, B), rng.normal(0.0, 0.3, B)])
    dt = 0.1
    params = default_scenario().cl_params()
    reference = copy.deepcopy(joint)
    Q = process_noise(x, dt, np.asarray(params.odometry_std), np.asarray(params.process_floor_std))
    expected = reference.predict(x, u, dt, Q)
    held = joint.sigma
    held_bits = held.copy()
    with kernels.use_backend("numba"):
        out = compiled_tracked_predict(joint, x, u, dt, params)
    assert out is not None
    assert joint.sigma is not held
    np.testing.assert_array_equal(_bits(held), _bits(held_bits))
    np.testing.assert_allclose(joint.sigma, reference.sigma, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(_bits(out), _bits(joint.diagonal()))


def test_a_step_builds_its_maps_where_first_read() -> None:
    """A step starts without building ``M`` and the noise (a compiled step starts twice,
    at its end and at the next prediction, and its commit hands both over): they are built
    where first read, ``M`` every robot's own identity block and the noise zero, and a write
    into them stays (the reference's ``update`` writes rows of both in place) until the next
    step starts."""
    joint = _random_joint(2, 4, seed=5)
    joint.finish()  # (the end of a step starts the next)
    assert joint._M is None and joint._noise is None
    expected = np.zeros((8, 3, 12))
    for b in range(8):
        expected[b, :, 3 * (b % 4) : 3 * (b % 4) + 3] = np.eye(3)
    np.testing.assert_array_equal(joint.M, expected)
    np.testing.assert_array_equal(joint.noise, np.zeros((8, 3, 3)))
    joint.M[1, 0, 5] = 2.0
    joint.noise[2, 1, 1] = 3.0
    assert joint.M[1, 0, 5] == 2.0 and joint.noise[2, 1, 1] == 3.0
    sigma = joint.sigma.copy()
    joint.finish()  # the written M and noise enter the end of step
    M = expected.copy()
    M[1, 0, 5] = 2.0
    noise = np.zeros((8, 3, 3))
    noise[2, 1, 1] = 3.0
    Mt = M.reshape(2, 12, 12)
    dense = Mt @ sigma @ np.swapaxes(Mt, -1, -2)
    for b in range(8):
        t, c = divmod(b, 4)
        dense[t, 3 * c : 3 * c + 3, 3 * c : 3 * c + 3] += noise[b]
    np.testing.assert_allclose(joint.sigma, 0.5 * (dense + np.swapaxes(dense, -1, -2)), atol=1e-12)
    np.testing.assert_array_equal(joint.M, expected)  # the next step's start
    np.testing.assert_array_equal(joint.noise, np.zeros((8, 3, 3)))


def test_compiled_prediction_takes_each_robots_odometry_noise() -> None:
    """Per-robot odometry standard deviations ``(B, 2)`` (checked once per ``params``, not
    per step): the compiled prediction is the reference's to 1e-12; with another number of
    robots' deviations, or a floor of another shape, it refuses (None: the reference runs)
    and leaves the joint as it was."""
    import dataclasses

    from resloc.cl.kernels_fusion_step import compiled_tracked_predict
    from resloc.models.motion import process_noise

    teams, robots = 2, 5
    B = teams * robots
    rng = np.random.default_rng(11)
    x = rng.normal(size=(B, 3))
    u = np.column_stack([rng.uniform(0.1, 1.0, B), rng.normal(0.0, 0.3, B)])
    dt = 0.1
    base = default_scenario().cl_params()
    odometry = rng.uniform(0.01, 0.2, size=(B, 2))
    params = dataclasses.replace(base, odometry_std=odometry)
    joint = _random_joint(teams, robots, seed=7)
    reference = copy.deepcopy(joint)
    Q = process_noise(x, dt, odometry, np.asarray(params.process_floor_std))
    expected = reference.predict(x, u, dt, Q)
    with kernels.use_backend("numba"):
        out = compiled_tracked_predict(joint, x, u, dt, params)
    assert out is not None
    np.testing.assert_allclose(joint.sigma, reference.sigma, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-12)
    for wrong in (
        dataclasses.replace(base, odometry_std=odometry[:-1]),  # B - 1 robots' deviations
        dataclasses.replace(base, odometry_std=odometry[:, :1]),
        dataclasses.replace(base, process_floor_std=np.ones(2)),
    ):
        held = joint.sigma
        with kernels.use_backend("numba"):
            assert compiled_tracked_predict(joint, x, u, dt, wrong) is None
        assert joint.sigma is held
