"""The lane pieces of the ``tracked`` and ``factorized`` joints' rounds
(:mod:`resloc.cl.kernels_joint_rounds`): the joint's 6 x 6 Cholesky factors over lanes
(:func:`chol6_lanes`), the points that move both robots (:func:`correlated_points_lanes`)
and ``factorized``'s cross-covariance of every lane with its certificate
(:func:`factorized_cross_lanes`). Each names its twin.
"""

from __future__ import annotations

import math

from resloc.cl import kernels_joint_links as _kernels_joint_links
from resloc.cl import kernels_round_cached as _kernels_round_cached
from resloc.cl.kernels_joint_links import CROSS_CAP
from resloc.cl.kernels_lanes import (
    CHUNK,
    SINCOS_LANES_MAX,
    atan2_lanes,
    sincos_lanes,
    wrap_lanes,
)
from resloc.cl.kernels_math import jit_inline, jit_lanes, stamp_with_pieces
from resloc.cl.kernels_round_cached import padded_lanes

_jit = jit_lanes

__all__ = [
    "CROSS_INPUT_ROWS",
    "LANE_STRIDE",
    "chol6_lanes",
    "correlated_points_lanes",
    "factorized_cross_lanes",
]


@_jit
def chol6_lanes(J, n, L, ok):
    """Lower Cholesky factors of the lanes' symmetric 6 x 6 joints, ``J: (21, C)`` (the
    lower triangle row by row, entry ``(r, c)`` at row ``r (r + 1) / 2 + c``), into ``L``
    (same layout) without jitter, and whether each succeeded (1.0; all entries finite, every
    pivot positive): the first level of :func:`~resloc.cl.kernels_joint_links.chol6`, same
    operations, same order. The arrays have :data:`LANE_STRIDE` columns (flat rows that far
    apart, a compile-time constant as in :func:`~resloc.cl.kernels_link_stages.kalman_lanes`)."""
    Jf = J.reshape(J.size)
    Lf = L.reshape(L.size)
    for c in range(n):
        j00 = Jf[c]
        j10 = Jf[1 * LANE_STRIDE + c]
        j11 = Jf[2 * LANE_STRIDE + c]
        j20 = Jf[3 * LANE_STRIDE + c]
        j21 = Jf[4 * LANE_STRIDE + c]
        j22 = Jf[5 * LANE_STRIDE + c]
        j30 = Jf[6 * LANE_STRIDE + c]
        j31 = Jf[7 * LANE_STRIDE + c]
        j32 = Jf[8 * LANE_STRIDE + c]
        j33 = Jf[9 * LANE_STRIDE + c]
        j40 = Jf[10 * LANE_STRIDE + c]
        j41 = Jf[11 * LANE_STRIDE + c]
        j42 = Jf[12 * LANE_STRIDE + c]
        j43 = Jf[13 * LANE_STRIDE + c]
        j44 = Jf[14 * LANE_STRIDE + c]
        j50 = Jf[15 * LANE_STRIDE + c]
        j51 = Jf[16 * LANE_STRIDE + c]
        j52 = Jf[17 * LANE_STRIDE + c]
        j53 = Jf[18 * LANE_STRIDE + c]
        j54 = Jf[19 * LANE_STRIDE + c]
        j55 = Jf[20 * LANE_STRIDE + c]
        good = True
        good = good & (abs(j00) < math.inf)
        good = good & (abs(j10) < math.inf)
        good = good & (abs(j11) < math.inf)
        good = good & (abs(j20) < math.inf)
        good = good & (abs(j21) < math.inf)
        good = good & (abs(j22) < math.inf)
        good = good & (abs(j30) < math.inf)
        good = good & (abs(j31) < math.inf)
        good = good & (abs(j32) < math.inf)
        good = good & (abs(j33) < math.inf)
        good = good & (abs(j40) < math.inf)
        good = good & (abs(j41) < math.inf)
        good = good & (abs(j42) < math.inf)
        good = good & (abs(j43) < math.inf)
        good = good & (abs(j44) < math.inf)
        good = good & (abs(j50) < math.inf)
        good = good & (abs(j51) < math.inf)
        good = good & (abs(j52) < math.inf)
        good = good & (abs(j53) < math.inf)
        good = good & (abs(j54) < math.inf)
        good = good & (abs(j55) < math.inf)
        s0 = j00
        good = good & (s0 > 0.0)
        d0 = math.sqrt(s0)
        l00 = d0
        l10 = (j10) / d0
        l20 = (j20) / d0
        l30 = (j30) / d0
        l40 = (j40) / d0
        l50 = (j50) / d0
        s1 = (j11) - l10 * l10
        good = good & (s1 > 0.0)
        d1 = math.sqrt(s1)
        l11 = d1
        l21 = ((j21) - l20 * l10) / d1
        l31 = ((j31) - l30 * l10) / d1
        l41 = ((j41) - l40 * l10) / d1
        l51 = ((j51) - l50 * l10) / d1
        s2 = ((j22) - l20 * l20) - l21 * l21
        good = good & (s2 > 0.0)
        d2 = math.sqrt(s2)
        l22 = d2
        l32 = (((j32) - l30 * l20) - l31 * l21) / d2
        l42 = (((j42) - l40 * l20) - l41 * l21) / d2
        l52 = (((j52) - l50 * l20) - l51 * l21) / d2
        s3 = (((j33) - l30 * l30) - l31 * l31) - l32 * l32
        good = good & (s3 > 0.0)
        d3 = math.sqrt(s3)
        l33 = d3
        l43 = ((((j43) - l40 * l30) - l41 * l31) - l42 * l32) / d3
        l53 = ((((j53) - l50 * l30) - l51 * l31) - l52 * l32) / d3
        s4 = ((((j44) - l40 * l40) - l41 * l41) - l42 * l42) - l43 * l43
        good = good & (s4 > 0.0)
        d4 = math.sqrt(s4)
        l44 = d4
        l54 = (((((j54) - l50 * l40) - l51 * l41) - l52 * l42) - l53 * l43) / d4
        s5 = (((((j55) - l50 * l50) - l51 * l51) - l52 * l52) - l53 * l53) - l54 * l54
        good = good & (s5 > 0.0)
        d5 = math.sqrt(s5)
        l55 = d5
        Lf[c] = l00
        Lf[1 * LANE_STRIDE + c] = l10
        Lf[2 * LANE_STRIDE + c] = l11
        Lf[3 * LANE_STRIDE + c] = l20
        Lf[4 * LANE_STRIDE + c] = l21
        Lf[5 * LANE_STRIDE + c] = l22
        Lf[6 * LANE_STRIDE + c] = l30
        Lf[7 * LANE_STRIDE + c] = l31
        Lf[8 * LANE_STRIDE + c] = l32
        Lf[9 * LANE_STRIDE + c] = l33
        Lf[10 * LANE_STRIDE + c] = l40
        Lf[11 * LANE_STRIDE + c] = l41
        Lf[12 * LANE_STRIDE + c] = l42
        Lf[13 * LANE_STRIDE + c] = l43
        Lf[14 * LANE_STRIDE + c] = l44
        Lf[15 * LANE_STRIDE + c] = l50
        Lf[16 * LANE_STRIDE + c] = l51
        Lf[17 * LANE_STRIDE + c] = l52
        Lf[18 * LANE_STRIDE + c] = l53
        Lf[19 * LANE_STRIDE + c] = l54
        Lf[20 * LANE_STRIDE + c] = l55
        ok[c] = 1.0 if good else 0.0


