"""The per-lane pieces of split CI's SIMD update (:mod:`resloc.cl.kernels_split_lanes`)
and of ``ci``'s (:mod:`resloc.cl.kernels_ci_lanes`): the scalar kernel's arithmetic on
tuples of scalars, without branches, so that a loop over lanes that inlines them
vectorizes. Each does its twin's operations in its twin's order
(the same values to the bit) and names it.

==============================  ==========================================================
function                        twin (same operations, same order)
==============================  ==========================================================
:func:`jacobians_of`            :func:`resloc.cl.kernels_gauge.range_bearing_jacobians_into`
:func:`pd6`, :func:`is_pd9`     ``kernels_split._is_pd6``, :func:`~resloc.cl.kernels_math.is_pd3`
:func:`clip_certified`          ``kernels_split._clip_independent``'s certificate
:func:`reduce_i9`               :func:`resloc.cl.kernels_ci_weight.reduce_i`
:func:`reduce_j9`               :func:`resloc.cl.kernels_ci_weight.reduce_j`
:func:`inflated_update_of`      :func:`resloc.cl.kernels_ci_update.inflated_update`
:func:`ci_update_of`            :func:`resloc.cl.kernels_ci_update.ci_update` after the weight
:func:`split_update_of`         ``kernels_split._split_ci_link`` after the weight
==============================  ==========================================================
"""

from __future__ import annotations

import math

from resloc.cl.kernels_math import jit_inline
from resloc.models.measurement import MIN_RANGE

__all__ = [
    "ci_update_of",
    "clip_certified",
    "inflated_update_of",
    "is_pd9",
    "jacobians_of",
    "minus9",
    "pd6",
    "reduce_i9",
    "reduce_j9",
    "split_update_of",
    "sym9",
]

_MIN_R2 = MIN_RANGE**2  # kernels_gauge's clamp of the squared range, computed alike


@jit_inline
def jacobians_of(xi0, xi1, xr0, xr1):
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
def pd6(m00, m01, m02, m11, m12, m22):
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
def clip_certified(P, J):
    """``(certified, sym(J))`` (9-tuples by row): :func:`resloc.cl.kernels_split.
    _clip_independent`'s certificate ``0 < J < P`` and the part it then keeps."""
    i00 = J[0]
    i11 = J[4]
    i22 = J[8]
    i01 = 0.5 * (J[1] + J[3])
    i02 = 0.5 * (J[2] + J[6])
    i12 = 0.5 * (J[5] + J[7])
    ok = pd6(i00, i01, i02, i11, i12, i22) & pd6(
        P[0] - i00,
        0.5 * (P[1] + P[3]) - i01,
        0.5 * (P[2] + P[6]) - i02,
        P[4] - i11,
        0.5 * (P[5] + P[7]) - i12,
        P[8] - i22,
    )
    return ok, (i00, i01, i02, i01, i11, i12, i02, i12, i22)


@jit_inline
def minus9(A, B):
    """``A - B`` of 9-tuples."""
    return (
        A[0] - B[0], A[1] - B[1], A[2] - B[2], A[3] - B[3], A[4] - B[4], A[5] - B[5],
        A[6] - B[6], A[7] - B[7], A[8] - B[8],
    )  # fmt: skip


