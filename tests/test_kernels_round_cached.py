"""The second pass of ``cached`` neighbour estimates by the SIMD stages
(:func:`resloc.cl.kernels_round_cached.fresh_moments`) against the scalar pieces it replaces
(:func:`resloc.cl.kernels_round_stages.inflated_moments`), called directly on one round's
lanes: the same moments, ``P^xz`` and update to 1e-12, on the lanes it is for (delivered
with a cached estimate, not inflated by the recovery), marked done, and no other lane
touched. The lockstep of the whole correction (rounds, row-order loop, reference) is
``test_kernels_round_options.py``'s ``cached`` cases."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.cl import kernels
from resloc.cl.backend import filter_kernel_spec
from resloc.filters import make_filter
from resloc.linalg import JITTER_LEVELS

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")


def _spd(rng, scale):
    A = rng.normal(size=(3, 3)) * scale
    return A @ A.T + 0.05 * scale * np.eye(3)


@pytest.mark.parametrize("name", ["ckf", "ukf"])
def test_fresh_moments_are_the_scalar_second_pass(name):
    from resloc.cl.kernels_lanes import CHUNK
    from resloc.cl.kernels_link_stages import UPDATE_ROWS, point_axes
    from resloc.cl.kernels_links import OK
    from resloc.cl.kernels_round_cached import FRESH_DONE, fresh_moments, fresh_scratch
    from resloc.cl.kernels_round_stages import inflated_moments, retry_lanes

    filt = make_filter("ckf") if name == "ckf" else make_filter("ukf", 0.8, 2.0, 1.0)
    spec = tuple(filter_kernel_spec(filt))
    nz_idx, nz_val, nz_cnt, Wm, Wc, circular = spec[1:]
    axis, value = point_axes(nz_idx, nz_val, nz_cnt)
    m = axis.shape[0]
    rng = np.random.default_rng(3)
    n = 12  # lanes: robot c's link c
    C = CHUNK
    x = np.column_stack([rng.uniform(-3, 3, (n, 2)), rng.uniform(-3, 3, n)])
    P = np.stack([_spd(rng, 0.1) for _ in range(n)])
    x_nb = x + np.column_stack([rng.uniform(1, 2, (n, 2)), rng.uniform(-1, 1, n)])
    P_nb = np.stack([_spd(rng, 0.05) for _ in range(n)])
    li = np.arange(n, dtype=np.int64)
    nb = np.arange(n, dtype=np.int64)
    z = np.column_stack([rng.uniform(1, 3, n), rng.uniform(-3, 3, n)])
    lane_e = np.zeros(C, np.int64)
    lane_e[:n] = li
    obs = lane_e.copy()
    src = lane_e.copy()
    zl = np.zeros((2, C))
    zl[:, :n] = z.T + 0.01  # the first pass's measurement (e.g. an attacker's), not z
    xi = np.zeros((3, C))
    xi[:, :n] = x.T
    sin_cos = np.zeros((2, C))
    sin_cos[0, :n], sin_cos[1, :n] = np.sin(x[:, 2]), np.cos(x[:, 2])
    xr = np.zeros((2, C))
    xr[:, :n] = x_nb[:, :2].T - 0.3  # the cached estimate's position (first pass)
    Li = np.zeros((3, 3, C))
    Li[:, :, :n] = np.moveaxis(np.linalg.cholesky(P), 0, -1)
    Lj = np.zeros((3, 3, C))  # the cached estimate's factor: not read for fresh lanes
    decision = np.zeros((4, C))
    decision[3, :n] = [1, 1, 1, 0, 1, 1, 1, 1, 0, 1, 1, 1]  # fused
    fresh = np.zeros(C)
    fresh[:n] = [1, 1, 0, 1, 1, 1, 1, 1, 1, 1, 0, 1]  # delivered with a cached estimate
    inflation = np.ones(C)
    inflation[5] = 2.5  # the recovery's re-admission: left to inflated_moments
    R = np.diag([0.01, 0.003])
    jitter = np.asarray(JITTER_LEVELS, dtype=float)
    first = {
        key: rng.normal(size=shape)
        for key, shape in (("moments", (5, C)), ("pxz", (6, C)), ("update", (UPDATE_ROWS, C)))
    }

    def second_pass(simd: bool):
        out = {key: a.copy() for key, a in first.items()}
        f = fresh.copy()
        if simd:
            status = fresh_moments(
                x, li, nb, x_nb, P_nb, z, lane_e, np.int64(n), decision, inflation, f, zl, Li,
                out["moments"], out["pxz"], out["update"], axis, value, Wm, Wc, circular, R,
                jitter, P, fresh_scratch(C, m),
            )  # fmt: skip
            assert status == OK
            done = f == FRESH_DONE
        else:
            done = None
        status = inflated_moments(
            P, obs, src, np.int64(n), inflation, decision, f, xi, xr, zl, sin_cos, Li, Lj,
            out["moments"], out["pxz"], out["update"], retry_lanes(m, C), spec, R, jitter, x_nb,
            P_nb,
        )  # fmt: skip
        assert status == OK
        return out, done

    simd, done = second_pass(True)
    scalar, _ = second_pass(False)
    expected = (decision[3] == 1.0) & (fresh == 1.0) & (inflation == 1.0)
    np.testing.assert_array_equal(done, expected)
    assert expected.sum() == 7
    for key in first:
        np.testing.assert_allclose(simd[key], scalar[key], rtol=1e-12, atol=1e-12)
    untouched = ~((decision[3] == 1.0) & ((fresh == 1.0) | (inflation > 1.0)))
    for key in first:  # lanes of neither pass keep the first pass's values
        np.testing.assert_array_equal(simd[key][:, untouched], first[key][:, untouched])
    assert (simd["update"][15, ~untouched] == 0.0).all()  # none needs the row-order loop