@_jit
def correlated_points_lanes(axis, value, Wm, n, xi, xr, sin_cos, Li, X, Ls, Z0, Z1, sums, bad):
    """Range and bearing of every sigma point (eq. 3) under the correlated joint's factor
    ``[[Li, 0], [X, Ls]]`` and their weighted sums, as
    :func:`~resloc.cl.kernels_link_stages.points_lanes` (whose twin block of
    ``correct_links`` this is too, on the offsets of ``correlated_offsets``): a point of
    i's half moves j's position by ``X``'s column, a point of j's half by ``Ls``'s."""
    for c in range(n):
        sums[0, c] = 0.0
        sums[1, c] = 0.0
        sums[2, c] = 0.0
        sums[3, c] = 0.0
    for k in range(axis.shape[0]):
        b = axis[k]
        w = Wm[k]
        if 0 <= b < 3:  # a point of robot i's half: i's pose and, correlated, j's position
            u = value[k]
            for c in range(n):
                dx = (xr[0, c] + X[0, b, c] * u) - (xi[0, c] + Li[0, b, c] * u)
                dy = (xr[1, c] + X[1, b, c] * u) - (xi[1, c] + Li[1, b, c] * u)
                o2 = Li[2, b, c] * u
                th = xi[2, c] + o2
                so, co = sincos_lanes(o2)
                sn = sin_cos[0, c] * co + sin_cos[1, c] * so
                cs = sin_cos[1, c] * co - sin_cos[0, c] * so
                r = math.sqrt(dx * dx + dy * dy)
                bearing = wrap_lanes(atan2_lanes(dy, dx) - th)
                Z0[k, c] = r
                Z1[k, c] = bearing
                sums[0, c] += r * w
                w_r = w / r
                sums[1, c] += (dy * cs - dx * sn) * w_r
                sums[2, c] += (dx * cs + dy * sn) * w_r
                sums[3, c] += bearing * w
                good = (r > 0.0) & (r < math.inf) & (abs(o2) <= SINCOS_LANES_MAX)
                bad[c] += 0.0 if good else 1.0
        else:  # a point of j's half (moves j's position), or the centre (u = 0)
            bj = b - 3 if b >= 3 else 0
            u = value[k] if b >= 3 else 0.0
            for c in range(n):
                dx = (xr[0, c] + Ls[0, bj, c] * u) - xi[0, c]
                dy = (xr[1, c] + Ls[1, bj, c] * u) - xi[1, c]
                sn = sin_cos[0, c]
                cs = sin_cos[1, c]
                r = math.sqrt(dx * dx + dy * dy)
                bearing = wrap_lanes(atan2_lanes(dy, dx) - xi[2, c])
                Z0[k, c] = r
                Z1[k, c] = bearing
                sums[0, c] += r * w
                w_r = w / r
                sums[1, c] += (dy * cs - dx * sn) * w_r
                sums[2, c] += (dx * cs + dy * sn) * w_r
                sums[3, c] += bearing * w
                good = (r > 0.0) & (r < math.inf)
                bad[c] += 0.0 if good else 1.0