@jit_inline
def reduce_i9(D, H):
    """:func:`resloc.cl.kernels_ci_weight.reduce_i` of a 9-tuple ``D`` and 6-tuple ``H``."""
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
def reduce_j9(D, H):
    """:func:`resloc.cl.kernels_ci_weight.reduce_j` of a 9-tuple ``D`` and 6-tuple ``H``,
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
def is_pd9(T):
    """:func:`~resloc.cl.kernels_math.is_pd3` of a 9-tuple by row, without branches."""
    m2 = T[0] * T[4] - T[1] * T[3]
    det = (
        T[0] * (T[4] * T[8] - T[5] * T[7])
        - T[1] * (T[3] * T[8] - T[5] * T[6])
        + T[2] * (T[3] * T[7] - T[4] * T[6])
    )
    return (T[0] > 0.0) & (m2 > 0.0) & (det > 0.0) & (abs(det) < math.inf)


@jit_inline
def inflated_update_of(Pi, Di, Dj, Hi, Hj, w, Sm, pxz, x, nu0, nu1, jitter0):
    """The inflated update of one lane with weight ``w``, as
    :func:`resloc.cl.kernels_ci_update.inflated_update` (EKF-free) with ``S``'s factor at the
    first jitter level (``jitter0``) only: ``A = sym(P_i + f_i D_i)``, ``S``'s factor,
    ``K``, ``x_i``, ``P_n = A - K S K^T``. ``P_i``, ``D_i``, ``D_j``: 9-tuples by row (the
    covariances for ``ci``, the dependent parts for split CI), ``H``: 6-tuples, ``Sm``:
    ``(S00, S01, S11)``, ``pxz``: ``P^xz`` by row, ``x``: ``x_i``. Returns ``(S factored,
    x_i's new estimate (heading not wrapped), A, P_n (9-tuples by row), K (6-tuple by
    row), P^xz + f_i D_i H_i^T (6-tuple by row))``; for ``w >= 1`` meaningless (the
    callers keep the prior)."""
    hdh, dh = reduce_i9(Di, Hi)
    hdj = reduce_j9(Dj, Hj)
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
    S00, S01, S11 = Sm
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
    x00 = pxz[0] + dh[0] * fi
    x01 = pxz[1] + dh[1] * fi
    x10 = pxz[2] + dh[2] * fi
    x11 = pxz[3] + dh[3] * fi
    x20 = pxz[4] + dh[4] * fi
    x21 = pxz[5] + dh[5] * fi
    y0 = x00 / l00
    k01 = ((x01 - l10 * y0) / l11) / l11
    k00 = (y0 - l10 * k01) / l00
    y0 = x10 / l00
    k11 = ((x11 - l10 * y0) / l11) / l11
    k10 = (y0 - l10 * k11) / l00
    y0 = x20 / l00
    k21 = ((x21 - l10 * y0) / l11) / l11
    k20 = (y0 - l10 * k21) / l00
    xn = (
        x[0] + (k00 * nu0 + k01 * nu1),
        x[1] + (k10 * nu0 + k11 * nu1),
        x[2] + (k20 * nu0 + k21 * nu1),
    )
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
    A = (a00, a01, a02, a10, a11, a12, a20, a21, a22)
    N = (n00, n01, n02, n10, n11, n12, n20, n21, n22)
    return ok_s, xn, A, N, (k00, k01, k10, k11, k20, k21), (x00, x01, x10, x11, x20, x21)


@jit_inline
def ci_update_of(Pi, Pj, Hi, Hj, w, Sm, pxz, x, nu0, nu1, jitter0):
    """One lane's ``ci`` update with weight ``w``, as
    :func:`resloc.cl.kernels_ci_update.ci_update` (EKF-free) then
    :func:`~resloc.cl.kernels_math.store_covariance`'s symmetrization and test:
    :func:`inflated_update_of` with ``D = P``; ``w >= 1``, the prior kept. Returns
    ``(certified, x_i's new estimate (heading not wrapped), sym(P_n) (9-tuple by row),
    sym(P_n) positive definite by is_pd3's test)``: certified where the prior is kept or
    ``S`` has its factor at the first jitter level."""
    ok_s, xn, _A, N, _K, _X = inflated_update_of(Pi, Pi, Pj, Hi, Hj, w, Sm, pxz, x, nu0, nu1,
                                                 jitter0)  # fmt: skip
    keep = w >= 1.0
    T = sym9(Pi) if keep else sym9(N)
    return keep | ok_s, xn, T, is_pd9(T)


@jit_inline
def sym9(M):
    """``0.5 (M + M^T)`` of a 9-tuple by row, entry by entry as ``store_covariance``."""
    return (
        0.5 * (M[0] + M[0]), 0.5 * (M[1] + M[3]), 0.5 * (M[2] + M[6]),
        0.5 * (M[3] + M[1]), 0.5 * (M[4] + M[4]), 0.5 * (M[5] + M[7]),
        0.5 * (M[6] + M[2]), 0.5 * (M[7] + M[5]), 0.5 * (M[8] + M[8]),
    )  # fmt: skip


@jit_inline
def split_update_of(ok, Pi, Ii, Di, Dj, Hi, Hj, w, Sm, pxz, x, nu0, nu1, R4, jitter0):
    """One lane's split CI update with weight ``w``, as
    :func:`resloc.cl.kernels_split._split_ci_link` (EKF-free): the inflated update
    (:func:`resloc.cl.kernels_ci_update.inflated_update`: ``A = sym(P_i + f_i D_i)``, ``S``'s
    factor, ``K``, ``x_i``, ``P_n = A - K S K^T``), ``H = (A^-1 P^xz)^T`` by ``A``'s factor,
    ``(I - K H) I_i (I - K H)^T + K R K^T`` and the posterior's clip; ``w >= 1``: the prior
    and its clipped part, clipped to it. Both factors at the first jitter level
    (``jitter0``) only. ``P_i``, ``I_i``, ``D_i``, ``D_j``: 9-tuples by row (``I_i`` the
    clipped part, ``ok``: both clips certified), ``H``: 6-tuples, ``Sm``: ``(S00, S01,
    S11)``, ``pxz``: ``P^xz`` by row, ``x``: ``x_i``, ``R4``: ``R`` by row. Returns
    ``(certified, x_i's new estimate (heading not wrapped), sym(P_n) (9-tuple), sym(P_n)
    positive definite by is_pd3's test, i's new independent part (00, 01, 02, 11, 12,
    22))``: certified where ``ok``, the factors and every clip's certificate pass."""
    r00, r01, r10, r11 = R4
    ok_s, xn, A, N, Kt, X = inflated_update_of(Pi, Di, Dj, Hi, Hj, w, Sm, pxz, x, nu0, nu1,
                                               jitter0)  # fmt: skip
    keep = w >= 1.0
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = A
    n00, n01, n02, n10, n11, n12, n20, n21, n22 = N
    k00, k01, k10, k11, k20, k21 = Kt
    x00, x01, x10, x11, x20, x21 = X
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
    ok_kept, kept = clip_certified(Pi, Mk)
    ok_new, new = clip_certified(Q, M)
    fresh = not keep
    good = ok & ((keep & ok_kept) | (fresh & ok_s & ok_a & ok_new))
    Pk = (
        0.5 * (Pi[0] + Pi[0]), 0.5 * (Pi[1] + Pi[3]), 0.5 * (Pi[2] + Pi[6]),
        0.5 * (Pi[3] + Pi[1]), 0.5 * (Pi[4] + Pi[4]), 0.5 * (Pi[5] + Pi[7]),
        0.5 * (Pi[6] + Pi[2]), 0.5 * (Pi[7] + Pi[5]), 0.5 * (Pi[8] + Pi[8]),
    )  # fmt: skip
    T = Pk if keep else Q  # store_covariance's sym(P_n)
    part = kept if keep else new
    return good, xn, T, is_pd9(T), (part[0], part[1], part[2], part[4], part[5], part[8])
