"""Split CI's update of a round's fused lanes in SIMD stages (``split_ci`` in the link rounds,
:func:`resloc.cl.kernels_round_stages.intersect_lanes`).

:func:`resloc.cl.kernels_split.split_ci_update` is scalar code, lane after lane (~800 ns a
fused lane: three clips, the weight, the inflated update, the statistical linearization's
factor and solves, the Joseph sandwich, the posterior's clip). Here the fused lanes of a
round are gathered by lane into the rows of one array (:data:`LANE_STRIDE` columns, a row
per input, :mod:`resloc.cl.kernels_lane_rows`), then each step of the update runs as a
loop over the lanes, free of branches, with the certificates the scalar code takes its
fast branch on computed for every lane (stages 1 and 3):

1. :func:`_weight_inputs_lanes`: both clips' certificates (``0 < P_ind < P`` by Sylvester's
   criterion, :func:`resloc.cl.kernels_split._clip_independent`), the dependent parts and
   the weight's 2 x 2 reductions (:func:`resloc.cl.kernels_ci_weight.weight_of`);
2. :func:`weight_lanes`: the weight as :func:`resloc.cl.kernels_ci_weight._search_weight`
   finds it: lane by lane the grid's costs (its SIMD loop over the candidates) and their
   first best, then the refinement over the lanes without branches;
3. :func:`_update_lanes`: the inflated update (:func:`resloc.cl.kernels_ci_update.
   inflated_update`, its Cholesky factor of ``S`` without jitter), ``A``'s factor without
   jitter and the linearization's solves, the Joseph form of the independent part and the
   posterior's clip certificate (:func:`resloc.cl.kernels_split._split_ci_link`), by
   :func:`resloc.cl.kernels_split_pieces.split_update_of`.

Each stage does the scalar code's operations in its order, so a certified lane's results
are the scalar's to the bit. A lane is certified when both clips and the posterior's pass
their certificates and (for ``w < 1``) both factors succeed at the first jitter level with
finite entries; any other lane (a clip through the eigenvalues, jitter, a non-finite entry)
runs :func:`~resloc.cl.kernels_split.split_ci_update` itself, from the same inputs. The
lanes of a round are distinct robots, so the order of the lanes' writes does not matter.

=============================  ==========================================================
kernel function                twin
=============================  ==========================================================
:func:`split_ci_lanes`         ``split_ci_update`` of each fused lane (intersect_lanes)
:func:`split_lane_scratch`     (the lanes' rows, once per step)
=============================  ==========================================================
"""

from __future__ import annotations

import numpy as np

from resloc.cl import kernels_ci_weight as _kernels_ci_weight
from resloc.cl import kernels_fusion as _kernels_fusion
from resloc.cl import kernels_gauge as _kernels_gauge
from resloc.cl import kernels_lane_rows as _kernels_lane_rows
from resloc.cl import kernels_math as _kernels_math
from resloc.cl import kernels_split as _kernels_split
from resloc.cl import kernels_split_pieces as _kernels_split_pieces
from resloc.cl.kernels_ci_weight import (
    ci_cost,
    det3_scaled_entries,
    first_best,
    gram,
    grid_costs,
)
from resloc.cl.kernels_fusion import CI, SPLIT_CI
from resloc.cl.kernels_gauge import range_bearing_jacobians_into
from resloc.cl.kernels_lane_rows import (
    R_A,
    R_AI,
    R_B,
    R_BEST,
    R_BI,
    R_COST,
    R_DET,
    R_DP,
    R_G,
    R_GDI,
    R_GII,
    R_II,
    R_IJ,
    R_IN,
    R_IP,
    R_KBEST,
    R_LANE,
    R_NU,
    R_OK,
    R_OKA,
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
    SPLIT_LANE_ROWS,
    S,
    gather_lane,
    pad_lanes,
    put4,
    put9,
    row4,
    row9,
)
from resloc.cl.kernels_math import (
    jit_inline,
    jit_lanes,
    repair3,
    stamp_with_pieces,
    store_covariance,
    wrap,
)
from resloc.cl.kernels_split import split_ci_update
from resloc.cl.kernels_split_pieces import (
    clip_certified,
    jacobians_of,
    minus9,
    reduce_i9,
    reduce_j9,
    split_update_of,
)

