"""The lane pieces of the ``tracked`` and ``factorized`` joints' rounds
(:mod:`resloc.cl.kernels_joint_rounds`): the joint's 6 x 6 Cholesky factors over lanes
(:func:`chol6_lanes`), the points that move both robots (:func:`correlated_points_lanes`)
and ``factorized``'s cross-covariance of one lane without a view of an array
(:func:`factorized_cross_lane`). Each names its twin.
"""

from __future__ import annotations

import math

from resloc.cl import kernels_joint_links as _kernels_joint_links
from resloc.cl.kernels_joint_links import CROSS_CAP
from resloc.cl.kernels_lanes import (
    CHUNK,
    SINCOS_LANES_MAX,
    atan2_lanes,
    sincos_lanes,
    wrap_lanes,
)
from resloc.cl.kernels_math import jit_inline, jit_lanes, stamp_with_pieces

_jit = jit_lanes

__all__ = ["chol6_lanes", "correlated_points_lanes", "factorized_cross_lane"]


@_jit
def chol6_lanes(J, n, L, ok):
    """Lower Cholesky factors of the lanes' symmetric 6 x 6 joints, ``J: (21, C)`` (the
    lower triangle row by row, entry ``(r, c)`` at row ``r (r + 1) / 2 + c``), into ``L``
    (same layout) without jitter, and whether each succeeded (1.0; all entries finite, every
    pivot positive): the first level of :func:`~resloc.cl.kernels_joint_links.chol6`, same
    operations, same order. The arrays have CHUNK columns (flat rows CHUNK apart, see
    :func:`~resloc.cl.kernels_link_stages.kalman_lanes`)."""
    Jf = J.reshape(J.size)
    Lf = L.reshape(L.size)
    for c in range(n):
        j00 = Jf[c]
        j10 = Jf[1 * CHUNK + c]
        j11 = Jf[2 * CHUNK + c]
        j20 = Jf[3 * CHUNK + c]
        j21 = Jf[4 * CHUNK + c]
        j22 = Jf[5 * CHUNK + c]
        j30 = Jf[6 * CHUNK + c]
        j31 = Jf[7 * CHUNK + c]
        j32 = Jf[8 * CHUNK + c]
        j33 = Jf[9 * CHUNK + c]
        j40 = Jf[10 * CHUNK + c]
        j41 = Jf[11 * CHUNK + c]
        j42 = Jf[12 * CHUNK + c]
        j43 = Jf[13 * CHUNK + c]
        j44 = Jf[14 * CHUNK + c]
        j50 = Jf[15 * CHUNK + c]
        j51 = Jf[16 * CHUNK + c]
        j52 = Jf[17 * CHUNK + c]
        j53 = Jf[18 * CHUNK + c]
        j54 = Jf[19 * CHUNK + c]
        j55 = Jf[20 * CHUNK + c]
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
        Lf[1 * CHUNK + c] = l10
        Lf[2 * CHUNK + c] = l11
        Lf[3 * CHUNK + c] = l20
        Lf[4 * CHUNK + c] = l21
        Lf[5 * CHUNK + c] = l22
        Lf[6 * CHUNK + c] = l30
        Lf[7 * CHUNK + c] = l31
        Lf[8 * CHUNK + c] = l32
        Lf[9 * CHUNK + c] = l33
        Lf[10 * CHUNK + c] = l40
        Lf[11 * CHUNK + c] = l41
        Lf[12 * CHUNK + c] = l42
        Lf[13 * CHUNK + c] = l43
        Lf[14 * CHUNK + c] = l44
        Lf[15 * CHUNK + c] = l50
        Lf[16 * CHUNK + c] = l51
        Lf[17 * CHUNK + c] = l52
        Lf[18 * CHUNK + c] = l53
        Lf[19 * CHUNK + c] = l54
        Lf[20 * CHUNK + c] = l55
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