#: Columns of the joints' lane arrays (:mod:`resloc.cl.kernels_joint_rounds`: the blocks,
#: the 6 x 6 joints and factors, the factor's parts, :func:`factorized_cross_lanes`'
#: inputs): one block of lanes more than ``CHUNK``. With ``CHUNK`` columns a row is 2 KiB
#: long, and a lane's entries, one per row, all fall in the same two sets of the first-level
#: cache: a loop that stores a lane's 45 inputs ran at ~150 ns a lane, ~14 ns with this
#: stride (measured, 24 lanes).
LANE_STRIDE = CHUNK + 8

#: Rows of :func:`factorized_cross_lanes`' gathered inputs: robot i's ``A_i``, its factor
#: ``sigma_il``, j's ``sigma_ji`` as the step began, ``P_i`` and ``P_j`` (9 each, by row).
CROSS_INPUT_ROWS = 45


@_jit
def factorized_cross_lanes(joint, P, P_ref, lane_e, obs, src, n, inputs, blocks, J, ok):
    """``factorized``'s cross-covariance of every lane with the certificate that it needs
    no shrink, as :func:`~resloc.cl.kernels_joint_links.factorized_cross` leaves it where
    the certificate holds. The inputs gathered by lane into ``inputs: (CROSS_INPUT_ROWS,
    LANE_STRIDE)`` (lanes ``n`` up to the padded count copies of lane 0, never read), then
    the factors' product, both covariances' first level of ``chol3``, the correlation
    ``L_i^-1 C L_j^-T`` and its norm, and the blocks, in one branch-free loop over lanes
    that LLVM compiles to SIMD (:func:`_cross_of_lanes`). Per lane: ``ok[c]`` 1.0 where
    certified (every entry finite, both factors without jitter, the correlation's Frobenius
    norm or Sylvester's criterion below the cap), the blocks ``P_i``, ``C_ij``, ``P_j``
    into ``blocks: (27, LANE_STRIDE)`` and the lower triangle of their symmetrized joint
    into ``J: (21, LANE_STRIDE)`` (as ``_joint_into_lane``); 0.0 elsewhere (jitter, a
    shrink, a non-finite entry: the caller runs ``factorized_cross`` itself, whose values
    these lanes' are not). Returns how many of the ``n`` lanes are not certified. The same
    operations in the same order as the scalar piece it replaced (one lane at a time:
    ~165 ns a lane of the joint's blocks, against ~80 for ``tracked``'s), so the same
    values to the bit."""
    N = joint[1]
    nbr = joint[2]
    A = joint[5]
    sig = joint[7]
    sig_pred = joint[8]
    n2 = padded_lanes(n, CHUNK)
    for c in range(n2):
        d = c if c < n else 0
        i = obs[d]
        j = nbr[lane_e[d]]
        s = src[d]
        li = i % N
        lj = j % N
        for a in range(3):
            for b in range(3):
                k = 3 * a + b
                inputs[k, c] = A[i, a, b]
                inputs[9 + k, c] = sig[i, lj, a, b]
                inputs[18 + k, c] = sig_pred[j, li, a, b]
                inputs[27 + k, c] = P[i, a, b]
                inputs[36 + k, c] = P_ref[s, a, b]
    _cross_of_lanes(n2, inputs, blocks, J, ok)
    full = 0
    for c in range(n):
        full += 1 if ok[c] == 0.0 else 0
    return full