_jit = jit_lanes

__all__ = ["SPLIT_LANE_ROWS", "split_ci_lanes", "split_lane_scratch", "weight_lanes"]


@_jit
def split_lane_scratch(fusion):
    """The lanes' rows of :func:`split_ci_lanes` and of
    :func:`resloc.cl.kernels_ci_lanes.ci_lanes`, ``(SPLIT_LANE_ROWS + G, LANE_STRIDE)`` for
    split CI and ``ci`` (``G``: the grid's candidate weights), no columns for another
    method."""
    columns = S if fusion[0] == SPLIT_CI or fusion[0] == CI else 0
    return np.empty((SPLIT_LANE_ROWS + fusion[2].shape[1], columns))


@jit_inline
def _parts(f, k):
    """Lane ``k``'s clipped independent parts, dependent parts, Jacobians, both clips'
    certificate: ``(ok, I_i, I_j, D_i, D_j, H_i, H_j)``."""
    Pi = row9(f, R_PI, k)
    Pj = row9(f, R_PJ, k)
    ok_i, Ii = clip_certified(Pi, row9(f, R_II, k))
    ok_j, Ij = clip_certified(Pj, row9(f, R_IJ, k))
    Hi, Hj = jacobians_of(
        f[R_X * S + k], f[(R_X + 1) * S + k], f[R_XR * S + k], f[(R_XR + 1) * S + k]
    )
    return ok_i & ok_j, Pi, Ii, Ij, minus9(Pi, Ii), minus9(Pj, Ij), Hi, Hj


@_jit
def _weight_inputs_lanes(f, m, R, det):
    """Stage 1 for lanes ``0 .. m - 1``: the clips' certificate and the weight's inputs
    (:func:`resloc.cl.kernels_ci_weight.weight_of` with ``split``)."""
    r00 = R[0, 0]
    r01 = R[0, 1]
    r10 = R[1, 0]
    r11 = R[1, 1]
    for k in range(m):
        ok, _Pi, Ii, Ij, Di, Dj, Hi, Hj = _parts(f, k)
        a, cd = reduce_i9(Di, Hi)
        b = reduce_j9(Dj, Hj)
        g = gram(cd, cd)
        ai, ci = reduce_i9(Ii, Hi)
        gdi = gram(cd, ci)
        gii = gram(ci, ci)
        bj = reduce_j9(Ij, Hj)
        tr_i = Di[0] + Di[4] + Di[8]
        tr_ip = Ii[0] + Ii[4] + Ii[8]
        prior = det3_scaled_entries(Di, 1.0, Ii) if det else tr_i + tr_ip
        put4(f, R_A, k, a)
        put4(f, R_AI, k, ai)
        put4(f, R_B, k, b)
        put4(f, R_BI, k, (bj[0] + r00, bj[1] + r01, bj[2] + r10, bj[3] + r11))
        put4(f, R_G, k, g)
        put4(f, R_GDI, k, gdi)
        put4(f, R_GII, k, gii)
        f[R_TR * S + k] = tr_i
        f[R_TRP * S + k] = tr_ip
        f[R_PRIOR * S + k] = prior
        f[R_OKA * S + k] = 1.0 if ok else 0.0
        f[R_DET * S + k] = 0.0
        put9(f, R_DP, k, Di)
        put9(f, R_IP, k, Ii)


