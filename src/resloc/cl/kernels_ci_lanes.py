"""Covariance intersection's update of a round's fused lanes in SIMD stages (``ci`` in the
link rounds, :func:`resloc.cl.kernels_round_stages.intersect_lanes`).

:func:`resloc.cl.kernels_ci_update.ci_update` is scalar code, lane after lane (~220 ns a fused
lane: the weight's reductions and search, the inflated update, ``store_covariance``). As
split CI's (:mod:`resloc.cl.kernels_split_lanes`, whose rows and weight stage this module
shares: stages 1-3 there without the independent parts), the fused lanes of a round are
gathered by lane into the rows of one array (:data:`~resloc.cl.kernels_joint_lanes.
LANE_STRIDE` columns), then:

1. :func:`_ci_weight_inputs_lanes`, over the lanes without branches: the Jacobians and the
   weight's reductions (``a = H_i P_i H_i^T``, ``b = H_j P_j H_j^T``, ``g = C^T C``), the
   trace and determinant of ``P_i`` and the prior's cost
   (:func:`resloc.cl.kernels_ci_weight.weight_of` without ``split``);
2. :func:`resloc.cl.kernels_split_lanes.weight_lanes` without ``split``: the weight;
3. :func:`_ci_update_lanes`, over the lanes without branches: the inflated update with
   ``S``'s factor at the first jitter level, ``sym(P_n)`` and its positive-definiteness test
   (:func:`resloc.cl.kernels_split_pieces.ci_update_of`).

Each stage does the scalar code's operations in its order, so a certified lane's results
are the scalar's to the bit. A lane is certified where the prior is kept (``w >= 1``) or
``S`` has its factor at the first jitter level with finite entries; any other lane runs
``ci_update`` itself from the same inputs (the lanes of a round are distinct robots: the
order of the writes does not matter).

=============================  ==========================================================
kernel function                twin
=============================  ==========================================================
:func:`ci_lanes`               ``ci_update`` of each fused lane (intersect_lanes)
=============================  ==========================================================
"""

from __future__ import annotations

from resloc.cl import kernels_ci_update as _kernels_ci_update
from resloc.cl import kernels_ci_weight as _kernels_ci_weight
from resloc.cl import kernels_gauge as _kernels_gauge
from resloc.cl import kernels_lane_rows as _kernels_lane_rows
from resloc.cl import kernels_math as _kernels_math
from resloc.cl import kernels_split_lanes as _kernels_split_lanes
from resloc.cl import kernels_split_pieces as _kernels_split_pieces
from resloc.cl.kernels_ci_update import ci_update
from resloc.cl.kernels_ci_weight import gram
from resloc.cl.kernels_gauge import range_bearing_jacobians_into
from resloc.cl.kernels_lane_rows import (
    R_A,
    R_AI,
    R_B,
    R_BI,
    R_DET,
    R_DP,
    R_G,
    R_GDI,
    R_GII,
    R_IP,
    R_LANE,
    R_NU,
    R_OK,
    R_PD,
    R_PI,
    R_PJ,
    R_PN,
    R_PRIOR,
    R_PXZ,
    R_S,
    R_TR,
    R_TRP,
    R_W,
    R_X,
    R_XN,
    R_XR,
    S,
    gather_lane,
    pad_lanes,
    put4,
    put9,
    row9,
)
from resloc.cl.kernels_math import jit_lanes, repair3, stamp_with_pieces, store_covariance, wrap
from resloc.cl.kernels_split_lanes import weight_lanes
from resloc.cl.kernels_split_pieces import ci_update_of, jacobians_of, reduce_i9, reduce_j9

_jit = jit_lanes

__all__ = ["ci_lanes"]

_ZERO4 = (0.0, 0.0, 0.0, 0.0)


@_jit
def _ci_weight_inputs_lanes(f, m, det):
    """Stage 1 for lanes ``0 .. m - 1``: the weight's inputs as
    :func:`resloc.cl.kernels_ci_weight.weight_of` without ``split`` (``D_i = P_i``, ``D_j =
    P_j``; the split rows zero, the determinant as it computes it)."""
    for k in range(m):
        Pi = row9(f, R_PI, k)
        Hi, Hj = jacobians_of(f[R_X * S + k], f[(R_X + 1) * S + k], f[R_XR * S + k],
                              f[(R_XR + 1) * S + k])  # fmt: skip
        a, cd = reduce_i9(Pi, Hi)
        b = reduce_j9(row9(f, R_PJ, k), Hj)
        tr_i = Pi[0] + Pi[4] + Pi[8]
        det_i = (
            Pi[0] * (Pi[4] * Pi[8] - Pi[5] * Pi[7])
            - Pi[1] * (Pi[3] * Pi[8] - Pi[5] * Pi[6])
            + Pi[2] * (Pi[3] * Pi[7] - Pi[4] * Pi[6])
        )
        put4(f, R_A, k, a)
        put4(f, R_AI, k, _ZERO4)
        put4(f, R_B, k, b)
        put4(f, R_BI, k, _ZERO4)
        put4(f, R_G, k, gram(cd, cd))
        put4(f, R_GDI, k, _ZERO4)
        put4(f, R_GII, k, _ZERO4)
        f[R_TR * S + k] = tr_i
        f[R_TRP * S + k] = tr_i
        f[R_DET * S + k] = det_i
        f[R_PRIOR * S + k] = det_i if det else tr_i
        put9(f, R_DP, k, Pi)
        put9(f, R_IP, k, Pi)


