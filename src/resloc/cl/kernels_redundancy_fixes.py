"""The redundancy stage's inputs, compiled: every link's claim raised to its observer's
median and its position fix (twins of :mod:`resloc.cl.detection_redundancy_fixes`'s
``weight_capped_covariance``, ``capped_claims`` and ``position_fix``).

The verdict kernels (:mod:`resloc.cl.kernels_redundancy_verdicts`) judge the fixes this
module computes; the claims' cap (:mod:`resloc.cl.kernels_claims`) raises the claims by
the same factors.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`claim_scales`           the scale of :func:`~resloc.cl.detection_redundancy_fixes.
                               weight_capped_covariance` and ``capped_claims``
                               (``_group_median``)
:func:`trace_scales`           the same from the rows' traces (``_group_median``)
:func:`position_fix_of_link`   :func:`~resloc.cl.detection_redundancy_fixes.position_fix`
                               (:func:`fixes_of_rows`: in SIMD lanes, by blocks)
=============================  ==========================================================
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl.kernels_lanes import SINCOS_LANES_MAX, sincos_lanes
from resloc.cl.kernels_math import jit, jit_inline, jit_lanes

__all__ = [
    "FIX_BLOCK",
    "claim_scales",
    "fixes_of_rows",
    "position_fix_of_link",
    "scales_to_median",
    "trace_scales",
]


@jit
def claim_scales(li, P_nb, nb, scale, scratch):
    """Per row ``e``: the factor ``max(m / t_e, 1)`` (1 where ``t_e <= 0``) with ``t_e``
    the trace of the position block of ``P_nb[nb[e]]`` and ``m`` the median of those traces
    over the rows of the same observer ``li[e]``, into ``scale: (E,)``. Rows must be sorted
    by observer (False otherwise; ``scratch``: (E,)). Twin: the scale of
    :func:`~resloc.cl.detection_redundancy_fixes.weight_capped_covariance` and
    :func:`~resloc.cl.detection_redundancy_fixes.capped_claims` (``_group_median``)."""
    E = li.shape[0]
    for e in range(E):  # the traces, once (the rows' own, then their factors, in scale)
        scale[e] = P_nb[nb[e], 0, 0] + P_nb[nb[e], 1, 1]
    return trace_scales(li, scale, scratch)


@jit_inline
def scales_to_median(scale, start, stop, median):
    """``scale[start:stop]``, a group's traces, replaced by ``max(median / t, 1)`` (1 where
    ``t <= 0`` or NaN; a NaN ratio stays NaN, as ``np.maximum``): the factor that raises
    each claim of the group to the group's median."""
    for e in range(start, stop):
        t = scale[e]
        s = 1.0
        if t > 0.0:
            s = median / t
            if s < 1.0:  # np.maximum: a NaN stays NaN
                s = 1.0
        scale[e] = s