@_jit
def _cross_of_lanes(n, inputs, blocks, J, ok):
    """The arithmetic of :func:`factorized_cross_lanes` on lanes ``0 .. n - 1``: scalars
    only, selects for the branches, the arrays (:data:`LANE_STRIDE` columns) read and written
    through flat views (as :func:`chol6_lanes`): LLVM vectorizes the loop."""
    f = inputs.reshape(inputs.size)
    bf = blocks.reshape(blocks.size)
    Jf = J.reshape(J.size)
    for c in range(n):
        a00 = f[c]
        a01 = f[1 * LANE_STRIDE + c]
        a02 = f[2 * LANE_STRIDE + c]
        a10 = f[3 * LANE_STRIDE + c]
        a11 = f[4 * LANE_STRIDE + c]
        a12 = f[5 * LANE_STRIDE + c]
        a20 = f[6 * LANE_STRIDE + c]
        a21 = f[7 * LANE_STRIDE + c]
        a22 = f[8 * LANE_STRIDE + c]
        s00 = f[9 * LANE_STRIDE + c]
        s01 = f[10 * LANE_STRIDE + c]
        s02 = f[11 * LANE_STRIDE + c]
        s10 = f[12 * LANE_STRIDE + c]
        s11 = f[13 * LANE_STRIDE + c]
        s12 = f[14 * LANE_STRIDE + c]
        s20 = f[15 * LANE_STRIDE + c]
        s21 = f[16 * LANE_STRIDE + c]
        s22 = f[17 * LANE_STRIDE + c]
        p00 = f[18 * LANE_STRIDE + c]
        p01 = f[19 * LANE_STRIDE + c]
        p02 = f[20 * LANE_STRIDE + c]
        p10 = f[21 * LANE_STRIDE + c]
        p11 = f[22 * LANE_STRIDE + c]
        p12 = f[23 * LANE_STRIDE + c]
        p20 = f[24 * LANE_STRIDE + c]
        p21 = f[25 * LANE_STRIDE + c]
        p22 = f[26 * LANE_STRIDE + c]
        pi00 = f[27 * LANE_STRIDE + c]
        pi01 = f[28 * LANE_STRIDE + c]
        pi02 = f[29 * LANE_STRIDE + c]
        pi10 = f[30 * LANE_STRIDE + c]
        pi11 = f[31 * LANE_STRIDE + c]
        pi12 = f[32 * LANE_STRIDE + c]
        pi20 = f[33 * LANE_STRIDE + c]
        pi21 = f[34 * LANE_STRIDE + c]
        pi22 = f[35 * LANE_STRIDE + c]
        pj00 = f[36 * LANE_STRIDE + c]
        pj01 = f[37 * LANE_STRIDE + c]
        pj02 = f[38 * LANE_STRIDE + c]
        pj10 = f[39 * LANE_STRIDE + c]
        pj11 = f[40 * LANE_STRIDE + c]
        pj12 = f[41 * LANE_STRIDE + c]
        pj20 = f[42 * LANE_STRIDE + c]
        pj21 = f[43 * LANE_STRIDE + c]
        pj22 = f[44 * LANE_STRIDE + c]
        t00 = a00 * s00 + a01 * s10 + (a02 * s20)
        t01 = a00 * s01 + a01 * s11 + (a02 * s21)
        t02 = a00 * s02 + a01 * s12 + (a02 * s22)
        t10 = a10 * s00 + a11 * s10 + (a12 * s20)
        t11 = a10 * s01 + a11 * s11 + (a12 * s21)
        t12 = a10 * s02 + a11 * s12 + (a12 * s22)
        t20 = a20 * s00 + a21 * s10 + (a22 * s20)
        t21 = a20 * s01 + a21 * s11 + (a22 * s21)
        t22 = a20 * s02 + a21 * s12 + (a22 * s22)
        c00 = t00 * p00 + t01 * p01 + t02 * p02
        c01 = t00 * p10 + t01 * p11 + t02 * p12
        c02 = t00 * p20 + t01 * p21 + t02 * p22
        c10 = t10 * p00 + t11 * p01 + t12 * p02
        c11 = t10 * p10 + t11 * p11 + t12 * p12
        c12 = t10 * p20 + t11 * p21 + t12 * p22
        c20 = t20 * p00 + t21 * p01 + t22 * p02
        c21 = t20 * p10 + t21 * p11 + t22 * p12
        c22 = t20 * p20 + t21 * p21 + t22 * p22
        good = True
        good = good & (abs(pi00) < math.inf)
        good = good & (abs(pi01) < math.inf)
        good = good & (abs(pi02) < math.inf)
        good = good & (abs(pi10) < math.inf)
        good = good & (abs(pi11) < math.inf)
        good = good & (abs(pi12) < math.inf)
        good = good & (abs(pi20) < math.inf)
        good = good & (abs(pi21) < math.inf)
        good = good & (abs(pi22) < math.inf)
        good = good & (abs(pj00) < math.inf)
        good = good & (abs(pj01) < math.inf)
        good = good & (abs(pj02) < math.inf)
        good = good & (abs(pj10) < math.inf)
        good = good & (abs(pj11) < math.inf)
        good = good & (abs(pj12) < math.inf)
        good = good & (abs(pj20) < math.inf)
        good = good & (abs(pj21) < math.inf)
        good = good & (abs(pj22) < math.inf)
        s = pi00 + 0.0  # the first level of chol3, as _chol3_first_level
        oki = s > 0.0
        i00 = math.sqrt(s) if oki else 1.0
        i10 = pi10 / i00
        i20 = pi20 / i00
        s = (pi11 + 0.0) - i10 * i10
        oki = oki & (s > 0.0)
        i11 = math.sqrt(s) if oki else 1.0
        i21 = (pi21 - i20 * i10) / i11
        s = ((pi22 + 0.0) - i20 * i20) - i21 * i21
        oki = oki & (s > 0.0)
        i22 = math.sqrt(s) if oki else 1.0
        s = pj00 + 0.0  # the first level of chol3, as _chol3_first_level
        okj = s > 0.0
        j00 = math.sqrt(s) if okj else 1.0
        j10 = pj10 / j00
        j20 = pj20 / j00
        s = (pj11 + 0.0) - j10 * j10
        okj = okj & (s > 0.0)
        j11 = math.sqrt(s) if okj else 1.0
        j21 = (pj21 - j20 * j10) / j11
        s = ((pj22 + 0.0) - j20 * j20) - j21 * j21
        okj = okj & (s > 0.0)
        j22 = math.sqrt(s) if okj else 1.0
        # Y = Lj^-1 C^T (column b of C^T: row b of C), then X = Li^-1 Y^T
        y00 = c00 / j00
        y10 = (c01 - j10 * y00) / j11
        y20 = (c02 - j20 * y00 - j21 * y10) / j22
        y01 = c10 / j00
        y11 = (c11 - j10 * y01) / j11
        y21 = (c12 - j20 * y01 - j21 * y11) / j22
        y02 = c20 / j00
        y12 = (c21 - j10 * y02) / j11
        y22 = (c22 - j20 * y02 - j21 * y12) / j22
        x00 = y00 / i00
        x10 = (y01 - i10 * x00) / i11
        x20 = (y02 - i20 * x00 - i21 * x10) / i22
        x01 = y10 / i00
        x11 = (y11 - i10 * x01) / i11
        x21 = (y12 - i20 * x01 - i21 * x11) / i22
        x02 = y20 / i00
        x12 = (y21 - i10 * x02) / i11
        x22 = (y22 - i20 * x02 - i21 * x12) / i22
        frob = 0.0
        frob += x00 * x00
        frob += x01 * x01
        frob += x02 * x02
        frob += x10 * x10
        frob += x11 * x11
        frob += x12 * x12
        frob += x20 * x20
        frob += x21 * x21
        frob += x22 * x22
        m00 = x00 * x00 + x10 * x10 + x20 * x20
        m01 = x00 * x01 + x10 * x11 + x20 * x21
        m02 = x00 * x02 + x10 * x12 + x20 * x22
        m11 = x01 * x01 + x11 * x11 + x21 * x21
        m12 = x01 * x02 + x11 * x12 + x21 * x22
        m22 = x02 * x02 + x12 * x12 + x22 * x22
        below = _unit_minus_is_pd(m00, m01, m02, m11, m12, m22, CROSS_CAP * CROSS_CAP)
        small = math.sqrt(frob) <= CROSS_CAP
        certified = good & oki & okj & (small | below)
        ok[c] = 1.0 if certified else 0.0
        bf[c] = pi00
        bf[1 * LANE_STRIDE + c] = pi01
        bf[2 * LANE_STRIDE + c] = pi02
        bf[3 * LANE_STRIDE + c] = pi10
        bf[4 * LANE_STRIDE + c] = pi11
        bf[5 * LANE_STRIDE + c] = pi12
        bf[6 * LANE_STRIDE + c] = pi20
        bf[7 * LANE_STRIDE + c] = pi21
        bf[8 * LANE_STRIDE + c] = pi22
        bf[9 * LANE_STRIDE + c] = c00
        bf[10 * LANE_STRIDE + c] = c01
        bf[11 * LANE_STRIDE + c] = c02
        bf[12 * LANE_STRIDE + c] = c10
        bf[13 * LANE_STRIDE + c] = c11
        bf[14 * LANE_STRIDE + c] = c12
        bf[15 * LANE_STRIDE + c] = c20
        bf[16 * LANE_STRIDE + c] = c21
        bf[17 * LANE_STRIDE + c] = c22
        bf[18 * LANE_STRIDE + c] = pj00
        bf[19 * LANE_STRIDE + c] = pj01
        bf[20 * LANE_STRIDE + c] = pj02
        bf[21 * LANE_STRIDE + c] = pj10
        bf[22 * LANE_STRIDE + c] = pj11
        bf[23 * LANE_STRIDE + c] = pj12
        bf[24 * LANE_STRIDE + c] = pj20
        bf[25 * LANE_STRIDE + c] = pj21
        bf[26 * LANE_STRIDE + c] = pj22
        Jf[c] = 0.5 * (pi00 + pi00)
        Jf[1 * LANE_STRIDE + c] = 0.5 * (pi10 + pi01)
        Jf[2 * LANE_STRIDE + c] = 0.5 * (pi11 + pi11)
        Jf[3 * LANE_STRIDE + c] = 0.5 * (pi20 + pi02)
        Jf[4 * LANE_STRIDE + c] = 0.5 * (pi21 + pi12)
        Jf[5 * LANE_STRIDE + c] = 0.5 * (pi22 + pi22)
        Jf[6 * LANE_STRIDE + c] = c00
        Jf[7 * LANE_STRIDE + c] = c10
        Jf[8 * LANE_STRIDE + c] = c20
        Jf[9 * LANE_STRIDE + c] = 0.5 * (pj00 + pj00)
        Jf[10 * LANE_STRIDE + c] = c01
        Jf[11 * LANE_STRIDE + c] = c11
        Jf[12 * LANE_STRIDE + c] = c21
        Jf[13 * LANE_STRIDE + c] = 0.5 * (pj10 + pj01)
        Jf[14 * LANE_STRIDE + c] = 0.5 * (pj11 + pj11)
        Jf[15 * LANE_STRIDE + c] = c02
        Jf[16 * LANE_STRIDE + c] = c12
        Jf[17 * LANE_STRIDE + c] = c22
        Jf[18 * LANE_STRIDE + c] = 0.5 * (pj20 + pj02)
        Jf[19 * LANE_STRIDE + c] = 0.5 * (pj21 + pj12)
        Jf[20 * LANE_STRIDE + c] = 0.5 * (pj22 + pj22)


@jit_inline
def _unit_minus_is_pd(m00, m01, m02, m11, m12, m22, c):
    """:func:`~resloc.cl.kernels_joint_links.scaled_unit_minus_is_pd` on scalars, branch
    free."""
    n00 = c - m00
    n11 = c - m11
    n22 = c - m22
    n01 = -m01
    n02 = -m02
    n12 = -m12
    m2 = n00 * n11 - n01 * n01
    det = (
        n00 * (n11 * n22 - n12 * n12)
        - n01 * (n01 * n22 - n12 * n02)
        + n02 * (n01 * n12 - n11 * n02)
    )
    return (n00 > 0.0) & (m2 > 0.0) & (det > 0.0)


for _dispatcher in (chol6_lanes, correlated_points_lanes, factorized_cross_lanes, _cross_of_lanes):
    stamp_with_pieces(_dispatcher, _kernels_joint_links, _kernels_round_cached)