@_jit
def _ci_update_lanes(f, m, jitter0):
    """Stage 3: the update of lanes ``0 .. m - 1`` with their weights (row ``R_W``) by
    :func:`~resloc.cl.kernels_split_pieces.ci_update_of`: ``x_i``, ``sym(P_n)`` and its
    test, certified (row ``R_OK``, 1.0)."""
    for k in range(m):
        Hi, Hj = jacobians_of(f[R_X * S + k], f[(R_X + 1) * S + k], f[R_XR * S + k],
                              f[(R_XR + 1) * S + k])  # fmt: skip
        good, xn, T, pd = ci_update_of(
            row9(f, R_PI, k), row9(f, R_PJ, k), Hi, Hj, f[R_W * S + k],
            (f[R_S * S + k], f[(R_S + 1) * S + k], f[(R_S + 2) * S + k]),
            (
                f[R_PXZ * S + k], f[(R_PXZ + 1) * S + k], f[(R_PXZ + 2) * S + k],
                f[(R_PXZ + 3) * S + k], f[(R_PXZ + 4) * S + k], f[(R_PXZ + 5) * S + k],
            ),
            (f[R_X * S + k], f[(R_X + 1) * S + k], f[(R_X + 2) * S + k]),
            f[R_NU * S + k], f[(R_NU + 1) * S + k], jitter0,
        )  # fmt: skip
        f[R_OK * S + k] = 1.0 if good else 0.0
        f[R_XN * S + k] = xn[0]
        f[(R_XN + 1) * S + k] = xn[1]
        f[(R_XN + 2) * S + k] = xn[2]
        put9(f, R_PN, k, T)
        f[R_PD * S + k] = 1.0 if pd else 0.0


@_jit
def ci_lanes(
    x, P, P_ref, lane_e, obs, src, n, xi, xr, update, moments, pxz, inflation, decision,
    options, fusion, out, work, lanes,
):  # fmt: skip
    """``ci`` of every fused lane (``decision[3] == 1``) of a round: the lanes' inputs
    gathered into ``lanes`` (:func:`~resloc.cl.kernels_split_lanes.split_lane_scratch`;
    padded to whole blocks with copies of the first), the three stages above, then each
    certified lane's results written (``x_i``, ``P_i`` symmetrized and repaired as
    :func:`store_covariance` does) and every other lane updated by ``ci_update`` itself.
    Arguments and result as :func:`resloc.cl.kernels_round_stages.intersect_lanes` (False:
    an inflated ``S`` without a Cholesky factor; EKF-free: ``filt[0]`` False, as wherever
    the rounds run). Twin: its ``ci_update`` loop."""
    R, jitter = options[0], options[8]
    flags = out[2]
    Pi, Pxz, K, Hi, Hj, A3, T3, Pn = work[:8]
    f = lanes.reshape(lanes.size)
    m = 0
    for c in range(n):
        if decision[3, c] != 1.0:
            continue
        i = obs[c]
        r = src[c]
        g = inflation[c]
        gather_lane(f, m, i, r, g, c, P, P_ref, xi, xr, pxz, moments, R, update)
        m += 1
    if m == 0:
        return True
    m2 = pad_lanes(f, m)
    _ci_weight_inputs_lanes(f, m2, fusion[1])
    weight_lanes(f, m, fusion[2], fusion[1], R, False)
    _ci_update_lanes(f, m2, jitter[0])
    for k in range(m):
        c = int(f[R_LANE * S + k])
        e = lane_e[c]
        i = obs[c]
        if f[R_OK * S + k] == 1.0:
            if f[R_W * S + k] < 1.0:
                x[i, 0] = f[R_XN * S + k]
                x[i, 1] = f[(R_XN + 1) * S + k]
                x[i, 2] = wrap(f[(R_XN + 2) * S + k])
            for a in range(3):  # store_covariance, its sym(P_n) and test from stage 3
                for b in range(3):
                    T3[a, b] = f[(R_PN + 3 * a + b) * S + k]
            if f[R_PD * S + k] != 1.0:
                repair3(T3)
                flags[4, e] = True
            for a in range(3):
                for b in range(3):
                    P[i, a, b] = T3[a, b]
        else:  # not certified: the scalar update from the same inputs
            g = inflation[c]
            for a in range(3):
                for b in range(3):
                    Pi[a, b] = P[i, a, b] * g
            for a in range(3):
                Pxz[a, 0] = pxz[2 * a, c]
                Pxz[a, 1] = pxz[2 * a + 1, c]
            S00 = moments[2, c] + R[0, 0]
            S01 = 0.5 * ((moments[3, c] + R[0, 1]) + (moments[3, c] + R[1, 0]))
            S11 = moments[4, c] + R[1, 1]
            xi0 = xi[0, c]
            xi1 = xi[1, c]
            range_bearing_jacobians_into(xi0, xi1, xr[0, c], xr[1, c], Hi, Hj)
            if not ci_update(
                x, i, xi0, xi1, xi[2, c], Pi, P_ref[src[c]], update[0, c], update[1, c],
                S00, S01, S11, Pxz, False, Hi, Hj, 0.0, 0.0, 0.0, R, fusion, jitter, K, A3,
                T3, Pn,
            ):  # fmt: skip
                return False
            if store_covariance(P, i, Pn, T3):
                flags[4, e] = True
    return True


for _dispatcher in (_ci_weight_inputs_lanes, _ci_update_lanes, ci_lanes):
    stamp_with_pieces(
        _dispatcher, _kernels_math, _kernels_ci_weight, _kernels_ci_update, _kernels_gauge,
        _kernels_lane_rows, _kernels_split_lanes, _kernels_split_pieces,
    )  # fmt: skip
