"""The sigma points of one link, all points at once: the stage of the row-order link loop
(:func:`resloc.cl.kernels_links.correct_links`) that evaluates the transcendental functions.

A link's ``m`` sigma points (12 for the CKF) are independent of each other once their
offsets are drawn, so their range and bearing (eq. 3) is one loop over the points that LLVM
compiles to SIMD instructions: the arctangent, the sine and cosine of the points' heading
offsets and the angle wrap are the branch-free polynomials of
:mod:`resloc.cl.kernels_lanes` (within 2e-16 of libm), where the scalar loop called libm's
``atan2``, ``sin`` and ``cos`` point by point. A point outside the polynomials' range (a
point at the robot's own position, a heading offset beyond ``SINCOS_LANES_MAX``, a heading
beyond ``2 pi``, non-finite values) is evaluated again by libm, as the scalar loop did. The
weighted sums then run point by point in the scalar loop's order.

This module is compiled with ``error_model="numpy"`` (an IEEE division, no
``ZeroDivisionError`` branch, which the loop vectorizer needs), so its functions are called
from the link loop, not inlined into it.

======================  ======================  ==============================================
function                paper                   numpy twin
======================  ======================  ==============================================
:func:`point_moments`   eq. (3), sigma points   ``SigmaPointFilter.relative_moments``,
                                                :func:`resloc.cl.tracking.joint_moments`
======================  ======================  ==============================================
"""

from __future__ import annotations

import math

from resloc.cl.kernels_lanes import SINCOS_LANES_MAX, atan2_lanes, sincos_lanes, wrap_lanes
from resloc.cl.kernels_math import jit_lanes, wrap
from resloc.cl.kernels_trig import fast_atan2

_jit = jit_lanes


__all__ = ["POINT_ROWS", "point_moments"]

#: Rows of the points' scratch ``Z`` of :func:`point_moments`: range, bearing, the
#: bearing's sine and cosine, and whether libm must evaluate the point again.
POINT_ROWS = 5
_TWO_PI = 2.0 * math.pi


@_jit
def _points_range_bearing(off, xi0, xi1, xi2, xr0, xr1, sin_i, cos_i, Z):
    """Range, bearing (eq. 3) and the bearing's sine and cosine of every point into ``Z``
    (rows as :data:`POINT_ROWS`); ``off: (6, m)`` the points' offsets of ``[x_i; x_j]``,
    ``sin_i``, ``cos_i`` of robot i's heading ``xi2``. One loop without calls or branches
    over the points (SIMD); the points it cannot evaluate are marked in ``Z[4]``. Returns
    how many."""
    m = off.shape[1]
    for k in range(m):
        dx = (xr0 + off[3, k]) - (xi0 + off[0, k])
        dy = (xr1 + off[4, k]) - (xi1 + off[1, k])
        o2 = off[2, k]
        th = xi2 + o2
        # sin and cos of the bearing atan2(dy, dx) - th from those of th (angle addition)
        so, co = sincos_lanes(o2)
        sn = sin_i * co + cos_i * so
        cs = cos_i * co - sin_i * so
        r = math.sqrt(dx * dx + dy * dy)
        Z[0, k] = r
        Z[1, k] = wrap_lanes(atan2_lanes(dy, dx) - th)
        Z[2, k] = (dy * cs - dx * sn) / r
        Z[3, k] = (dx * cs + dy * sn) / r
        good = (r > 0.0) & (r < math.inf) & (abs(o2) <= SINCOS_LANES_MAX) & (abs(th) < _TWO_PI)
        Z[4, k] = 0.0 if good else 1.0
    bad = 0
    for k in range(m):
        bad += Z[4, k] != 0.0
    return bad


@_jit
def _points_by_libm(off, xi0, xi1, xi2, xr0, xr1, Z):
    """The points :func:`_points_range_bearing` marked, by libm (the scalar loop's
    operations: the bearing's sine and cosine from those of the heading, or of the bearing
    itself for a point at the robot's position)."""
    for k in range(off.shape[1]):
        if Z[4, k] == 0.0:
            continue
        dx = (xr0 + off[3, k]) - (xi0 + off[0, k])
        dy = (xr1 + off[4, k]) - (xi1 + off[1, k])
        th = xi2 + off[2, k]
        r = math.sqrt(dx * dx + dy * dy)
        bearing = wrap(math.atan2(dy, dx) - th)
        Z[0, k] = r
        Z[1, k] = bearing
        if r > 0.0:
            sn = math.sin(th)
            cs = math.cos(th)
            Z[2, k] = (dy * cs - dx * sn) / r
            Z[3, k] = (dx * cs + dy * sn) / r
        else:
            Z[2, k] = math.sin(bearing)
            Z[3, k] = math.cos(bearing)


