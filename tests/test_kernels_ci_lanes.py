"""Covariance intersection's update of a round's fused lanes in SIMD stages
(:mod:`resloc.cl.kernels_ci_lanes`): the same results, to the bit, as the scalar update lane
by lane (``ci_update`` in :func:`resloc.cl.kernels_round_stages.intersect_lanes`), for
certified lanes and for lanes that fall back to the scalar code. (Against the numpy
specification: the rounds' lockstep tests, ``tests/test_kernels_round_options.py``.)"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from resloc.cl import kernels, kernels_plain, kernels_prepared
from resloc.cl.kernels_inputs import KernelOutputs

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

#: Lane ``c``'s kind is ``c % 6``: 0 plain, 1 ``j`` so uncertain that ``w = 1``, 2 ``i``'s
#: covariance inflated, 3 not fused, 4 ``S`` just indefinite at the first jitter level
#: (falls back; factored at a later one), 5 ``P^xz`` so large that the posterior is repaired.
_KINDS = 6


def spd(rng, n: int, scale: float) -> np.ndarray:
    """``n`` random SPD 3x3 matrices ``(n, 3, 3)`` of about ``scale**2``."""
    A = rng.normal(size=(n, 3, 3)) * scale
    return A @ np.swapaxes(A, -1, -2) + scale**2 * np.eye(3)


def jacobians(xi, xr):
    """The range-bearing Jacobians ``H_i``, ``H_j`` (2, 3) at the observer's ``xi`` (3,)
    and the observed's position ``xr`` (2,)."""
    dx, dy = xr[0] - xi[0], xr[1] - xi[1]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    Hj = np.array([[dx / r, dy / r, 0.0], [-dy / q, dx / q, 0.0]])
    Hi = -Hj
    Hi[1, 2] = -1.0
    return Hi, Hj


def _lanes_inputs(n: int, seed: int, det: bool, weights=None):
    """A round of ``n`` lanes (robot ``c`` observes through link ``e = perm[c]``) of the
    kinds of :data:`_KINDS`. ``weights``: the lanes' weights of a first run, with which
    the kind-4 lanes' ``S`` is made singular (``S + H_i P_i H_i^T f_i + H_j P_j H_j^T
    f_j`` a rank-one matrix, up to rounding)."""
    from resloc.cl.fusion import CICriterion
    from resloc.cl.kernels_fusion import CI, kernel_fusion
    from resloc.cl.kernels_lanes import CHUNK
    from resloc.experiments.config import default_scenario

    rng = np.random.default_rng(seed)
    C = CHUNK
    perm = rng.permutation(n)
    x = rng.uniform(-5.0, 5.0, (n, 3))
    P = spd(rng, n, 0.15)
    P_nb = spd(rng, n, 0.15)
    x_nb = x[perm] + rng.normal(size=(n, 3)) * 3.0
    inflation = np.ones(C)
    fused = np.ones(n, dtype=bool)
    kind = np.arange(n) % _KINDS
    for c in range(n):
        if kind[c] == 1:
            P_nb[perm[c]] *= 1e4
        elif kind[c] == 2:
            inflation[c] = 2.5
        elif kind[c] == 3:
            fused[c] = False
    lane_e, obs, src, xi, xr, moments, pxz, update, decision = lane_arrays(x, x_nb, perm, C, fused)
    params = replace(default_scenario().cl_params(), fusion="ci")
    options = kernels_prepared.prepared_for(params).plain_options
    R = options[0]
    for c in range(n):
        Hi, Hj = jacobians(xi[:, c], xr[:, c])
        Pi = P[c] * inflation[c]
        S = Hi @ Pi @ Hi.T + Hj @ P_nb[perm[c]] @ Hj.T
        if kind[c] == 4 and weights is not None:
            w = weights[c]
            inflate = (Hi @ Pi @ Hi.T) * (1.0 / w - 1.0) + (Hj @ P_nb[perm[c]] @ Hj.T) * (
                1.0 / (1.0 - w) - 1.0
            )
            v = rng.normal(size=2)
            S = np.outer(v, v) - inflate - R  # S + R + the inflations: rank one
            S[1, 1] -= 1e-9 * (v @ v)  # indefinite at jitter 0, factored at 1e-8
        moments[2:, c] = S[0, 0], S[0, 1], S[1, 1]
        pxz[:, c] = (Pi @ Hi.T).ravel() * (30.0 if kind[c] == 5 else 1.0)
        update[:2, c] = rng.normal(size=2) * 0.05
    criterion = CICriterion.DET if det else CICriterion.TRACE
    fusion = kernel_fusion(CI, criterion, n)
    # the kernels' own structure: a plain tuple would compile another specialization
    out = KernelOutputs(np.zeros(n), np.zeros(n), np.zeros((5, n), dtype=np.bool_))
    return [x, P, P_nb, lane_e, obs, src, n, xi, xr, update, moments, pxz, inflation,
            decision, options, kernels_plain.plain(fusion), out]  # fmt: skip