@jit_inline
def trace_scales(li, scale, scratch):
    """:func:`claim_scales` from the rows' traces, given in ``scale: (E,)`` and replaced by
    their factors (for callers that hold the claims per row: no index array)."""
    E = li.shape[0]
    start = 0
    while start < E:
        if start > 0 and li[start] < li[start - 1]:
            return False
        stop = start + 1
        while stop < E and li[stop] == li[start]:
            stop += 1
        count = stop - start
        for e in range(start, stop):  # insertion sort of the group's traces (a few rows)
            t = scale[e]
            k = e
            while k > start and scratch[k - 1] > t:
                scratch[k] = scratch[k - 1]
                k -= 1
            scratch[k] = t
        median = 0.5 * (scratch[start + (count - 1) // 2] + scratch[start + count // 2])
        scales_to_median(scale, start, stop, median)
        start = stop
    return True


@jit_inline
def position_fix_of_link(
    z0, c, s, xo0, xo1, var_heading, grow, xn0, xn1, p00, p01, p10, p11, r00, r01, r10, r11
):  # fmt: skip
    """Observer i's position as link ``(i, j)`` says, ``f = p_j - r u(theta_i + b)``, and
    its covariance ``C``, symmetrized, as the entries ``(a, b, c)`` of ``[[a, b], [b, c]]``
    from j's credited position covariance ``[[p00, p01], [p10, p11]]``, i's heading variance
    and the sensor noise ``R = [[r00, r01], [r10, r11]]``: ``(f0, f1, C_a, C_b, C_c)``.
    ``(c, s)``: the cosine and sine of ``theta_i + b`` (:func:`fixes_of_rows` computes them
    for every row at once). ``grow``: the range's mean correction ``exp((R_bb +
    var_heading) / 2)`` (one per observer: the caller computes it once for the observer's
    rows). Scalars only, no branch (:func:`_fixes_of_block` runs it over SIMD lanes). Twin:
    :func:`~resloc.cl.detection_redundancy_fixes.position_fix` (same operations, same order,
    but for ``np.hypot``, here the square root of the sum of squares, and ``np.cos``,
    ``np.sin``, the caller's polynomials: within a few ulps, no libm call; measured, the
    pass 16.2 -> 12.6 us a step of 260 links)."""
    r = z0
    r_mean = r * grow
    f0 = xn0 - r_mean * c
    f1 = xn1 - r_mean * s
    rel0 = xn0 - xo0
    rel1 = xn1 - xo1
    r_pred = math.sqrt(rel0 * rel0 + rel1 * rel1)  # (np.hypot's, within an ulp)
    known = r_pred > 0.0  # (selects, not a branch: the lanes' loop stays vectorized)
    c = rel0 / r_pred if known else c
    s = rel1 / r_pred if known else s
    r = r_pred if known else r
    ja0 = r * s
    ja1 = r * -c
    # J_z = [[-c, ja0], [-s, ja1]]; J_z R J_z^T as numpy's matmul of 2 x 2 matrices
    t00 = -c * r00 + ja0 * r10
    t01 = -c * r01 + ja0 * r11
    t10 = -s * r00 + ja1 * r10
    t11 = -s * r01 + ja1 * r11
    n00 = t00 * -c + t01 * ja0
    n01 = t00 * -s + t01 * ja1
    n10 = t10 * -c + t11 * ja0
    n11 = t10 * -s + t11 * ja1
    c00 = p00 + ja0 * ja0 * var_heading + n00
    c01 = p01 + ja0 * ja1 * var_heading + n01
    c10 = p10 + ja1 * ja0 * var_heading + n10
    c11 = p11 + ja1 * ja1 * var_heading + n11
    return f0, f1, 0.5 * (c00 + c00), 0.5 * (c01 + c10), 0.5 * (c11 + c11)


@jit_inline
def _information(a, b, c):
    """``[[a, b], [b, c]]^-1`` in closed form (twin:
    ``detection_redundancy_exclusion._information``)."""
    det = a * c - b * b
    return c / det, -b / det, a / det


#: Rows of :func:`fixes_of_rows`' blocks (:func:`_fixes_of_block`): a fixed width, so that
#: the rows of the flat blocks lie a compile-time constant apart and LLVM proves the rows'
#: stores independent and vectorizes the loop (with the rows ``E`` apart it did not: a step
#: of 260 rows' fixes 3.8 -> 0.9 us measured on their own).
FIX_BLOCK = 64
# the rows of a block's inputs: range, cos, sin of theta_i + b, i's position and heading
# variance, the range's correction, j's position, j's credited covariance, theta_i + b
_RANGE, _COS, _SIN, _XO0, _XO1, _VAR_H, _GROW = 0, 1, 2, 3, 4, 5, 6
_XN0, _XN1, _P00, _P01, _P10, _P11, _ANGLE = 7, 8, 9, 10, 11, 12, 13
_FIX_INPUTS = 14
#: the rows of its results: the fix, its covariance's entries, the information's entries
#: and the information times the fix (:func:`fixes_of_rows`' ``fix``, ``cov``, ``info``)
_FIX_OUTPUTS = 10


@jit_lanes
def _fixes_of_block(n, inputs, out, r00, r01, r10, r11):
    """Rows ``0 .. n - 1`` of a block: the sine and cosine of ``theta_i + b`` (by the
    branch-free polynomials in SIMD lanes; by libm out of their range), then each row's
    fix, its covariance (:func:`position_fix_of_link`) and its information
    (:func:`_information`), in a loop over rows that compiles to SIMD. ``inputs:
    (_FIX_INPUTS, FIX_BLOCK)``, ``out: (_FIX_OUTPUTS, FIX_BLOCK)``; ``R = [[r00, r01],
    [r10, r11]]``."""
    a = inputs.reshape(inputs.size)
    b = out.reshape(out.size)
    B = FIX_BLOCK
    for c in range(n):
        sn, cs = sincos_lanes(a[_ANGLE * B + c])
        a[_COS * B + c] = cs
        a[_SIN * B + c] = sn
    for c in range(n):  # (the polynomials' range; nan)
        angle = a[_ANGLE * B + c]
        if not abs(angle) <= SINCOS_LANES_MAX:
            a[_COS * B + c] = math.cos(angle)
            a[_SIN * B + c] = math.sin(angle)
    for c in range(n):
        f0, f1, ca, cb, cc = position_fix_of_link(
            a[_RANGE * B + c], a[_COS * B + c], a[_SIN * B + c], a[_XO0 * B + c],
            a[_XO1 * B + c], a[_VAR_H * B + c], a[_GROW * B + c], a[_XN0 * B + c],
            a[_XN1 * B + c], a[_P00 * B + c], a[_P01 * B + c], a[_P10 * B + c],
            a[_P11 * B + c], r00, r01, r10, r11,
        )  # fmt: skip
        Ya, Yb, Yc = _information(ca, cb, cc)  # once per row, not per exclusion round
        b[c] = f0
        b[B + c] = f1
        b[2 * B + c] = ca
        b[3 * B + c] = cb
        b[4 * B + c] = cc
        b[5 * B + c] = Ya
        b[6 * B + c] = Yb
        b[7 * B + c] = Yc
        b[8 * B + c] = Ya * f0 + Yb * f1
        b[9 * B + c] = Yb * f0 + Yc * f1


@jit_inline
def fixes_of_rows(li, z, x, P, x_nb, P_nb, nb, scale, R, fix, cov, info):
    """Every row's position fix, its covariance and its information at the predicted
    estimates ``x: (B, 3)``, ``P: (B, 3, 3)``: row ``e`` reads ``z[e]``, observer ``li[e]``
    and j's claimed estimate ``x_nb[nb[e]]``, ``P_nb[nb[e]]`` raised by the factor
    ``scale[e]`` (:func:`claim_scales`'); rows sorted by observer. Into ``fix: (2, E)``,
    ``cov: (3, E)`` (entries ``a, b, c``) and ``info: (5, E)`` (the information's entries,
    then the information times the fix), by component (``exclude_group``'s arrays). By
    blocks of :data:`FIX_BLOCK` rows: each block's inputs gathered, its fixes in SIMD lanes
    (:func:`_fixes_of_block`), its results copied out by component."""
    E = li.shape[0]
    B = FIX_BLOCK
    block = np.empty((_FIX_INPUTS + _FIX_OUTPUTS, B))
    inputs = block[:_FIX_INPUTS]
    out = block[_FIX_INPUTS:]
    grow = 1.0
    for start in range(0, E, B):
        n = min(B, E - start)
        for c in range(n):
            e = start + c
            i = li[e]
            m = nb[e]
            f = scale[e]
            if e == 0 or i != li[e - 1]:  # the observer's range correction, once
                grow = math.exp(0.5 * (R[1, 1] + P[i, 2, 2]))
            inputs[_RANGE, c] = z[e, 0]
            inputs[_XO0, c] = x[i, 0]
            inputs[_XO1, c] = x[i, 1]
            inputs[_VAR_H, c] = P[i, 2, 2]
            inputs[_GROW, c] = grow
            inputs[_XN0, c] = x_nb[m, 0]
            inputs[_XN1, c] = x_nb[m, 1]
            inputs[_P00, c] = P_nb[m, 0, 0] * f
            inputs[_P01, c] = P_nb[m, 0, 1] * f
            inputs[_P10, c] = P_nb[m, 1, 0] * f
            inputs[_P11, c] = P_nb[m, 1, 1] * f
            inputs[_ANGLE, c] = x[i, 2] + z[e, 1]
        _fixes_of_block(n, inputs, out, R[0, 0], R[0, 1], R[1, 0], R[1, 1])
        for c in range(n):
            e = start + c
            fix[0, e] = out[0, c]
            fix[1, e] = out[1, c]
            cov[0, e] = out[2, c]
            cov[1, e] = out[3, c]
            cov[2, e] = out[4, c]
            for k in range(5):
                info[k, e] = out[5 + k, c]