@_jit
def weight_lanes(f, m, grid, det, R, split):
    """Stage 2 (``ci``'s lanes too, ``split`` False: the rows ``R_AI``, ``R_BI``, ``R_GDI``,
    ``R_GII``, ``R_IP``, ``R_TRP`` then unread, ``R_DET`` read): the weight of lanes
    ``0 .. m - 1`` into row ``R_W``, as
    :func:`resloc.cl.kernels_ci_weight._search_weight`: lane by lane, the grid's costs (its
    :func:`~resloc.cl.kernels_ci_weight.grid_costs`, a SIMD loop over the candidates) and
    their first best (:func:`~resloc.cl.kernels_ci_weight.first_best`); then, over the lanes
    without branches, the parabola through the best and its neighbours, the refinement
    kept where not worse, ``1.0`` where no weight beats the prior (the refinement's three
    dependent divisions, ~45 ns a lane in the scalar search, overlap across lanes).
    (Measured against the whole search over lanes, the candidates outside and the lanes
    inside, three candidates a pass: 8 lanes 1.26 us there against 0.83 us by the scalar
    search lane by lane; about 60 flops and a division per candidate and lane either way.)"""
    n = grid.shape[1]
    R4 = (R[0, 0], R[0, 1], R[1, 0], R[1, 1])
    for k in range(m):
        cost = f[R_COST * S + k * n : R_COST * S + (k + 1) * n]
        grid_costs(
            grid, det, split, f[R_TR * S + k], f[R_DET * S + k], row4(f, R_A, k), row4(f, R_AI, k),
            row4(f, R_B, k), row4(f, R_BI, k), row4(f, R_G, k), row4(f, R_GDI, k),
            row4(f, R_GII, k), row9(f, R_DP, k), row9(f, R_IP, k), f[R_TRP * S + k], R4, cost,
        )  # fmt: skip
        best, kb = first_best(cost, n)
        f[R_BEST * S + k] = best
        f[R_KBEST * S + k] = kb
    h = grid[0, 1] - grid[0, 0]
    first = grid[0, 0]
    last = grid[0, n - 1]
    for k in range(m):
        best = f[R_BEST * S + k]
        kb = int(f[R_KBEST * S + k])
        kc = min(max(kb, 1), n - 2)
        at = R_COST * S + k * n + kc
        c0 = f[at - 1]
        c1 = f[at]
        c2 = f[at + 1]
        denom = c0 - 2.0 * c1 + c2
        shift = 0.5 * h * (c0 - c2) / denom if denom > 0.0 else 0.0
        shift = min(max(shift, -h), h)
        w = min(max(grid[0, kc] + shift, first), last) if kb == kc else grid[0, kb]
        refined = ci_cost(
            1.0 / w, 1.0 / (1.0 - w), det, split, f[R_TR * S + k], f[R_DET * S + k],
            row4(f, R_A, k),
            row4(f, R_AI, k), row4(f, R_B, k), row4(f, R_BI, k), row4(f, R_G, k),
            row4(f, R_GDI, k), row4(f, R_GII, k), row9(f, R_DP, k), row9(f, R_IP, k),
            f[R_TRP * S + k], R4,
        )  # fmt: skip
        kept = refined <= best
        best = refined if kept else best
        w = w if kept else grid[0, kb]
        f[R_W * S + k] = w if best < f[R_PRIOR * S + k] else 1.0


@_jit
def _update_lanes(f, m, R, jitter0):
    """Stage 3: the update of lanes ``0 .. m - 1`` with their weights (row ``R_W``) by
    :func:`~resloc.cl.kernels_split_pieces.split_update_of` (the scalar kernel's after the
    weight, its factors at the first jitter level): ``x_i``, ``sym(P_n)`` and its test, i's
    new independent part, certified (row ``R_OK``, 1.0)."""
    R4 = (R[0, 0], R[0, 1], R[1, 0], R[1, 1])
    for k in range(m):
        ok, Pi, Ii, _Ij, Di, Dj, Hi, Hj = _parts(f, k)
        good, xn, T, pd, part = split_update_of(
            ok, Pi, Ii, Di, Dj, Hi, Hj, f[R_W * S + k],
            (f[R_S * S + k], f[(R_S + 1) * S + k], f[(R_S + 2) * S + k]),
            (
                f[R_PXZ * S + k], f[(R_PXZ + 1) * S + k], f[(R_PXZ + 2) * S + k],
                f[(R_PXZ + 3) * S + k], f[(R_PXZ + 4) * S + k], f[(R_PXZ + 5) * S + k],
            ),
            (f[R_X * S + k], f[(R_X + 1) * S + k], f[(R_X + 2) * S + k]),
            f[R_NU * S + k], f[(R_NU + 1) * S + k], R4, jitter0,
        )  # fmt: skip
        f[R_OK * S + k] = 1.0 if good else 0.0
        f[R_XN * S + k] = xn[0]
        f[(R_XN + 1) * S + k] = xn[1]
        f[(R_XN + 2) * S + k] = xn[2]
        put9(f, R_PN, k, T)
        f[R_PD * S + k] = 1.0 if pd else 0.0
        put4(f, R_IN, k, (part[0], part[1], part[2], part[3]))
        f[(R_IN + 4) * S + k] = part[4]
        f[(R_IN + 5) * S + k] = part[5]