@_jit
def point_moments(off, Wm, Wc, circular, xi0, xi1, xi2, xr0, xr1, sin_i, cos_i, R, Z, Pxz):
    """Moments of ``z_ij`` (eq. 3) from a link's sigma points: ``(zh0, zh1, S00, S01, S11)``
    with ``S = sum_k Wc_k (Z_k - z_hat)(Z_k - z_hat)^T + R``, and ``P^xz`` of robot i's half
    into ``Pxz: (3, 2)``.

    Parameters
    ----------
    off : ndarray, shape (6, m)
        The points' offsets of ``[x_i; x_j]`` (the filter's unit points times a Cholesky
        factor of the joint covariance).
    Wm, Wc : ndarray, shape (m,)
        Mean and covariance weights.
    circular : bool
        The bearing's mean is the circular mean (else the wrapped weighted sum).
    xi0, xi1, xi2 : float
        Robot i's estimate; ``sin_i``, ``cos_i``: the sine and cosine of ``xi2``.
    xr0, xr1 : float
        The position of j the moments use.
    R : ndarray, shape (2, 2)
    Z : ndarray, shape (POINT_ROWS, m)
        Scratch.

    Twin: the moments of ``SigmaPointFilter.relative_moments`` (independent joint) and of
    :func:`resloc.cl.tracking.joint_moments` (correlated joint).
    """
    m = Wm.shape[0]
    if _points_range_bearing(off, xi0, xi1, xi2, xr0, xr1, sin_i, cos_i, Z):
        _points_by_libm(off, xi0, xi1, xi2, xr0, xr1, Z)
    zr = 0.0
    ssin = 0.0
    scos = 0.0
    zb = 0.0
    for k in range(m):
        zr += Z[0, k] * Wm[k]
        if circular:
            ssin += Z[2, k] * Wm[k]
            scos += Z[3, k] * Wm[k]
        else:
            zb += Z[1, k] * Wm[k]
    zh0 = zr
    zh1 = wrap(fast_atan2(ssin, scos)) if circular else wrap(zb)
    mx0 = 0.0
    mx1 = 0.0
    mx2 = 0.0
    for k in range(m):
        mx0 += off[0, k] * Wm[k]
        mx1 += off[1, k] * Wm[k]
        mx2 += off[2, k] * Wm[k]
    # the points' deviations from the means, all points at once (rows 2-4 are free now)
    for k in range(m):
        Z[0, k] = Z[0, k] - zh0
        Z[1, k] = wrap_lanes(Z[1, k] - zh1)  # both bearings in [-pi, pi)
        Z[2, k] = off[0, k] - mx0
        Z[3, k] = off[1, k] - mx1
        Z[4, k] = off[2, k] - mx2
    s00 = 0.0
    s01 = 0.0
    s11 = 0.0
    p00 = 0.0
    p01 = 0.0
    p10 = 0.0
    p11 = 0.0
    p20 = 0.0
    p21 = 0.0
    for k in range(m):
        d0 = Z[0, k]
        d1 = Z[1, k]
        w = Wc[k]
        s00 += d0 * w * d0
        s01 += d0 * w * d1
        s11 += d1 * w * d1
        g0 = Z[2, k]
        g1 = Z[3, k]
        g2 = Z[4, k]
        p00 += g0 * w * d0
        p01 += g0 * w * d1
        p10 += g1 * w * d0
        p11 += g1 * w * d1
        p20 += g2 * w * d0
        p21 += g2 * w * d1
    Pxz[0, 0] = p00
    Pxz[0, 1] = p01
    Pxz[1, 0] = p10
    Pxz[1, 1] = p11
    Pxz[2, 0] = p20
    Pxz[2, 1] = p21
    S00 = s00 + R[0, 0]
    S01 = 0.5 * ((s01 + R[0, 1]) + (s01 + R[1, 0]))
    S11 = s11 + R[1, 1]
    return zh0, zh1, S00, S01, S11