def lane_arrays(x, x_nb, perm, C: int, fused):
    """A round's lanes for ``n = len(perm)`` links in ``C`` lanes (robot ``c`` observes
    through link ``perm[c]``; ``x`` (n, 3) and ``fused`` (n,) by lane, ``x_nb`` (n, 3) by
    link): ``lane_e``, ``obs``, ``src`` (C,), ``xi`` (3, C), ``xr`` (2, C), zeroed
    ``moments`` (5, C), ``pxz`` (6, C), ``update`` (UPDATE_ROWS, C) and ``decision``
    (4, C) with the fused flags."""
    from resloc.cl.kernels_link_stages import UPDATE_ROWS

    n = len(perm)
    lane_e = np.zeros(C, np.int64)
    obs = np.zeros(C, np.int64)
    src = np.zeros(C, np.int64)
    lane_e[:n] = perm
    obs[:n] = np.arange(n)
    src[:n] = perm
    xi = np.zeros((3, C))
    xr = np.zeros((2, C))
    xi[:, :n] = x.T
    xr[:, :n] = x_nb[perm, :2].T
    moments = np.zeros((5, C))
    pxz = np.zeros((6, C))
    update = np.zeros((UPDATE_ROWS, C))
    decision = np.zeros((4, C))
    decision[3, :n] = fused
    return lane_e, obs, src, xi, xr, moments, pxz, update, decision


def bits(a: np.ndarray) -> np.ndarray:
    """``a``'s float64 values as their bits, to compare to the bit."""
    return np.ascontiguousarray(a, dtype=float).view(np.uint64)


def _run(n: int, det: bool, form: str, weights=None):
    from resloc.cl import kernels_lane_rows as rows
    from resloc.cl import kernels_split_lanes as sl
    from resloc.cl.kernels_round_stages import intersect_lanes, link_scratch

    args = _lanes_inputs(n, 70 + n, det, weights)
    lanes = sl.split_lane_scratch(args[15])
    if form == "scalar":
        lanes = np.empty((lanes.shape[0], 0))
    else:
        lanes[rows.R_OK] = np.nan  # written by the stages (and only by them)
        lanes[rows.R_W] = np.nan
    done = intersect_lanes(*args, link_scratch(), False, lanes)
    return done, args, lanes


@pytest.mark.parametrize("det", [False, True])
@pytest.mark.parametrize("n", [5, 17, 30])
def test_ci_lanes_are_the_scalar_update_lane_by_lane(n: int, det: bool) -> None:
    """The SIMD stages' ``x``, ``P`` and repair flags are the scalar update's to the bit;
    lanes certified (plain ``w < 1``, kept ``w = 1``, inflated, repaired) and lanes with a
    singular ``S`` that run the scalar update inside the stage."""
    from resloc.cl import kernels_lane_rows as rows

    _, _, first = _run(n, det, "lanes")
    fused_lanes = [c for c in range(n) if c % _KINDS != 3]
    weights = np.zeros(n)
    weights[fused_lanes] = first[rows.R_W, : len(fused_lanes)]
    done, args, lanes = _run(n, det, "lanes", weights)
    done_s, args_s, _ = _run(n, det, "scalar", weights)
    assert done and done_s
    np.testing.assert_array_equal(bits(args[0]), bits(args_s[0]))  # x
    np.testing.assert_array_equal(bits(args[1]), bits(args_s[1]))  # P
    np.testing.assert_array_equal(args[16][2], args_s[16][2])  # the repair flags
    kinds = np.array(fused_lanes) % _KINDS
    certified = lanes[rows.R_OK, : len(fused_lanes)] == 1.0
    kept = lanes[rows.R_W, : len(fused_lanes)] >= 1.0
    # the lanes the inputs make fall back are exactly the uncertified ones
    np.testing.assert_array_equal(certified, kinds != 4)
    assert (certified & ~kept).any()
    assert kept[kinds == 1].all()
    repaired = args[16][2][4][args[3][fused_lanes]]  # by lane, from the links' flags
    np.testing.assert_array_equal(repaired & (kinds < 4), False)  # (kind 4: jitter)
    assert repaired[kinds == 5].all()  # the large P^xz: a posterior not positive definite
    # the lanes not fused are untouched
    x0, P0 = _lanes_inputs(n, 70 + n, det, weights)[:2]
    for c in range(n):
        if c % _KINDS == 3:
            np.testing.assert_array_equal(args[0][c], x0[c])
            np.testing.assert_array_equal(args[1][c], P0[c])
