"""The compiled sigma-point prediction in SIMD lanes: chunks of robots, one robot a lane.

:func:`resloc.cl.kernels_predict._predict_robots` predicts one robot after the other with
scalar code. Robots are independent in the prediction, so :func:`predict_lanes` takes them
in chunks of ``CHUNK`` and runs every stage as a loop over the chunk's robots on arrays
of one component each (structure of arrays), which LLVM compiles to SIMD instructions; the
sines, cosines and the circular mean's ``atan2`` are the branch-free polynomials of
:mod:`resloc.cl.kernels_lanes`. Same operations as the scalar kernel otherwise (its twin;
equal to ~1e-15, tested to 1e-9 against the numpy path). A robot the lanes do not take (a
heading out of ``[-SINCOS_LANES_MAX, SINCOS_LANES_MAX]``, a point's heading offset or the
turn ``omega dt`` above ``pi/4``: a heading standard deviation above ~0.45 rad for the
CKF; a circular mean of points that cancel; non-finite values) makes
:func:`predict_lanes` return ``FALLBACK``, and the caller runs the scalar kernel
instead; a covariance that needs Cholesky jitter gets it from
:func:`~resloc.cl.kernels_math.chol3` in its lane.
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl import kernels_lanes as _kernels_lanes
from resloc.cl import kernels_math as _kernels_math
from resloc.cl.kernels_lanes import (
    CHUNK,
    FALLBACK,
    SINCOS_LANES_MAX,
    atan2_lanes,
    sincos_lanes,
    small_sincos_lanes,
    wrap_lanes,
)
from resloc.cl.kernels_links import NOT_PD, OK
from resloc.cl.kernels_math import chol3, jit_lanes, stamp_with_pieces

_jit = jit_lanes


__all__ = ["predict_lanes"]

_QUARTER_PI = math.pi / 4.0

# Rows of the chunk's input array (``lanes``), CHUNK apart
_X0, _X1, _X2, _V, _W, _M0, _M1 = 0, 1, 2, 3, 4, 5, 6
_P = 7  # 9 rows: P[a, c] at _P + 3 a + c
_OK = 16  # the covariance is finite (1.0)
_ROWS = 17


@_jit
def _load(x, P, u, odometry_var, b0, n, lanes):
    """The chunk's robots ``b0 .. b0 + n`` into lanes."""
    per_robot_noise = odometry_var.shape[0] > 1
    for c in range(n):
        b = b0 + c
        r = b if per_robot_noise else 0
        lanes[_X0, c] = x[b, 0]
        lanes[_X1, c] = x[b, 1]
        lanes[_X2, c] = x[b, 2]
        lanes[_V, c] = u[b, 0]
        lanes[_W, c] = u[b, 1]
        lanes[_M0, c] = odometry_var[r, 0]
        lanes[_M1, c] = odometry_var[r, 1]
        finite = True
        for a in range(3):
            for d in range(3):
                lanes[_P + 3 * a + d, c] = P[b, a, d]
                finite = finite and math.isfinite(P[b, a, d])
        lanes[_OK, c] = 1.0 if finite else 0.0


@_jit
def _factor(n, lanes, L, ok):
    """Cholesky factors without jitter (the first level of ``chol3``: same operations, same
    order) into ``L = (l00, l10, l20, l11, l21, l22)`` rows, and whether each succeeded."""
    lf = lanes.reshape(lanes.size)
    Lf = L.reshape(L.size)
    for c in range(n):
        a00 = lf[_P * CHUNK + c]
        a10 = lf[(_P + 3) * CHUNK + c]
        a20 = lf[(_P + 6) * CHUNK + c]
        l00 = math.sqrt(a00)
        l10 = a10 / l00
        l20 = a20 / l00
        s1 = lf[(_P + 4) * CHUNK + c] - l10 * l10
        l11 = math.sqrt(s1)
        l21 = (lf[(_P + 7) * CHUNK + c] - l20 * l10) / l11
        s2 = lf[(_P + 8) * CHUNK + c] - l20 * l20 - l21 * l21
        l22 = math.sqrt(s2)
        Lf[c] = l00
        Lf[CHUNK + c] = l10
        Lf[2 * CHUNK + c] = l20
        Lf[3 * CHUNK + c] = l11
        Lf[4 * CHUNK + c] = l21
        Lf[5 * CHUNK + c] = l22
        good = (lf[_OK * CHUNK + c] == 1.0) & (a00 > 0.0) & (s1 > 0.0) & (s2 > 0.0)
        ok[c] = 1.0 if good else 0.0