@_jit
def split_ci_lanes(
    x, P, P_ref, lane_e, obs, src, n, xi, xr, update, moments, pxz, inflation, decision,
    options, fusion, out, work, linearized, lanes,
):  # fmt: skip
    """Split CI of every fused lane (``decision[3] == 1``) of a round: the lanes' inputs
    gathered into ``lanes`` (:func:`split_lane_scratch`; padded to whole blocks with copies
    of the first), the three stages above, then each certified lane's results written
    (``x_i``, ``P_i`` symmetrized and repaired as :func:`store_covariance` does, i's
    independent part) and every other lane updated by ``split_ci_update`` itself. Arguments
    and result as :func:`resloc.cl.kernels_round_stages.intersect_lanes` (False: a
    covariance without a Cholesky factor). Twin: its ``split_ci_update`` loop."""
    R, jitter = options[0], options[8]
    flags = out[2]
    Pi, Pxz, K, Hi, Hj, A3, T3, Pn = work[:8]
    independent = fusion[4]
    P_nb_ind = fusion[5]
    f = lanes.reshape(lanes.size)
    m = 0
    for c in range(n):
        if decision[3, c] != 1.0:
            continue
        e = lane_e[c]
        i = obs[c]
        r = src[c]
        g = inflation[c]
        gather_lane(f, m, i, r, g, c, P, P_ref, xi, xr, pxz, moments, R, update)
        for a in range(3):
            for b in range(3):
                f[(R_II + 3 * a + b) * S + m] = independent[i, a, b]
                f[(R_IJ + 3 * a + b) * S + m] = P_nb_ind[e, a, b]
        m += 1
    if m == 0:
        return True
    m2 = pad_lanes(f, m)
    _weight_inputs_lanes(f, m2, R, fusion[1])
    weight_lanes(f, m, fusion[2], fusion[1], R, True)
    _update_lanes(f, m2, R, jitter[0])
    for k in range(m):
        c = int(f[R_LANE * S + k])
        e = lane_e[c]
        i = obs[c]
        if f[R_OK * S + k] == 1.0 and not linearized:
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
            v00 = f[R_IN * S + k]
            v01 = f[(R_IN + 1) * S + k]
            v02 = f[(R_IN + 2) * S + k]
            v11 = f[(R_IN + 3) * S + k]
            v12 = f[(R_IN + 4) * S + k]
            v22 = f[(R_IN + 5) * S + k]
            independent[i, 0, 0] = v00
            independent[i, 1, 1] = v11
            independent[i, 2, 2] = v22
            independent[i, 0, 1] = independent[i, 1, 0] = v01
            independent[i, 0, 2] = independent[i, 2, 0] = v02
            independent[i, 1, 2] = independent[i, 2, 1] = v12
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
            if not split_ci_update(
                x, e, i, xi0, xi1, xi[2, c], Pi, P_ref[src[c]], update[0, c], update[1, c],
                S00, S01, S11, Pxz, linearized, Hi, Hj, 0.0, 0.0, 0.0, R, fusion, jitter, K,
                A3, T3, Pn,
            ):  # fmt: skip
                return False
            if store_covariance(P, i, Pn, T3):
                flags[4, e] = True
    return True


for _dispatcher in (
    split_lane_scratch,
    _weight_inputs_lanes,
    weight_lanes,
    _update_lanes,
    split_ci_lanes,
):
    stamp_with_pieces(
        _dispatcher, _kernels_math, _kernels_fusion, _kernels_ci_weight, _kernels_gauge,
        _kernels_lane_rows, _kernels_split, _kernels_split_pieces,
    )  # fmt: skip
