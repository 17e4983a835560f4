"""The link loop in rounds (:mod:`resloc.cl.kernels_rounds`) against the row-order loop and
the numpy reference: same estimates, covariances and decisions to 1e-9 on random batches
with falsified measurements (detector rejections), failing channels (jamming), untriggered
links, covariances that need Cholesky jitter and repairs, over multi-step runs, with the
loop that ran asserted; its fallback to the row-order loop; the branch-free lane math
(:mod:`resloc.cl.kernels_lanes`) against libm; the caller-owned state buffers. The options
in the rounds: ``tests/test_kernels_round_options.py``."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world
from resloc.cl import CLParams, LinkBatch, LinkMemory, ThresholdInnovation, correct, kernels
from resloc.cl import kernels_rounds as rounds
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.step import predict
from resloc.experiments.config import default_scenario
from test_engine import (
    FILTERS,
    PARAM_CASES,
    assert_equivalent,
    lockstep_both_backends,
    random_batch,
)

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

SIGMA_FILTERS = ["ckf", "ukf", "ckf-arith"]


def _compiled(filt, x, P, links, params, memory=None, loop="rounds"):
    """The compiled correction by the loop ``loop`` (``rounds`` or ``row_order``), asserting
    that this loop ran (and no fallback)."""
    before = rounds.LOOP_RUNS.copy()
    saved = rounds.ROUNDS_MIN_LINKS
    rounds.ROUNDS_MIN_LINKS = 1 if loop == "rounds" else 10**18
    try:
        with kernels.use_backend("numba"):
            res = correct(filt, x, P, links, params, memory)
    finally:
        rounds.ROUNDS_MIN_LINKS = saved
    ran = rounds.LOOP_RUNS - before
    assert res[2].compiled
    assert ran == {loop: 1}, f"expected the {loop} loop, ran {dict(ran)}"
    return res


def _reference(filt, x, P, links, params, memory=None):
    with kernels.use_backend("numpy"):
        return correct(filt, x, P, links, params, memory)


def assert_same_loops(a, b, tol: float = 1e-9) -> None:
    """Two compiled corrections agree (estimates, covariances, every decision)."""
    (xa, Pa, oa), (xb, Pb, ob) = a, b
    assert np.abs(xa - xb).max() <= tol
    assert np.abs(Pa - Pb).max() <= tol
    np.testing.assert_allclose(oa.norm, ob.norm, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(oa.threshold, ob.threshold, rtol=1e-12, equal_nan=True)
    for name in ("detected", "triggered", "delivered", "fused", "repaired"):
        np.testing.assert_array_equal(getattr(oa, name), getattr(ob, name), err_msg=name)


@pytest.mark.parametrize("case", list(PARAM_CASES))
@pytest.mark.parametrize("name", SIGMA_FILTERS)
def test_rounds_equal_row_order_and_reference(name: str, case: str) -> None:
    params = PARAM_CASES[case]
    filt = FILTERS[name]
    decided = np.zeros(4, dtype=int)
    for seed in range(3):
        x, P, links = random_batch(100 + seed, B=120, outliers=0.2, fail=0.3)
        by_rounds = _compiled(filt, x, P, links, params)
        assert_same_loops(by_rounds, _compiled(filt, x, P, links, params, loop="row_order"))
        ref = _reference(filt, x, P, links, params)
        assert_equivalent(by_rounds, ref)
        out = ref[2]
        decided += [out.detected.sum(), out.triggered.sum(), out.delivered.sum(), 0]
        decided[3] += (out.triggered & ~out.delivered).sum()  # jammed
    if params.detector:
        assert decided[0] > 0, "no measurement was rejected"
    assert decided[2] > 0 and decided[3] > 0, "no delivery, or no jammed link"


def test_rounds_with_per_robot_gains_and_last_sent_memory() -> None:
    rng = np.random.default_rng(0)
    B = 120
    params = CLParams(
        range_std=0.02, bearing_std=0.03, rho=rng.uniform(0.3, 2.0, B),
        alpha=rng.uniform(0.0, 0.2, B), gamma=rng.uniform(0, 2, B),
        zeta_s=rng.uniform(0, 1, B), zeta_c=rng.uniform(0, 1, B),
        threshold_innovation=ThresholdInnovation.LAST_SENT,
    )  # fmt: skip
    mem_rounds, mem_ref = LinkMemory(B), LinkMemory(B)
    for seed in (3, 4, 5):  # later calls read the norms earlier ones stored
        x, P, links = random_batch(seed, B=B)
        fast = _compiled(FILTERS["ckf"], x, P, links, params, mem_rounds)
        assert_equivalent(fast, _reference(FILTERS["ckf"], x, P, links, params, mem_ref))
    assert len(mem_ref) > 0
    np.testing.assert_allclose(mem_rounds.last_norm, mem_ref.last_norm, rtol=1e-12)


def test_rounds_with_jitter_and_repairs() -> None:
    """Singular covariances (the factor needs jitter) and updates that leave a covariance
    not positive definite (repaired), as the row-order loop does them."""
    x, P, links = random_batch(7, B=120)
    P = P.copy()
    P[::5] = np.diag([0.04, 0.04, 0.0])  # singular: chol3 escalates its jitter
    links = replace(links, P_nb=P[links.j].copy())
    params = CLParams(range_std=1e-4, bearing_std=1e-4, rho=1e6, alpha=0.0)
    by_rounds = _compiled(FILTERS["ckf"], x, P, links, params)
    assert_same_loops(by_rounds, _compiled(FILTERS["ckf"], x, P, links, params, loop="row_order"))
    assert_equivalent(by_rounds, _reference(FILTERS["ckf"], x, P, links, params))
    assert by_rounds[2].fused.sum() > len(x) // 2


def test_rounds_fall_back_to_row_order_on_a_special_case() -> None:
    """A measured bearing outside (-2 pi, 2 pi) is a case the lanes do not take: the
    whole correction is redone in row order, with the same result as the reference."""
    x, P, links = random_batch(8, B=120)
    z = links.z.copy()
    z[len(z) // 2, 1] = 7.5
    links = replace(links, z=z)
    params = PARAM_CASES["paper"]
    before = rounds.LOOP_RUNS.copy()
    with kernels.use_backend("numba"):
        fast = correct(FILTERS["ckf"], x, P, links, params)
    assert rounds.LOOP_RUNS - before == {"rounds_fallback": 1, "row_order": 1}
    assert_equivalent(fast, _reference(FILTERS["ckf"], x, P, links, params))


def test_rounds_give_way_on_rows_not_sorted_by_observer() -> None:
    """Rows out of observer order would put a robot in two lanes of one round: the row-order
    loop runs instead (same result as asking for it)."""
    x, P, links = random_batch(11, B=120)
    order = np.r_[np.arange(60, len(links.i)), np.arange(60)]
    shuffled = LinkBatch(
        links.i[order], links.j[order], links.z[order], links.x_nb[order], links.P_nb[order],
        links.channel_ok[order], links.risk_s, links.risk_c, links.lambda2,
    )  # fmt: skip
    params = PARAM_CASES["paper"]
    before = rounds.LOOP_RUNS.copy()
    with kernels.use_backend("numba"):
        got = correct(FILTERS["ckf"], x, P, shuffled, params)
    assert rounds.LOOP_RUNS - before == {"rounds_fallback": 1, "row_order": 1}
    assert_same_loops(got, _compiled(FILTERS["ckf"], x, P, shuffled, params, loop="row_order"))


@pytest.mark.parametrize(
    ("name", "changes"),
    [
        ("ekf", {}),
        ("ekf", {"fusion": "ci", "cusum": True}),
        # (the CKF's run their own rounds: tests/test_kernels_joint_rounds.py)
        ("ekf", {"fusion": "tracked"}),
        ("ckf", {"fusion": "factorized", "recovery": True}),
    ],
)
def test_rounds_leave_what_they_do_not_cover_to_the_row_order_loop(name, changes) -> None:
    x, P, links = random_batch(9, B=120)
    params = replace(PARAM_CASES["paper"], **changes)
    memory = LinkMemory(len(x))
    fusion_strategy(params.fusion).init(memory, x, P, len(x))
    if params.fusion == "split_ci":  # the neighbours' independent parts travel with them
        links = replace(links, P_nb_ind=0.5 * links.P_nb)
    before = rounds.LOOP_RUNS.copy()
    with kernels.use_backend("numba"):
        res = correct(FILTERS[name], x, P, links, params, memory)
    assert res[2].compiled
    assert rounds.LOOP_RUNS - before == {"row_order": 1}


@pytest.mark.parametrize("name", ["ckf", "ukf"])
def test_rounds_over_a_run_of_the_default_scenario(name: str) -> None:
    """Two batched trials (34 robots, ~100 links a step: the rounds run) for 80 steps in
    lockstep with the reference; every step compared inside."""
    sc = default_scenario()
    world = default_world(2, 5, scenario=sc)
    before = rounds.LOOP_RUNS.copy()
    detected = 0
    for res, _ in lockstep_both_backends(world, FILTERS[name], sc.cl_params(), 80):
        detected += int(res["numpy"][2].detected.sum())
    ran = rounds.LOOP_RUNS - before
    assert ran["rounds"] >= 70 and "rounds_fallback" not in ran, dict(ran)
    assert detected > 0


# ---------------------------------------------------------------------------------------
# The lane math
# ---------------------------------------------------------------------------------------
def _lane_loops():
    """The lane functions over arrays in compiled loops (as the kernels run them)."""
    import numba

    from resloc.cl.kernels_lanes import atan2_lanes, sincos_lanes, wrap_lanes

    @numba.njit
    def atan2_loop(y, x, out):
        for k in range(y.shape[0]):
            out[k] = atan2_lanes(y[k], x[k])

    @numba.njit
    def sincos_loop(a, s, c):
        for k in range(a.shape[0]):
            s[k], c[k] = sincos_lanes(a[k])

    @numba.njit
    def wrap_loop(a, out):
        for k in range(a.shape[0]):
            out[k] = wrap_lanes(a[k])

    return atan2_loop, sincos_loop, wrap_loop


def test_atan2_lanes_equals_libm() -> None:
    from resloc.cl.kernels_lanes import atan2_lanes

    rng = np.random.default_rng(1)
    y = np.concatenate([rng.normal(size=200_000), [0.0, -0.0, 1.0, -1.0, 1e-300, 3.0]])
    x = np.concatenate([rng.normal(size=200_000), [1.0, -1.0, 0.0, 0.0, -1e-300, 3.0]])
    scale = 10.0 ** rng.uniform(-8, 8, len(x))
    got = np.empty_like(x)
    _lane_loops()[0](y * scale, x * scale, got)
    assert np.abs(got - np.arctan2(y * scale, x * scale)).max() <= 2.5e-16 * math.pi
    py = getattr(atan2_lanes, "py_func", atan2_lanes)
    assert py(-0.0, -1.0) == math.atan2(-0.0, -1.0) and py(0.5, 0.25) == pytest.approx(
        math.atan2(0.5, 0.25), abs=1e-16
    )


def test_sincos_lanes_equals_libm() -> None:
    from resloc.cl.kernels_lanes import SINCOS_LANES_MAX

    rng = np.random.default_rng(2)
    a = np.concatenate(
        [rng.uniform(-SINCOS_LANES_MAX, SINCOS_LANES_MAX, 200_000), rng.uniform(-4, 4, 100_000)]
    )
    a = np.concatenate([a, np.arange(-40, 41) * (math.pi / 4), [0.0, -0.0, math.pi, -math.pi]])
    s, c = np.empty_like(a), np.empty_like(a)
    _lane_loops()[1](a, s, c)
    assert np.abs(s - np.sin(a)).max() <= 3e-16
    assert np.abs(c - np.cos(a)).max() <= 3e-16


def test_wrap_lanes_equals_wrap_bit_for_bit() -> None:
    from resloc.angles import wrap_angle

    rng = np.random.default_rng(3)
    a = np.concatenate(
        [rng.uniform(-3 * math.pi, 3 * math.pi, 200_000), [-math.pi, math.pi, 2 * math.pi]]
    )
    a = np.concatenate([a, [-2 * math.pi, 0.0, -3 * math.pi, np.nextafter(3 * math.pi, 0)]])
    got = np.empty_like(a)
    _lane_loops()[2](a, got)
    np.testing.assert_array_equal(got, wrap_angle(a))


# ---------------------------------------------------------------------------------------
# Caller-owned state buffers
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_buffers_give_the_same_step(backend: str) -> None:
    x, P, links = random_batch(10, B=120)
    params = PARAM_CASES["paper"]
    filt = FILTERS["ckf"]
    u = np.tile([0.1, 0.05], (len(x), 1))
    with kernels.use_backend(backend):
        xp, Pp = predict(filt, x, P, u, 0.1, params)
        spare = (np.full_like(x, np.nan), np.full_like(P, np.nan))
        xb, Pb = predict(filt, x, P, u, 0.1, params, spare)
        assert xb is spare[0] and Pb is spare[1]
        np.testing.assert_array_equal(xb, xp)
        np.testing.assert_array_equal(Pb, Pp)
        links = LinkBatch.from_predicted(
            links.i, links.j, links.z, xp, Pp, links.channel_ok, links.risk_s, links.risk_c,
            links.lambda2,
        )  # fmt: skip
        new = correct(filt, xp, Pp, links, params)
        into = (np.full_like(x, np.nan), np.full_like(P, np.nan))
        buffered = correct(filt, xp, Pp, links, params, None, into)
    assert buffered[0] is into[0] and buffered[1] is into[1]
    np.testing.assert_array_equal(buffered[0], new[0])
    np.testing.assert_array_equal(buffered[1], new[1])
    np.testing.assert_array_equal(buffered[2].fused, new[2].fused)


def test_buffers_are_checked() -> None:
    x, P, links = random_batch(10, B=20)
    params = PARAM_CASES["paper"]
    filt = FILTERS["ckf"]
    u = np.zeros((len(x), 2))
    with pytest.raises(ValueError, match="share memory"):
        predict(filt, x, P, u, 0.1, params, (x, P.copy()))
    with pytest.raises(ValueError, match="share memory"):
        correct(filt, x, P, links, params, None, (np.empty_like(x), P))
    x_sent, P_sent = x.copy(), P.copy()  # the neighbours' transmitted estimates, by row
    by_row = LinkBatch.from_predicted(
        links.i, links.j, links.z, x_sent, P_sent, links.channel_ok, links.risk_s,
        links.risk_c, links.lambda2,
    )  # fmt: skip
    with pytest.raises(ValueError, match="share memory"):
        correct(filt, x, P, by_row, params, None, (x_sent, np.empty_like(P)))
    with pytest.raises(ValueError, match="the P buffer must be"):
        correct(filt, x, P, links, params, None, (np.empty_like(x), np.empty((3, 3, 3))))
    with pytest.raises(ValueError, match="pair"):
        correct(filt, x, P, links, params, None, np.empty_like(x))