@_jit
def _factor_with_jitter(P, b0, n, L, ok, jitter, scratch_in, scratch_out):
    """The lanes whose factor needs jitter, by :func:`chol3`. False: one failed."""
    for c in range(n):
        if ok[c] == 1.0:
            continue
        for a in range(3):
            for d in range(3):
                scratch_in[a, d] = P[b0 + c, a, d]
        if not chol3(scratch_in, scratch_out, jitter):
            return False
        L[0, c] = scratch_out[0, 0]
        L[1, c] = scratch_out[1, 0]
        L[2, c] = scratch_out[2, 0]
        L[3, c] = scratch_out[1, 1]
        L[4, c] = scratch_out[2, 1]
        L[5, c] = scratch_out[2, 2]
    return True


@_jit
def _points(n, dt, floor_var, unit, mirror, Wm, lanes, L, Xf, sums, SC, Q, bad):
    """The process noise into ``Q`` (9 rows) and every point ``x + L xi_k`` through the
    unicycle into ``Xf`` (``3 k + a`` rows), with the weighted sums ``(mean0, mean1, sin,
    cos, heading)`` (then the heading's and the turn's sine and cosine) in ``sums``; ``SC``:
    the points' offsets' sines and cosines (a mirrored point reuses its twin's). Twin:
    ``odometry_process_noise`` and the points block of ``_predict_robots``."""
    lf = lanes.reshape(lanes.size)
    Lf = L.reshape(L.size)
    Xff = Xf.reshape(Xf.size)
    sf = sums.reshape(sums.size)
    Qf = Q.reshape(Q.size)
    fv0 = floor_var[0]
    fv1 = floor_var[1]
    fv2 = floor_var[2]
    for c in range(n):
        x2 = lf[_X2 * CHUNK + c]
        s2, c2 = sincos_lanes(x2)
        m0 = lf[_M0 * CHUNK + c]
        g0 = c2 * dt
        g1 = s2 * dt
        Qf[c] = g0 * m0 * g0 + fv0
        Qf[CHUNK + c] = g0 * m0 * g1
        Qf[2 * CHUNK + c] = 0.0
        Qf[3 * CHUNK + c] = g1 * m0 * g0
        Qf[4 * CHUNK + c] = g1 * m0 * g1 + fv1
        Qf[5 * CHUNK + c] = 0.0
        Qf[6 * CHUNK + c] = 0.0
        Qf[7 * CHUNK + c] = 0.0
        Qf[8 * CHUNK + c] = dt * lf[_M1 * CHUNK + c] * dt + fv2
        for a in range(5):
            sf[a * CHUNK + c] = 0.0
        sf[5 * CHUNK + c] = s2
        sf[6 * CHUNK + c] = c2
        turn = lf[_W * CHUNK + c] * dt
        sw, cw = small_sincos_lanes(turn)
        sf[7 * CHUNK + c] = sw
        sf[8 * CHUNK + c] = cw
        good = (abs(x2) <= SINCOS_LANES_MAX) & (abs(turn) <= _QUARTER_PI)
        bad[c] = 0.0 if good else 1.0
    for k in range(unit.shape[0]):
        u0 = unit[k, 0]
        u1 = unit[k, 1]
        u2 = unit[k, 2]
        w_k = Wm[k]
        q = mirror[k]  # the point this one mirrors (its offset's sine negated), or -1
        for c in range(n):
            l00 = Lf[c]
            l10 = Lf[CHUNK + c]
            l20 = Lf[2 * CHUNK + c]
            l11 = Lf[3 * CHUNK + c]
            l21 = Lf[4 * CHUNK + c]
            l22 = Lf[5 * CHUNK + c]
            o0 = l00 * u0 + 0.0 * u1 + 0.0 * u2
            o1 = l10 * u0 + l11 * u1 + 0.0 * u2
            o2 = l20 * u0 + l21 * u1 + l22 * u2
            x2 = lf[_X2 * CHUNK + c]
            v = lf[_V * CHUNK + c]
            w = lf[_W * CHUNK + c]
            s2 = sf[5 * CHUNK + c]
            c2 = sf[6 * CHUNK + c]
            th = x2 + o2
            if q >= 0:
                so = -SC[2 * q, c]
                co = SC[2 * q + 1, c]
            else:
                so, co = small_sincos_lanes(o2)
            SC[2 * k, c] = so
            SC[2 * k + 1, c] = co
            sn = s2 * co + c2 * so
            cs = c2 * co - s2 * so
            sw = sf[7 * CHUNK + c]
            cw = sf[8 * CHUNK + c]
            f0 = (lf[_X0 * CHUNK + c] + o0) + v * cs * dt
            f1 = (lf[_X1 * CHUNK + c] + o1) + v * sn * dt
            heading = th + w * dt
            f2 = wrap_lanes(heading)
            Xff[(3 * k) * CHUNK + c] = f0
            Xff[(3 * k + 1) * CHUNK + c] = f1
            Xff[(3 * k + 2) * CHUNK + c] = f2
            sf[c] += f0 * w_k
            sf[CHUNK + c] += f1 * w_k
            sf[2 * CHUNK + c] += (sn * cw + cs * sw) * w_k
            sf[3 * CHUNK + c] += (cs * cw - sn * sw) * w_k
            sf[4 * CHUNK + c] += f2 * w_k
            good = (abs(heading) < 3.0 * math.pi) & (abs(o2) <= _QUARTER_PI)
            bad[c] += 0.0 if good else 1.0