@jit_inline
def _chol3_first_level(a00, a10, a20, a11, a21, a22):
    """The first level (no jitter) of :func:`~resloc.cl.kernels_math.chol3` on scalars:
    ``(ok, l00, l10, l20, l11, l21, l22)``, same operations, same order."""
    s = a00 + 0.0
    ok = s > 0.0
    l00 = math.sqrt(s) if ok else 1.0
    l10 = a10 / l00
    l20 = a20 / l00
    s = (a11 + 0.0) - l10 * l10
    ok = ok and s > 0.0
    l11 = math.sqrt(s) if ok else 1.0
    l21 = (a21 - l20 * l10) / l11
    s = ((a22 + 0.0) - l20 * l20) - l21 * l21
    ok = ok and s > 0.0
    l22 = math.sqrt(s) if ok else 1.0
    return ok, l00, l10, l20, l11, l21, l22


@jit_inline
def factorized_cross_lane(joint, e, i, P, P_ref, s):
    """:func:`~resloc.cl.kernels_joint_links.factorized_cross` of one lane (``P[i]``,
    ``P_ref[s]``) without a view of an array: the factors' product, and the certificate
    that it needs no shrinking (both covariances factored at the first level of ``chol3``,
    the correlation's Frobenius norm or Sylvester's criterion below the cap) on scalars,
    the blocks into ``work[0:3]`` as ``factorized_cross`` leaves them. False for any other
    case (jitter, a shrink, a non-finite entry): the caller runs ``factorized_cross``
    itself, from the start, in a loop of its own."""
    N = joint[1]
    j = joint[2][e]
    work = joint[11]
    sig = joint[7]
    sig_pred = joint[8]
    A = joint[5]
    li = i % N
    lj = j % N
    t00 = (
        A[i, 0, 0] * sig[i, lj, 0, 0]
        + A[i, 0, 1] * sig[i, lj, 1, 0]
        + (A[i, 0, 2] * sig[i, lj, 2, 0])
    )
    t01 = (
        A[i, 0, 0] * sig[i, lj, 0, 1]
        + A[i, 0, 1] * sig[i, lj, 1, 1]
        + (A[i, 0, 2] * sig[i, lj, 2, 1])
    )
    t02 = (
        A[i, 0, 0] * sig[i, lj, 0, 2]
        + A[i, 0, 1] * sig[i, lj, 1, 2]
        + (A[i, 0, 2] * sig[i, lj, 2, 2])
    )
    t10 = (
        A[i, 1, 0] * sig[i, lj, 0, 0]
        + A[i, 1, 1] * sig[i, lj, 1, 0]
        + (A[i, 1, 2] * sig[i, lj, 2, 0])
    )
    t11 = (
        A[i, 1, 0] * sig[i, lj, 0, 1]
        + A[i, 1, 1] * sig[i, lj, 1, 1]
        + (A[i, 1, 2] * sig[i, lj, 2, 1])
    )
    t12 = (
        A[i, 1, 0] * sig[i, lj, 0, 2]
        + A[i, 1, 1] * sig[i, lj, 1, 2]
        + (A[i, 1, 2] * sig[i, lj, 2, 2])
    )
    t20 = (
        A[i, 2, 0] * sig[i, lj, 0, 0]
        + A[i, 2, 1] * sig[i, lj, 1, 0]
        + (A[i, 2, 2] * sig[i, lj, 2, 0])
    )
    t21 = (
        A[i, 2, 0] * sig[i, lj, 0, 1]
        + A[i, 2, 1] * sig[i, lj, 1, 1]
        + (A[i, 2, 2] * sig[i, lj, 2, 1])
    )
    t22 = (
        A[i, 2, 0] * sig[i, lj, 0, 2]
        + A[i, 2, 1] * sig[i, lj, 1, 2]
        + (A[i, 2, 2] * sig[i, lj, 2, 2])
    )
    c00 = t00 * sig_pred[j, li, 0, 0] + t01 * sig_pred[j, li, 0, 1] + t02 * sig_pred[j, li, 0, 2]
    c01 = t00 * sig_pred[j, li, 1, 0] + t01 * sig_pred[j, li, 1, 1] + t02 * sig_pred[j, li, 1, 2]
    c02 = t00 * sig_pred[j, li, 2, 0] + t01 * sig_pred[j, li, 2, 1] + t02 * sig_pred[j, li, 2, 2]
    c10 = t10 * sig_pred[j, li, 0, 0] + t11 * sig_pred[j, li, 0, 1] + t12 * sig_pred[j, li, 0, 2]
    c11 = t10 * sig_pred[j, li, 1, 0] + t11 * sig_pred[j, li, 1, 1] + t12 * sig_pred[j, li, 1, 2]
    c12 = t10 * sig_pred[j, li, 2, 0] + t11 * sig_pred[j, li, 2, 1] + t12 * sig_pred[j, li, 2, 2]
    c20 = t20 * sig_pred[j, li, 0, 0] + t21 * sig_pred[j, li, 0, 1] + t22 * sig_pred[j, li, 0, 2]
    c21 = t20 * sig_pred[j, li, 1, 0] + t21 * sig_pred[j, li, 1, 1] + t22 * sig_pred[j, li, 1, 2]
    c22 = t20 * sig_pred[j, li, 2, 0] + t21 * sig_pred[j, li, 2, 1] + t22 * sig_pred[j, li, 2, 2]
    finite = True
    for a in range(3):
        for b in range(3):
            finite = finite and math.isfinite(P[i, a, b]) and math.isfinite(P_ref[s, a, b])
    oki, i00, i10, i20, i11, i21, i22 = _chol3_first_level(
        P[i, 0, 0], P[i, 1, 0], P[i, 2, 0], P[i, 1, 1], P[i, 2, 1], P[i, 2, 2]
    )
    okj, j00, j10, j20, j11, j21, j22 = _chol3_first_level(
        P_ref[s, 0, 0],
        P_ref[s, 1, 0],
        P_ref[s, 2, 0],
        P_ref[s, 1, 1],
        P_ref[s, 2, 1],
        P_ref[s, 2, 2],
    )
    certified = finite and oki and okj
    if certified:
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
        if not math.sqrt(frob) <= CROSS_CAP:  # X^T X below cap^2 (Sylvester), else shrink
            m00 = x00 * x00 + x10 * x10 + x20 * x20
            m01 = x00 * x01 + x10 * x11 + x20 * x21
            m02 = x00 * x02 + x10 * x12 + x20 * x22
            m11 = x01 * x01 + x11 * x11 + x21 * x21
            m12 = x01 * x02 + x11 * x12 + x21 * x22
            m22 = x02 * x02 + x12 * x12 + x22 * x22
            certified = _unit_minus_is_pd(m00, m01, m02, m11, m12, m22, CROSS_CAP * CROSS_CAP)
    if not certified:
        return False
    for a in range(3):
        for b in range(3):
            work[0, a, b] = P[i, a, b]
            work[2, a, b] = P_ref[s, a, b]
    work[1, 0, 0] = c00
    work[1, 0, 1] = c01
    work[1, 0, 2] = c02
    work[1, 1, 0] = c10
    work[1, 1, 1] = c11
    work[1, 1, 2] = c12
    work[1, 2, 0] = c20
    work[1, 2, 1] = c21
    work[1, 2, 2] = c22
    return True


@jit_inline
def _unit_minus_is_pd(m00, m01, m02, m11, m12, m22, c):
    """:func:`~resloc.cl.kernels_joint_links.scaled_unit_minus_is_pd` on scalars."""
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
    return n00 > 0.0 and m2 > 0.0 and det > 0.0


for _dispatcher in (chol6_lanes, correlated_points_lanes):
    stamp_with_pieces(_dispatcher, _kernels_joint_links)
