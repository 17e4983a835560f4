"""``cached``'s second pass ahead of the decisions (:mod:`resloc.cl.kernels_round_cached`):
lanes ``n .. 2n - 1`` of a round, the same links with j's transmitted estimate through the
vectorized stages, give a delivered lane the moments and update of the second pass lane by
lane (:func:`~resloc.cl.kernels_round_stages.inflated_moments`, the row-order loop's
pieces), and leave it the lanes the vectorized stages cannot take. The whole rounds with
``cached`` against the row-order loop and the reference: tests/test_kernels_round_options.py
(cases ``cached*``)."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.cl import kernels
from resloc.filters import make_filter

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")


def _spd(rng, scale: float) -> np.ndarray:
    A = rng.normal(size=(3, 3))
    return scale * (A @ A.T + 0.5 * np.eye(3))


def _round(n: int, singular: int | None, seed: int):
    """One round of ``n`` lanes (robot ``c`` observes robot ``(c + 1) % n``) through the
    rounds' first pass with ``2n`` lanes as :func:`resloc.cl.kernels_rounds._rounds` runs it
    for ``cached``; ``singular``: a lane whose transmitted covariance needs jitter."""
    from resloc.cl.kernels import filter_kernel_spec
    from resloc.cl.kernels_lanes import CHUNK
    from resloc.cl.kernels_link_stages import (
        UPDATE_ROWS,
        chol_jitter_lanes,
        chol_lanes,
        gather_lanes,
        kalman_lanes,
        load_covariances,
        load_robot_covariances,
        moment_scratch,
        moments_lanes,
        point_axes,
        points_lanes,
    )
    from resloc.cl.kernels_round_cached import fresh_covariances, fresh_lanes, lanes_ahead
    from resloc.cl.kernels_round_stages import retry_lanes

    rng = np.random.default_rng(seed)
    filt = tuple(filter_kernel_spec(make_filter("ckf")))
    nz_idx, nz_val, nz_cnt, Wm, Wc, circular = filt[1:]
    m = Wm.shape[0]
    x = np.column_stack([rng.uniform(-5, 5, (n, 2)), rng.uniform(-3, 3, n)])
    P = np.stack([_spd(rng, 0.05) for _ in range(n)])
    li = np.arange(n, dtype=np.int64)
    nb = np.arange(n, dtype=np.int64)  # cached: per-link rows
    lj = (li + 1) % n
    x_nb = x[lj] + rng.normal(0.0, 0.01, (n, 3))
    P_nb = P[lj] * 1.1
    x_ref = x[lj] + rng.normal(0.0, 0.2, (n, 3))  # the cached estimates
    P_ref = P[lj] * 0.9
    if singular is not None:  # PSD, not PD: chol3 needs jitter
        v = rng.normal(size=3)
        P_nb[singular] = 0.05 * np.outer(v, v)
    z = np.column_stack([np.hypot(*(x[lj, :2] - x[:, :2]).T) + 0.05, rng.uniform(-1, 1, n)])
    R = np.diag([0.01, 0.003])
    jitter = np.array([0.0, 1e-12, 1e-9, 1e-6, 1e-3])
    C = CHUNK
    (lane_e, obs, src, xi, xr, zl, sin_cos, Li, Lj, cov, ok_i, ok_j, bad, Z0, Z1, sums,
     moments, pxz, mean) = moment_scratch(C, m)  # fmt: skip
    axis, value = point_axes(nz_idx, nz_val, nz_cnt)
    s_in, s_out = np.empty((3, 3)), np.empty((3, 3))
    Pi = np.empty((9, C))
    update = np.empty((UPDATE_ROWS, C))
    lane_e[:n] = np.arange(n)
    n = np.int64(n)
    n2 = lanes_ahead(n, C)
    assert n2 >= 2 * n and n2 % 8 == 0
    gather_lanes(x, li, nb, x_ref, z, lane_e, n, obs, src, xi, xr, zl, sin_cos, bad)
    fresh_lanes(x_nb, n, n2, obs, src, xi, xr, zl, sin_cos, bad)
    load_covariances(P, obs, n2, cov)
    chol_lanes(cov, n2, Li, ok_i)
    load_covariances(P_ref, src, n, cov)
    fresh_covariances(P_nb, src, n, n2, cov)
    chol_lanes(cov, n2, Lj, ok_j)
    assert chol_jitter_lanes(P, obs, n2, Li, ok_i, jitter, s_in, s_out)
    assert chol_jitter_lanes(P_ref, src, n, Lj, ok_j, jitter, s_in, s_out)
    points_lanes(axis, value, Wm, n2, xi, xr, sin_cos, Li, Lj, Z0, Z1, sums, bad)
    moments_lanes(axis, value, Wm, Wc, circular, n2, Li, Z0, Z1, sums, moments, pxz, mean, bad)
    load_robot_covariances(P, obs, n2, Pi)
    kalman_lanes(n2, zl, R, moments, pxz, Pi, update)
    lanes = (P, obs, src, n, xi, xr, zl, sin_cos, Li, Lj, moments, pxz, update)
    return lanes, ok_j, bad, retry_lanes(m, C), filt, R, jitter, x_nb, P_nb


@pytest.mark.parametrize("n", [5, 17, 40])
def test_the_lanes_ahead_are_the_second_pass(n: int) -> None:
    from resloc.cl.kernels_round_cached import take_fresh
    from resloc.cl.kernels_round_stages import inflated_moments

    singular = 2
    lanes, ok_j, bad, retry, filt, R, jitter, x_nb, P_nb = _round(n, singular, seed=n)
    P, obs, src, n, xi, xr, zl, sin_cos, Li, Lj, moments, pxz, update = lanes
    rng = np.random.default_rng(100 + n)
    decision = np.zeros((4, moments.shape[1]))
    decision[3, :n] = rng.random(n) < 0.6  # fused
    decision[3, singular] = 1.0
    fresh = np.where(rng.random(moments.shape[1]) < 0.7, 1.0, 0.0)
    fresh[singular] = 1.0
    inflation = np.ones(moments.shape[1])
    inflation[0] = 2.0  # a re-admission: the second pass from 2 P_i, lane by lane
    decision[3, 0] = fresh[0] = 1.0
    assert ok_j[n + singular] == 0.0  # its twin's factor needed jitter

    def second_pass(take: bool):
        mom, px, up, fr = moments.copy(), pxz.copy(), update.copy(), fresh.copy()
        if take:
            take_fresh(n, inflation, decision, fr, ok_j, bad, mom, px, up)
        status = inflated_moments(
            P, obs, src, n, inflation, decision, fr, xi, xr, zl, sin_cos, Li, Lj, mom, px,
            up, retry, filt, R, jitter, x_nb, P_nb,
        )  # fmt: skip
        assert status == 0
        return mom[:, :n], px[:, :n], up[:, :n], fr[:n]

    ahead = second_pass(True)
    by_lane = second_pass(False)
    taken = (decision[3, :n] == 1.0) & (fresh[:n] == 1.0) & (ahead[3] == 0.0)
    assert taken.sum() >= 2, "no lane took its twin's second pass"
    left = (decision[3, :n] == 1.0) & (fresh[:n] == 1.0) & ~taken
    assert left[singular] and left[0], "the jittered twin and the re-admission stay lane by lane"
    for got, want in zip(ahead[:3], by_lane[:3], strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
    # the lanes not fused, or fused with the cached estimate, keep the first pass
    kept = decision[3, :n] != 1.0
    np.testing.assert_array_equal(ahead[0][:, kept], moments[:, :n][:, kept])


def test_padded_lanes_fill_whole_simd_blocks() -> None:
    from resloc.cl.kernels_lanes import CHUNK
    from resloc.cl.kernels_round_cached import LANE_BLOCK, LANE_MIN, lanes_ahead, padded_lanes

    for n in range(1, CHUNK + 1):
        p = padded_lanes(n, CHUNK)
        if n < LANE_BLOCK:
            assert p == n
        else:
            assert n <= p <= CHUNK and p >= min(LANE_MIN, CHUNK)
            assert p % LANE_BLOCK == 0 or p == CHUNK
            assert p - n < LANE_BLOCK or p == LANE_MIN
        a = lanes_ahead(n, CHUNK)
        assert a == (n if 2 * n > CHUNK else padded_lanes(2 * n, CHUNK))
    assert padded_lanes(17, CHUNK) == 24 and lanes_ahead(17, CHUNK) == 40