@_jit
def _covariance(n, circular, Wc, Xf, sums, Q, bad):
    """The heading mean (circular or arithmetic) into ``sums[4]`` and the points'
    covariance added to ``Q``. Twin: the mean and covariance blocks of ``_predict_robots``."""
    Xff = Xf.reshape(Xf.size)
    sf = sums.reshape(sums.size)
    Qf = Q.reshape(Q.size)
    for c in range(n):
        ssin = sf[2 * CHUNK + c]
        scos = sf[3 * CHUNK + c]
        arithmetic = sf[4 * CHUNK + c]
        if circular:
            sf[4 * CHUNK + c] = wrap_lanes(atan2_lanes(ssin, scos))
            bad[c] += 1.0 if (ssin == 0.0) & (scos == 0.0) else 0.0
        else:
            sf[4 * CHUNK + c] = wrap_lanes(arithmetic)
            bad[c] += 0.0 if abs(arithmetic) < 3.0 * math.pi else 1.0
    for k in range(Wc.shape[0]):
        wc = Wc[k]
        for c in range(n):
            d0 = Xff[(3 * k) * CHUNK + c] - sf[c]
            d1 = Xff[(3 * k + 1) * CHUNK + c] - sf[CHUNK + c]
            d2 = wrap_lanes(Xff[(3 * k + 2) * CHUNK + c] - sf[4 * CHUNK + c])
            Qf[c] += d0 * wc * d0
            Qf[CHUNK + c] += d0 * wc * d1
            Qf[2 * CHUNK + c] += d0 * wc * d2
            Qf[3 * CHUNK + c] += d1 * wc * d0
            Qf[4 * CHUNK + c] += d1 * wc * d1
            Qf[5 * CHUNK + c] += d1 * wc * d2
            Qf[6 * CHUNK + c] += d2 * wc * d0
            Qf[7 * CHUNK + c] += d2 * wc * d1
            Qf[8 * CHUNK + c] += d2 * wc * d2


@_jit
def _store(b0, n, sums, Q, x_out, P_out):
    """The chunk's means and symmetrized covariances into the outputs."""
    for c in range(n):
        b = b0 + c
        x_out[b, 0] = sums[0, c]
        x_out[b, 1] = sums[1, c]
        x_out[b, 2] = sums[4, c]
        for a in range(3):
            for d in range(3):
                P_out[b, a, d] = 0.5 * (Q[3 * a + d, c] + Q[3 * d + a, c])


@_jit
def predict_lanes(x, P, u, dt, odometry_var, floor_var, spec, jitter, x_out, P_out):
    """Every robot's sigma-point prediction, a chunk of robots at a time in lanes; writes
    ``x_out: (B, 3)``, ``P_out: (B, 3, 3)``. Arguments as
    :func:`resloc.cl.kernels_predict._predict_robots` (a sigma-point ``spec``). Returns the
    status: ``OK``, ``NOT_PD`` or ``FALLBACK`` (on both, the outputs are partial)."""
    unit, mirror, Wm, Wc, circular = spec[1], spec[2], spec[3], spec[4], spec[5]
    m = unit.shape[0]
    lanes = np.empty((_ROWS, CHUNK))
    L = np.empty((6, CHUNK))
    ok = np.empty(CHUNK)
    bad = np.empty(CHUNK)
    Xf = np.empty((3 * m, CHUNK))
    sums = np.empty((9, CHUNK))
    SC = np.empty((2 * m, CHUNK))
    Q = np.empty((9, CHUNK))
    scratch_in = np.empty((3, 3))
    scratch_out = np.zeros((3, 3))
    B = x.shape[0]
    for b0 in range(0, B, CHUNK):
        n = min(CHUNK, B - b0)
        _load(x, P, u, odometry_var, b0, n, lanes)
        _factor(n, lanes, L, ok)
        if not _factor_with_jitter(P, b0, n, L, ok, jitter, scratch_in, scratch_out):
            return NOT_PD
        _points(n, dt, floor_var, unit, mirror, Wm, lanes, L, Xf, sums, SC, Q, bad)
        _covariance(n, circular, Wc, Xf, sums, Q, bad)
        for c in range(n):
            if bad[c] != 0.0:
                return FALLBACK
        _store(b0, n, sums, Q, x_out, P_out)
    return OK


stamp_with_pieces(predict_lanes, _kernels_math, _kernels_lanes)
