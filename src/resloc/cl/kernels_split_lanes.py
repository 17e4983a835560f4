"""Split CI's update of a round's fused lanes in SIMD stages (``split_ci`` in the link rounds,
:func:`resloc.cl.kernels_round_stages.intersect_lanes`).

:func:`resloc.cl.kernels_split.split_ci_update` is scalar code, lane after lane (~800 ns a
fused lane: three clips, the weight, the inflated update, the statistical linearization's
factor and solves, the Joseph sandwich, the posterior's clip). Here the fused lanes of a
round are gathered by lane into the rows of one array (:data:`LANE_STRIDE` columns, a row
per input), then each step of the update runs as a loop over the lanes, free of branches,
with the certificates the scalar code takes its fast branch on computed for every lane
(stages 1 and 3):

1. :func:`_weight_inputs_lanes`: both clips' certificates (``0 < P_ind < P`` by Sylvester's
   criterion, :func:`resloc.cl.kernels_split._clip_independent`), the dependent parts and
   the weight's 2 x 2 reductions (:func:`resloc.cl.kernels_fusion.weight_of`);
2. :func:`_weight_lanes`: the weight, lane by lane, by the scalar code's own search
   (:func:`resloc.cl.kernels_fusion._search_weight`, already a SIMD loop over the grid's
   candidates) from the lane's rows;
3. :func:`_update_lanes`: the inflated update (:func:`resloc.cl.kernels_fusion.
   inflated_update`, its Cholesky factor of ``S`` without jitter), ``A``'s factor without
   jitter and the linearization's solves, the Joseph form of the independent part and the
   posterior's clip certificate (:func:`resloc.cl.kernels_split._split_ci_link`).

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

import math

import numpy as np

from resloc.cl import kernels_fusion as _kernels_fusion
from resloc.cl import kernels_gauge as _kernels_gauge
from resloc.cl import kernels_math as _kernels_math
from resloc.cl import kernels_split as _kernels_split
from resloc.cl.kernels_fusion import (
    SPLIT_CI,
    ci_cost,
    det3_scaled_entries,
    first_best,
    gram,
    grid_costs,
)
from resloc.cl.kernels_gauge import range_bearing_jacobians_into
from resloc.cl.kernels_joint_lanes import LANE_STRIDE
from resloc.cl.kernels_math import (
    jit_inline,
    jit_lanes,
    repair3,
    stamp_with_pieces,
    store_covariance,
    wrap,
)
from resloc.cl.kernels_split import split_ci_update
from resloc.models.measurement import MIN_RANGE

_jit = jit_lanes
_MIN_R2 = MIN_RANGE**2  # kernels_gauge's clamp of the squared range, computed alike

__all__ = ["SPLIT_LANE_ROWS", "split_ci_lanes", "split_lane_scratch"]

S = LANE_STRIDE
# The rows of the lanes' array (lane k in column k). Gathered: P_i (times the recovery's
# inflation), P_j, i's independent part as stored, j's transmitted one (9 rows each, by
# row), x_i, x_j's position, P^xz (by row), S (00, 01, 11), the innovation, the lane.
_PI = 0
_PJ = 9
_II = 18
_IJ = 27
_X = 36
_XR = 39
_PXZ = 41
_S = 47
_NU = 50
_LANE = 52
# The weight's inputs (_weight_inputs_lanes): the 2 x 2 reductions a, ai, b, bi, g, gdi,
# gii (4 rows each), tr(D_i), tr(I_i), the prior's cost, both clips certified (1.0), the
# dependent and independent parts of P_i (9 rows each, for the determinant's cost).
_A = 53
_AI = 57
_B = 61
_BI = 65
_G = 69
_GDI = 73
_GII = 77
_TR = 81
_TRP = 82
_PRIOR = 83
_OKA = 84
_DP = 85
_IP = 94
# The weight (_weight_lanes): the best cost and its index on the grid, the weight.
_BEST = 103
_KBEST = 104
_W = 105
# The update (_update_lanes): x_i's new estimate (its heading not wrapped), the posterior
# symmetrized (9), i's new independent part (00, 01, 02, 11, 12, 22), certified (1.0), the
# posterior positive definite by :func:`~resloc.cl.kernels_math.is_pd3`'s test (1.0).
_XN = 106
_PN = 109
_IN = 118
_OK = 124
_PD = 125
# The grid's costs, lane after lane (lane k's G costs from _COST * S + k * G on).
_COST = 126
#: The rows of :func:`split_lane_scratch` before the grid's costs (G rows more).
SPLIT_LANE_ROWS = _COST
#: The fused lanes are padded to whole blocks of this many (copies of the first).
_BLOCK = 8


@_jit
def split_lane_scratch(fusion):
    """The lanes' rows of :func:`split_ci_lanes`, ``(SPLIT_LANE_ROWS + G, LANE_STRIDE)``
    for split CI (``G``: the grid's candidate weights), no columns for another method."""
    columns = S if fusion[0] == SPLIT_CI else 0
    return np.empty((SPLIT_LANE_ROWS + fusion[2].shape[1], columns))


@jit_inline
def _row9(f, row, k):
    """Rows ``row .. row + 8`` of lane ``k`` as a 9-tuple (a 3 x 3 matrix by row)."""
    return (
        f[row * S + k], f[(row + 1) * S + k], f[(row + 2) * S + k], f[(row + 3) * S + k],
        f[(row + 4) * S + k], f[(row + 5) * S + k], f[(row + 6) * S + k],
        f[(row + 7) * S + k], f[(row + 8) * S + k],
    )  # fmt: skip


@jit_inline
def _row4(f, row, k):
    return (f[row * S + k], f[(row + 1) * S + k], f[(row + 2) * S + k], f[(row + 3) * S + k])


@jit_inline
def _put4(f, row, k, v):
    """A 4-tuple ``v`` into rows ``row .. row + 3`` of lane ``k``."""
    f[row * S + k] = v[0]
    f[(row + 1) * S + k] = v[1]
    f[(row + 2) * S + k] = v[2]
    f[(row + 3) * S + k] = v[3]


@jit_inline
def _put9(f, row, k, v):
    """A 9-tuple ``v`` into rows ``row .. row + 8`` of lane ``k``."""
    _put4(f, row, k, (v[0], v[1], v[2], v[3]))
    _put4(f, row + 4, k, (v[4], v[5], v[6], v[7]))
    f[(row + 8) * S + k] = v[8]


@jit_inline
def _jacobians(xi0, xi1, xr0, xr1):
    """``(H_i, H_j)`` as 6-tuples by row: the operations of
    :func:`~resloc.cl.kernels_gauge.range_bearing_jacobians_into` (``H_i = -H_j`` but for
    ``H_i[1, 2] = -1``; ``H_i[0, 2]`` is ``-0.0`` there too)."""
    dx = xr0 - xi0
    dy = xr1 - xi1
    q = dx * dx + dy * dy
    q = _MIN_R2 if q < _MIN_R2 else q
    r = math.sqrt(q)
    j00 = dx / r
    j01 = dy / r
    j10 = -dy / q
    j11 = dx / q
    return (-j00, -j01, -0.0, -j10, -j11, -1.0), (j00, j01, 0.0, j10, j11, 0.0)


@jit_inline
def _pd6(m00, m01, m02, m11, m12, m22):
    """Sylvester's criterion on a symmetric 3 x 3 matrix of upper entries ``m``, without
    branches (:func:`resloc.cl.kernels_split._is_pd6`)."""
    m2 = m00 * m11 - m01 * m01
    det = (
        m00 * (m11 * m22 - m12 * m12)
        - m01 * (m01 * m22 - m12 * m02)
        + m02 * (m01 * m12 - m11 * m02)
    )
    return (m00 > 0.0) & (m2 > 0.0) & (det > 0.0)


@jit_inline
def _clip_certified(P, J):
    """``(certified, sym(J))`` (9-tuples by row): :func:`resloc.cl.kernels_split.
    _clip_independent`'s certificate ``0 < J < P`` and the part it then keeps."""
    i00 = J[0]
    i11 = J[4]
    i22 = J[8]
    i01 = 0.5 * (J[1] + J[3])
    i02 = 0.5 * (J[2] + J[6])
    i12 = 0.5 * (J[5] + J[7])
    ok = _pd6(i00, i01, i02, i11, i12, i22) & _pd6(
        P[0] - i00,
        0.5 * (P[1] + P[3]) - i01,
        0.5 * (P[2] + P[6]) - i02,
        P[4] - i11,
        0.5 * (P[5] + P[7]) - i12,
        P[8] - i22,
    )
    return ok, (i00, i01, i02, i01, i11, i12, i02, i12, i22)


@jit_inline
def _minus(A, B):
    """``A - B`` of 9-tuples."""
    return (
        A[0] - B[0], A[1] - B[1], A[2] - B[2], A[3] - B[3], A[4] - B[4], A[5] - B[5],
        A[6] - B[6], A[7] - B[7], A[8] - B[8],
    )  # fmt: skip


@jit_inline
def _reduce_i(D, H):
    """:func:`resloc.cl.kernels_fusion.reduce_i` of a 9-tuple ``D`` and 6-tuple ``H``."""
    c00 = D[0] * H[0] + D[1] * H[1] + D[2] * H[2]
    c01 = D[0] * H[3] + D[1] * H[4] + D[2] * H[5]
    c10 = D[3] * H[0] + D[4] * H[1] + D[5] * H[2]
    c11 = D[3] * H[3] + D[4] * H[4] + D[5] * H[5]
    c20 = D[6] * H[0] + D[7] * H[1] + D[8] * H[2]
    c21 = D[6] * H[3] + D[7] * H[4] + D[8] * H[5]
    a00 = H[0] * c00 + H[1] * c10 + H[2] * c20
    a01 = H[0] * c01 + H[1] * c11 + H[2] * c21
    a10 = H[3] * c00 + H[4] * c10 + H[5] * c20
    a11 = H[3] * c01 + H[4] * c11 + H[5] * c21
    return (a00, a01, a10, a11), (c00, c01, c10, c11, c20, c21)


@jit_inline
def _reduce_j(D, H):
    """:func:`resloc.cl.kernels_fusion.reduce_j` of a 9-tuple ``D`` and 6-tuple ``H``,
    its sums in its order (from ``0.0``)."""
    b00 = b01 = b10 = b11 = 0.0
    for k in range(3):
        t0 = 0.0
        t0 += H[0] * D[k]
        t0 += H[1] * D[3 + k]
        t0 += H[2] * D[6 + k]
        t1 = 0.0
        t1 += H[3] * D[k]
        t1 += H[4] * D[3 + k]
        t1 += H[5] * D[6 + k]
        b00 += t0 * H[k]
        b01 += t0 * H[3 + k]
        b10 += t1 * H[k]
        b11 += t1 * H[3 + k]
    return (b00, b01, b10, b11)


@jit_inline
def _parts(f, k):
    """Lane ``k``'s clipped independent parts, dependent parts, Jacobians, both clips'
    certificate: ``(ok, I_i, I_j, D_i, D_j, H_i, H_j)``."""
    Pi = _row9(f, _PI, k)
    Pj = _row9(f, _PJ, k)
    ok_i, Ii = _clip_certified(Pi, _row9(f, _II, k))
    ok_j, Ij = _clip_certified(Pj, _row9(f, _IJ, k))
    Hi, Hj = _jacobians(f[_X * S + k], f[(_X + 1) * S + k], f[_XR * S + k], f[(_XR + 1) * S + k])
    return ok_i & ok_j, Pi, Ii, Ij, _minus(Pi, Ii), _minus(Pj, Ij), Hi, Hj


@_jit
def _weight_inputs_lanes(f, m, R, det):
    """Stage 1 for lanes ``0 .. m - 1``: the clips' certificate and the weight's inputs
    (:func:`resloc.cl.kernels_fusion.weight_of` with ``split``)."""
    r00 = R[0, 0]
    r01 = R[0, 1]
    r10 = R[1, 0]
    r11 = R[1, 1]
    for k in range(m):
        ok, _Pi, Ii, Ij, Di, Dj, Hi, Hj = _parts(f, k)
        a, cd = _reduce_i(Di, Hi)
        b = _reduce_j(Dj, Hj)
        g = gram(cd, cd)
        ai, ci = _reduce_i(Ii, Hi)
        gdi = gram(cd, ci)
        gii = gram(ci, ci)
        bj = _reduce_j(Ij, Hj)
        tr_i = Di[0] + Di[4] + Di[8]
        tr_ip = Ii[0] + Ii[4] + Ii[8]
        prior = det3_scaled_entries(Di, 1.0, Ii) if det else tr_i + tr_ip
        _put4(f, _A, k, a)
        _put4(f, _AI, k, ai)
        _put4(f, _B, k, b)
        _put4(f, _BI, k, (bj[0] + r00, bj[1] + r01, bj[2] + r10, bj[3] + r11))
        _put4(f, _G, k, g)
        _put4(f, _GDI, k, gdi)
        _put4(f, _GII, k, gii)
        f[_TR * S + k] = tr_i
        f[_TRP * S + k] = tr_ip
        f[_PRIOR * S + k] = prior
        f[_OKA * S + k] = 1.0 if ok else 0.0
        _put9(f, _DP, k, Di)
        _put9(f, _IP, k, Ii)


@_jit
def _weight_lanes(f, m, grid, det, R):
    """Stage 2: the weight of lanes ``0 .. m - 1`` into row ``_W``, as
    :func:`resloc.cl.kernels_fusion._search_weight`: lane by lane, the grid's costs (its
    :func:`~resloc.cl.kernels_fusion.grid_costs`, a SIMD loop over the candidates) and
    their first best (:func:`~resloc.cl.kernels_fusion.first_best`); then, over the lanes
    without branches, the parabola through the best and its neighbours, the refinement
    kept where not worse, ``1.0`` where no weight beats the prior (the refinement's three
    dependent divisions, ~45 ns a lane in the scalar search, overlap across lanes).
    (Measured against the whole search over lanes, the candidates outside and the lanes
    inside, three candidates a pass: 8 lanes 1.26 us there against 0.83 us by the scalar
    search lane by lane; about 60 flops and a division per candidate and lane either way.)"""
    n = grid.shape[1]
    R4 = (R[0, 0], R[0, 1], R[1, 0], R[1, 1])
    for k in range(m):
        cost = f[_COST * S + k * n : _COST * S + (k + 1) * n]
        grid_costs(
            grid, det, True, f[_TR * S + k], 0.0, _row4(f, _A, k), _row4(f, _AI, k),
            _row4(f, _B, k), _row4(f, _BI, k), _row4(f, _G, k), _row4(f, _GDI, k),
            _row4(f, _GII, k), _row9(f, _DP, k), _row9(f, _IP, k), f[_TRP * S + k], R4, cost,
        )  # fmt: skip
        best, kb = first_best(cost, n)
        f[_BEST * S + k] = best
        f[_KBEST * S + k] = kb
    h = grid[0, 1] - grid[0, 0]
    first = grid[0, 0]
    last = grid[0, n - 1]
    for k in range(m):
        best = f[_BEST * S + k]
        kb = int(f[_KBEST * S + k])
        kc = min(max(kb, 1), n - 2)
        at = _COST * S + k * n + kc
        c0 = f[at - 1]
        c1 = f[at]
        c2 = f[at + 1]
        denom = c0 - 2.0 * c1 + c2
        shift = 0.5 * h * (c0 - c2) / denom if denom > 0.0 else 0.0
        shift = min(max(shift, -h), h)
        w = min(max(grid[0, kc] + shift, first), last) if kb == kc else grid[0, kb]
        refined = ci_cost(
            1.0 / w, 1.0 / (1.0 - w), det, True, f[_TR * S + k], 0.0, _row4(f, _A, k),
            _row4(f, _AI, k), _row4(f, _B, k), _row4(f, _BI, k), _row4(f, _G, k),
            _row4(f, _GDI, k), _row4(f, _GII, k), _row9(f, _DP, k), _row9(f, _IP, k),
            f[_TRP * S + k], R4,
        )  # fmt: skip
        kept = refined <= best
        best = refined if kept else best
        w = w if kept else grid[0, kb]
        f[_W * S + k] = w if best < f[_PRIOR * S + k] else 1.0


@jit_inline
def _is_pd9(T):
    """:func:`~resloc.cl.kernels_math.is_pd3` of a 9-tuple by row, without branches."""
    m2 = T[0] * T[4] - T[1] * T[3]
    det = (
        T[0] * (T[4] * T[8] - T[5] * T[7])
        - T[1] * (T[3] * T[8] - T[5] * T[6])
        + T[2] * (T[3] * T[7] - T[4] * T[6])
    )
    return (T[0] > 0.0) & (m2 > 0.0) & (det > 0.0) & (abs(det) < math.inf)


@_jit
def _update_lanes(f, m, R, jitter0):
    """Stage 3: the update of lanes ``0 .. m - 1`` with their weights (row ``_W``), as
    :func:`resloc.cl.kernels_split._split_ci_link`: the inflated update
    (:func:`resloc.cl.kernels_fusion.inflated_update`, EKF-free: ``P_n = A - K S K^T``),
    ``H = (A^-1 P^xz)^T``, ``(I - K H) I_i (I - K H)^T + K R K^T`` and the posterior's clip;
    ``w >= 1``: the prior and its clipped part, clipped to it. The factors of ``S`` and
    ``A`` at the first jitter level (``jitter0``) only; certified (row ``_OK``, 1.0) where
    they and every clip's certificate pass."""
    r00 = R[0, 0]
    r01 = R[0, 1]
    r10 = R[1, 0]
    r11 = R[1, 1]
    for k in range(m):
        ok, Pi, Ii, _Ij, Di, Dj, Hi, Hj = _parts(f, k)
        hdh, dh = _reduce_i(Di, Hi)
        hdj = _reduce_j(Dj, Hj)
        w = f[_W * S + k]
        keep = w >= 1.0
        fi = 1.0 / w - 1.0
        fj = 1.0 / (1.0 - w) - 1.0
        d00 = hdh[0] * fi
        d01 = hdh[1] * fi
        d10 = hdh[2] * fi
        d11 = hdh[3] * fi
        e00 = hdj[0] * fj
        e01 = hdj[1] * fj
        e10 = hdj[2] * fj
        e11 = hdj[3] * fj
        # A = sym(P_i + f_i D_i)
        a00 = 0.5 * ((Pi[0] + Di[0] * fi) + (Pi[0] + Di[0] * fi))
        a01 = 0.5 * ((Pi[1] + Di[1] * fi) + (Pi[3] + Di[3] * fi))
        a02 = 0.5 * ((Pi[2] + Di[2] * fi) + (Pi[6] + Di[6] * fi))
        a10 = 0.5 * ((Pi[3] + Di[3] * fi) + (Pi[1] + Di[1] * fi))
        a11 = 0.5 * ((Pi[4] + Di[4] * fi) + (Pi[4] + Di[4] * fi))
        a12 = 0.5 * ((Pi[5] + Di[5] * fi) + (Pi[7] + Di[7] * fi))
        a20 = 0.5 * ((Pi[6] + Di[6] * fi) + (Pi[2] + Di[2] * fi))
        a21 = 0.5 * ((Pi[7] + Di[7] * fi) + (Pi[5] + Di[5] * fi))
        a22 = 0.5 * ((Pi[8] + Di[8] * fi) + (Pi[8] + Di[8] * fi))
        S00 = f[_S * S + k]
        S01 = f[(_S + 1) * S + k]
        S11 = f[(_S + 2) * S + k]
        s00 = S00 + d00 + e00
        s11 = S11 + d11 + e11
        s01 = 0.5 * ((S01 + d01 + e01) + (S01 + d10 + e10))
        # chol2 at its first level
        fin2 = (abs(s00) < math.inf) & (abs(s01) < math.inf) & (abs(s11) < math.inf)
        scale2 = (abs(s00) + abs(s11)) / 2.0
        scale2 = 1e-300 if scale2 < 1e-300 else scale2
        eps2 = jitter0 * scale2
        p2 = s00 + eps2
        l00 = math.sqrt(p2)
        l10 = s01 / l00
        q2 = s11 + eps2 - l10 * l10
        l11 = math.sqrt(q2)
        ok_s = fin2 & (p2 > 0.0) & (q2 > 0.0)
        # P^xz + f_i D_i H_i^T, then K by the factor of S (solve2)
        x00 = f[_PXZ * S + k] + dh[0] * fi
        x01 = f[(_PXZ + 1) * S + k] + dh[1] * fi
        x10 = f[(_PXZ + 2) * S + k] + dh[2] * fi
        x11 = f[(_PXZ + 3) * S + k] + dh[3] * fi
        x20 = f[(_PXZ + 4) * S + k] + dh[4] * fi
        x21 = f[(_PXZ + 5) * S + k] + dh[5] * fi
        y0 = x00 / l00
        k01 = ((x01 - l10 * y0) / l11) / l11
        k00 = (y0 - l10 * k01) / l00
        y0 = x10 / l00
        k11 = ((x11 - l10 * y0) / l11) / l11
        k10 = (y0 - l10 * k11) / l00
        y0 = x20 / l00
        k21 = ((x21 - l10 * y0) / l11) / l11
        k20 = (y0 - l10 * k21) / l00
        nu0 = f[_NU * S + k]
        nu1 = f[(_NU + 1) * S + k]
        f[_XN * S + k] = f[_X * S + k] + (k00 * nu0 + k01 * nu1)
        f[(_XN + 1) * S + k] = f[(_X + 1) * S + k] + (k10 * nu0 + k11 * nu1)
        f[(_XN + 2) * S + k] = f[(_X + 2) * S + k] + (k20 * nu0 + k21 * nu1)
        # A - K S K^T
        t00 = k00 * s00 + k01 * s01
        t01 = k00 * s01 + k01 * s11
        t10 = k10 * s00 + k11 * s01
        t11 = k10 * s01 + k11 * s11
        t20 = k20 * s00 + k21 * s01
        t21 = k20 * s01 + k21 * s11
        n00 = a00 - (t00 * k00 + t01 * k01)
        n01 = a01 - (t00 * k10 + t01 * k11)
        n02 = a02 - (t00 * k20 + t01 * k21)
        n10 = a10 - (t10 * k00 + t11 * k01)
        n11 = a11 - (t10 * k10 + t11 * k11)
        n12 = a12 - (t10 * k20 + t11 * k21)
        n20 = a20 - (t20 * k00 + t21 * k01)
        n21 = a21 - (t20 * k10 + t21 * k11)
        n22 = a22 - (t20 * k20 + t21 * k21)
        # chol3(A) at its first level, then H = (A^-1 P^xz)^T (P^xz inflated)
        fin3 = (
            (abs(a00) < math.inf) & (abs(a01) < math.inf) & (abs(a02) < math.inf)
            & (abs(a10) < math.inf) & (abs(a11) < math.inf) & (abs(a12) < math.inf)
            & (abs(a20) < math.inf) & (abs(a21) < math.inf) & (abs(a22) < math.inf)
        )  # fmt: skip
        scale3 = (abs(a00) + abs(a11) + abs(a22)) / 3.0
        scale3 = 1e-300 if scale3 < 1e-300 else scale3
        eps3 = jitter0 * scale3
        p0 = a00 + eps3
        L00 = math.sqrt(p0)
        L10 = a10 / L00
        L20 = a20 / L00
        p1 = a11 + eps3
        p1 -= L10 * L10
        L11 = math.sqrt(p1)
        L21 = (a21 - L20 * L10) / L11
        p3 = a22 + eps3
        p3 -= L20 * L20
        p3 -= L21 * L21
        L22 = math.sqrt(p3)
        ok_a = fin3 & (p0 > 0.0) & (p1 > 0.0) & (p3 > 0.0)
        y0 = x00 / L00
        y1 = (x10 - L10 * y0) / L11
        y2 = (x20 - L20 * y0 - L21 * y1) / L22
        h02 = y2 / L22
        h01 = (y1 - L21 * h02) / L11
        h00 = (y0 - L10 * h01 - L20 * h02) / L00
        y0 = x01 / L00
        y1 = (x11 - L10 * y0) / L11
        y2 = (x21 - L20 * y0 - L21 * y1) / L22
        h12 = y2 / L22
        h11 = (y1 - L21 * h12) / L11
        h10 = (y0 - L10 * h11 - L20 * h12) / L00
        # G = I - K H; G I_i G^T + K R K^T (sandwich3: (G I_i) G^T)
        g00 = 1.0 - (k00 * h00 + k01 * h10)
        g01 = 0.0 - (k00 * h01 + k01 * h11)
        g02 = 0.0 - (k00 * h02 + k01 * h12)
        g10 = 0.0 - (k10 * h00 + k11 * h10)
        g11 = 1.0 - (k10 * h01 + k11 * h11)
        g12 = 0.0 - (k10 * h02 + k11 * h12)
        g20 = 0.0 - (k20 * h00 + k21 * h10)
        g21 = 0.0 - (k20 * h01 + k21 * h11)
        g22 = 1.0 - (k20 * h02 + k21 * h12)
        u00 = g00 * Ii[0] + g01 * Ii[3] + g02 * Ii[6]
        u01 = g00 * Ii[1] + g01 * Ii[4] + g02 * Ii[7]
        u02 = g00 * Ii[2] + g01 * Ii[5] + g02 * Ii[8]
        u10 = g10 * Ii[0] + g11 * Ii[3] + g12 * Ii[6]
        u11 = g10 * Ii[1] + g11 * Ii[4] + g12 * Ii[7]
        u12 = g10 * Ii[2] + g11 * Ii[5] + g12 * Ii[8]
        u20 = g20 * Ii[0] + g21 * Ii[3] + g22 * Ii[6]
        u21 = g20 * Ii[1] + g21 * Ii[4] + g22 * Ii[7]
        u22 = g20 * Ii[2] + g21 * Ii[5] + g22 * Ii[8]
        q00 = k00 * r00 + k01 * r10
        q01 = k00 * r01 + k01 * r11
        q10 = k10 * r00 + k11 * r10
        q11 = k10 * r01 + k11 * r11
        q20 = k20 * r00 + k21 * r10
        q21 = k20 * r01 + k21 * r11
        j00 = (u00 * g00 + u01 * g01 + u02 * g02) + (q00 * k00 + q01 * k01)
        j01 = (u00 * g10 + u01 * g11 + u02 * g12) + (q00 * k10 + q01 * k11)
        j02 = (u00 * g20 + u01 * g21 + u02 * g22) + (q00 * k20 + q01 * k21)
        j10 = (u10 * g00 + u11 * g01 + u12 * g02) + (q10 * k00 + q11 * k01)
        j11 = (u10 * g10 + u11 * g11 + u12 * g12) + (q10 * k10 + q11 * k11)
        j12 = (u10 * g20 + u11 * g21 + u12 * g22) + (q10 * k20 + q11 * k21)
        j20 = (u20 * g00 + u21 * g01 + u22 * g02) + (q20 * k00 + q21 * k01)
        j21 = (u20 * g10 + u21 * g11 + u22 * g12) + (q20 * k10 + q21 * k11)
        j22 = (u20 * g20 + u21 * g21 + u22 * g22) + (q20 * k20 + q21 * k21)
        # the part to clip, M, and the posterior it is clipped to, Q: w < 1, sym of the
        # above; w >= 1, sym(I_i) and the prior P_i itself
        M = (
            0.5 * (j00 + j00), 0.5 * (j01 + j10), 0.5 * (j02 + j20),
            0.5 * (j10 + j01), 0.5 * (j11 + j11), 0.5 * (j12 + j21),
            0.5 * (j20 + j02), 0.5 * (j21 + j12), 0.5 * (j22 + j22),
        )  # fmt: skip
        Mk = (
            0.5 * (Ii[0] + Ii[0]), 0.5 * (Ii[1] + Ii[3]), 0.5 * (Ii[2] + Ii[6]),
            0.5 * (Ii[3] + Ii[1]), 0.5 * (Ii[4] + Ii[4]), 0.5 * (Ii[5] + Ii[7]),
            0.5 * (Ii[6] + Ii[2]), 0.5 * (Ii[7] + Ii[5]), 0.5 * (Ii[8] + Ii[8]),
        )  # fmt: skip
        Q = (
            0.5 * (n00 + n00), 0.5 * (n01 + n10), 0.5 * (n02 + n20),
            0.5 * (n10 + n01), 0.5 * (n11 + n11), 0.5 * (n12 + n21),
            0.5 * (n20 + n02), 0.5 * (n21 + n12), 0.5 * (n22 + n22),
        )  # fmt: skip
        ok_kept, kept = _clip_certified(Pi, Mk)
        ok_new, new = _clip_certified(Q, M)
        fresh = not keep
        good = ok & ((keep & ok_kept) | (fresh & ok_s & ok_a & ok_new))
        f[_OK * S + k] = 1.0 if good else 0.0
        Pk = (
            0.5 * (Pi[0] + Pi[0]), 0.5 * (Pi[1] + Pi[3]), 0.5 * (Pi[2] + Pi[6]),
            0.5 * (Pi[3] + Pi[1]), 0.5 * (Pi[4] + Pi[4]), 0.5 * (Pi[5] + Pi[7]),
            0.5 * (Pi[6] + Pi[2]), 0.5 * (Pi[7] + Pi[5]), 0.5 * (Pi[8] + Pi[8]),
        )  # fmt: skip
        T = Pk if keep else Q  # store_covariance's sym(P_n)
        _put9(f, _PN, k, T)
        f[_PD * S + k] = 1.0 if _is_pd9(T) else 0.0
        part = kept if keep else new
        _put4(f, _IN, k, (part[0], part[1], part[2], part[4]))
        f[(_IN + 4) * S + k] = part[5]
        f[(_IN + 5) * S + k] = part[8]


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
        for a in range(3):
            for b in range(3):
                f[(_PI + 3 * a + b) * S + m] = P[i, a, b] * g  # g = 1: P_i itself
                f[(_PJ + 3 * a + b) * S + m] = P_ref[r, a, b]
                f[(_II + 3 * a + b) * S + m] = independent[i, a, b]
                f[(_IJ + 3 * a + b) * S + m] = P_nb_ind[e, a, b]
        for a in range(3):
            f[(_X + a) * S + m] = xi[a, c]
        f[_XR * S + m] = xr[0, c]
        f[(_XR + 1) * S + m] = xr[1, c]
        for a in range(6):
            f[(_PXZ + a) * S + m] = pxz[a, c]
        f[_S * S + m] = moments[2, c] + R[0, 0]
        f[(_S + 1) * S + m] = 0.5 * ((moments[3, c] + R[0, 1]) + (moments[3, c] + R[1, 0]))
        f[(_S + 2) * S + m] = moments[4, c] + R[1, 1]
        f[_NU * S + m] = update[0, c]
        f[(_NU + 1) * S + m] = update[1, c]
        f[_LANE * S + m] = c
        m += 1
    if m == 0:
        return True
    m2 = min((m + _BLOCK - 1) // _BLOCK * _BLOCK, S)
    for row in range(_LANE + 1):  # the padding: copies of lane 0, never read
        for k in range(m, m2):
            f[row * S + k] = f[row * S]
    _weight_inputs_lanes(f, m2, R, fusion[1])
    _weight_lanes(f, m, fusion[2], fusion[1], R)
    _update_lanes(f, m2, R, jitter[0])
    for k in range(m):
        c = int(f[_LANE * S + k])
        e = lane_e[c]
        i = obs[c]
        if f[_OK * S + k] == 1.0 and not linearized:
            if f[_W * S + k] < 1.0:
                x[i, 0] = f[_XN * S + k]
                x[i, 1] = f[(_XN + 1) * S + k]
                x[i, 2] = wrap(f[(_XN + 2) * S + k])
            for a in range(3):  # store_covariance, its sym(P_n) and test from stage 3
                for b in range(3):
                    T3[a, b] = f[(_PN + 3 * a + b) * S + k]
            if f[_PD * S + k] != 1.0:
                repair3(T3)
                flags[4, e] = True
            for a in range(3):
                for b in range(3):
                    P[i, a, b] = T3[a, b]
            v00 = f[_IN * S + k]
            v01 = f[(_IN + 1) * S + k]
            v02 = f[(_IN + 2) * S + k]
            v11 = f[(_IN + 3) * S + k]
            v12 = f[(_IN + 4) * S + k]
            v22 = f[(_IN + 5) * S + k]
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
    _weight_lanes,
    _update_lanes,
    split_ci_lanes,
):
    stamp_with_pieces(_dispatcher, _kernels_math, _kernels_fusion, _kernels_gauge, _kernels_split)
