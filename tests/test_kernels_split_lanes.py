"""Split CI's update of a round's fused lanes in SIMD stages
(:mod:`resloc.cl.kernels_split_lanes`): the same results, to the bit, as the scalar update
lane by lane (``split_ci_update`` in :func:`resloc.cl.kernels_round_stages.intersect_lanes`),
for certified lanes and for lanes that fall back to the scalar code. (Against the numpy
specification: the rounds' lockstep tests, ``tests/test_kernels_round_options.py``.)"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from resloc.cl import kernels, kernels_plain, kernels_prepared
from resloc.cl.kernels_inputs import KernelOutputs
from test_kernels_ci_lanes import bits, jacobians, lane_arrays, spd

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")


def _lanes_inputs(n: int, seed: int, det: bool, special: int = 7):
    """A round of ``n`` lanes (robot ``c`` observes through link ``e = perm[c]``) with the
    moments of the plain update, and lanes made to fall back: an independent part above
    its covariance (the clip through the factor), one equal to it, one zero;
    lanes whose ``j`` is so uncertain that ``w = 1``; an inflated covariance; a lane
    not fused (lane ``c`` of kind ``c % special``: ``special = 1``, every lane plain)."""
    from resloc.cl.fusion import CICriterion
    from resloc.cl.kernels_fusion import SPLIT_CI, kernel_fusion
    from resloc.cl.kernels_lanes import CHUNK
    from resloc.experiments.config import default_scenario

    rng = np.random.default_rng(seed)
    C = CHUNK
    perm = rng.permutation(n)
    x = rng.uniform(-5.0, 5.0, (n, 3))
    P = spd(rng, n, 0.15)
    P_nb = spd(rng, n, 0.15)
    ind = P * rng.uniform(0.05, 0.9, (n, 1, 1))
    ind_nb = P_nb * rng.uniform(0.05, 0.9, (n, 1, 1))
    x_nb = x[perm] + rng.normal(size=(n, 3)) * 3.0
    inflation = np.ones(C)
    fused = np.ones(n, dtype=bool)
    # lanes that fall back, and lanes kept (w = 1); c % 7 keeps the other lanes plain
    for c in range(n):
        e = perm[c]
        kind = c % special
        if kind == 1:
            ind[c] = 1.3 * P[c]
        elif kind == 2:
            ind_nb[e] = P_nb[e]
        elif kind == 3:
            P_nb[e] *= 1e4
        elif kind == 4:
            inflation[c] = 2.5
        elif kind == 5:
            fused[c] = False
        elif kind == 6 and c > 7:
            ind[c] = 0.0
    lane_e, obs, src, xi, xr, moments, pxz, update, decision = lane_arrays(x, x_nb, perm, C, fused)
    for c in range(n):
        Hi, Hj = jacobians(xi[:, c], xr[:, c])
        Pi = P[c] * inflation[c]
        S = Hi @ Pi @ Hi.T + Hj @ P_nb[perm[c]] @ Hj.T
        moments[2:, c] = S[0, 0], S[0, 1], S[1, 1]
        pxz[:, c] = (Pi @ Hi.T).ravel()
        update[:2, c] = rng.normal(size=2) * 0.05
    params = replace(default_scenario().cl_params(), fusion="split_ci")
    options = kernels_prepared.prepared_for(params).plain_options
    criterion = CICriterion.DET if det else CICriterion.TRACE
    fusion = kernel_fusion(SPLIT_CI, criterion, n)._replace(
        independent=np.ascontiguousarray(ind), P_nb_ind=np.ascontiguousarray(ind_nb)
    )
    # the kernels' own structure: a plain tuple would compile another specialization
    out = KernelOutputs(np.zeros(n), np.zeros(n), np.zeros((5, n), dtype=np.bool_))
    return [x, P, P_nb, lane_e, obs, src, n, xi, xr, update, moments, pxz, inflation,
            decision, options, kernels_plain.plain(fusion), out]  # fmt: skip


@pytest.mark.parametrize("det", [False, True])
@pytest.mark.parametrize("n", [5, 17, 30])
def test_split_ci_lanes_are_the_scalar_update_lane_by_lane(n: int, det: bool) -> None:
    """The SIMD stages' ``x``, ``P``, independent parts and repair flags are the scalar
    update's to the bit; some lanes certified (plain, ``w < 1``, and kept, ``w = 1``) and
    some not (they run the scalar update inside the stage)."""
    from resloc.cl import kernels_lane_rows as rows
    from resloc.cl import kernels_split_lanes as sl
    from resloc.cl.kernels_round_stages import intersect_lanes, link_scratch

    results = {}
    for form in ("lanes", "scalar"):
        args = _lanes_inputs(n, 40 + n, det)
        fusion = args[15]
        lanes = sl.split_lane_scratch(fusion)
        if form == "scalar":
            lanes = np.empty((lanes.shape[0], 0))
        else:
            lanes[rows.R_OK] = np.nan  # written by the stages (and only by them)
        done = intersect_lanes(*args, link_scratch(), False, lanes)
        x, P = args[0], args[1]
        results[form] = (done, x, P, fusion[4], args[16][2], lanes)
    done, x, P, ind, flags, lanes = results["lanes"]
    done_s, x_s, P_s, ind_s, flags_s, _ = results["scalar"]
    assert done and done_s
    np.testing.assert_array_equal(bits(x), bits(x_s))
    np.testing.assert_array_equal(bits(P), bits(P_s))
    np.testing.assert_array_equal(bits(ind), bits(ind_s))
    np.testing.assert_array_equal(flags, flags_s)
    fused = int(_lanes_inputs(n, 40 + n, det)[13][3].sum())
    certified = lanes[rows.R_OK, :fused] == 1.0
    kept = lanes[rows.R_W, :fused] >= 1.0
    assert (certified & ~kept).any() and (certified & kept).any() and (~certified).any()
    # the lanes the inputs make fall back are exactly the uncertified ones
    order = [c for c in range(n) if c % 7 != 5]
    expect = np.array([c % 7 not in (1, 2) and not (c % 7 == 6 and c > 7) for c in order])
    np.testing.assert_array_equal(certified, expect)


def test_compiled_finish_zeroes_the_delivered_senders_parts_as_numpy() -> None:
    """``SplitCIFusion.finish``'s compiled twin writes what ``independent[j[delivered]] =
    0`` writes (repeated senders too) and refuses, writing nothing, a negative or
    out-of-range index (numpy's assignment then wraps it or raises)."""
    from resloc.cl.kernels_split import compiled_independent_finish

    rng = np.random.default_rng(3)
    independent = rng.normal(size=(17, 3, 3))
    j = rng.integers(0, 17, 260)
    delivered = np.zeros(260, dtype=bool)
    delivered[[3, 40, 41, 200]] = True
    j[41] = j[40]  # a sender delivered twice
    expected = independent.copy()
    expected[j[delivered]] = 0.0
    assert (expected != 0.0).any(axis=(1, 2)).sum() == 17 - 3  # the others' parts kept
    assert compiled_independent_finish(independent, j, delivered)
    np.testing.assert_array_equal(independent, expected)
    assert (independent == 0.0).all(axis=(1, 2)).sum() == len(np.unique(j[delivered]))
    for bad in (-1, 17):
        before = independent.copy()
        j_bad = j.copy()
        j_bad[np.flatnonzero(delivered)[-1]] = bad
        assert not compiled_independent_finish(independent, j_bad, delivered)
        np.testing.assert_array_equal(independent, before)
    with kernels.use_backend("numpy"):
        assert not compiled_independent_finish(independent, j, delivered)
