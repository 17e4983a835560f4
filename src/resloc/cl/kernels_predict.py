"""Compiled twin of the CL prediction (:func:`resloc.cl.step.predict`).

The numpy prediction makes a dozen passes over ``(B, m, 3)`` temporaries (the process
noise, the Cholesky factors, the points, the unicycle, the circular mean, the covariance);
this kernel makes one pass over the robots and keeps a robot's work in registers, so the
step allocates only its outputs. Per robot, fused:

============================  =========================  ==========================================
kernel block                  paper                      numpy twin
============================  =========================  ==========================================
``odometry_process_noise``    odometry noise             :func:`resloc.models.motion.process_noise`
``_predict_robots`` (points)  Algorithm 1, "Prediction"  :meth:`SigmaPointFilter.predict`
``_predict_robots`` (EKF)     eq. (2), linearized        :meth:`ExtendedFilter.predict`
============================  =========================  ==========================================

For sigma-point filters and at least :data:`LANES_MIN_ROBOTS` robots, :func:`fast_predict`
runs the same prediction a chunk of robots at a time in SIMD lanes
(:func:`resloc.cl.kernels_predict_lanes.predict_lanes`), robot by robot when a robot is
outside the lanes' range. Which filters it covers is :func:`predict_kernel_spec` (the
CKF and the UKF with any 3-D point rule, circular or arithmetic heading means, and the
EKF); the backend choice is the correction's (:func:`resloc.cl.backend.backend`). A
covariance that is not positive definite even with jitter (or NaN) makes the kernel give
up: the reference path then raises the library's :class:`~resloc.errors.NumericalError`.

Numerics: the sines and cosines of the points' headings after the move are obtained from
those before it by the angle-addition formulas (the move turns every point by the same
``omega dt``), and a point mirrored about the mean (``-xi_k``) reuses its twin's sine and
cosine of the offset; the offsets' and the turn's are Taylor polynomials
(:func:`~resloc.cl.kernels_trig.small_angle_sincos`): one libm ``sin``/``cos`` pair per robot
instead of 13 (CKF). The results equal
the reference to ~1e-15 (tested to 1e-9).
"""

from __future__ import annotations

import math
import weakref
from collections import Counter
from typing import NamedTuple

import numpy as np

from resloc.cl import kernels_math as _kernels_math
from resloc.cl import kernels_trig as _kernels_trig
from resloc.cl.backend import backend, per_filter
from resloc.cl.kernels_links import NOT_PD, OK
from resloc.cl.kernels_math import chol3, jit, stamp_with_pieces, wrap
from resloc.cl.kernels_predict_lanes import FALLBACK, predict_lanes
from resloc.cl.kernels_trig import fast_atan2, small_angle_sincos
from resloc.filters.ekf import ExtendedFilter
from resloc.filters.sigma_points import SigmaPointFilter
from resloc.linalg import JITTER_LEVELS

__all__ = [
    "LANES_MIN_ROBOTS",
    "PREDICT_RUNS",
    "PredictKernelSpec",
    "fast_predict",
    "noise_variances",
    "predict_kernel_spec",
]

_JITTER = np.asarray(JITTER_LEVELS, dtype=float)
#: Sigma-point predictions of at least this many robots run in SIMD lanes
#: (:mod:`resloc.cl.kernels_predict_lanes`).
LANES_MIN_ROBOTS = 64
#: How many predictions each loop ran (``lanes``, ``lanes_fallback``, ``robots``).
PREDICT_RUNS: Counter = Counter()


class PredictKernelSpec(NamedTuple):
    """A filter's prediction as the kernel sees it.

    Attributes
    ----------
    linearized : bool
        EKF (True) or sigma points (False).
    unit : ndarray, shape (m, 3)
        Unit points of the 3-D rule (``(1, 3)`` zeros for the EKF).
    mirror : ndarray of int, shape (m,)
        For a point whose unit is the negative of an earlier one's, that point; else -1.
    Wm, Wc : ndarray, shape (m,)
        Mean and covariance weights.
    circular : bool
        Circular mean of the headings.
    """

    linearized: bool
    unit: np.ndarray
    mirror: np.ndarray
    Wm: np.ndarray
    Wc: np.ndarray
    circular: bool


def _build_spec(filt) -> PredictKernelSpec | None:
    if type(filt) is ExtendedFilter:
        w = np.zeros(1)
        return PredictKernelSpec(True, np.zeros((1, 3)), np.full(1, -1, np.int64), w, w, True)
    if type(filt) is not SigmaPointFilter or filt.rule3.unit.shape[1] != 3:
        return None
    unit = np.ascontiguousarray(filt.rule3.unit, dtype=float)
    m = unit.shape[0]
    mirror = np.full(m, -1, np.int64)
    for k in range(m):
        for q in range(k):
            if np.any(unit[q] != 0.0) and np.array_equal(unit[k], -unit[q]):
                mirror[k] = q
                break
    return PredictKernelSpec(
        False,
        unit,
        mirror,
        np.ascontiguousarray(filt.rule3.Wm, dtype=float),
        np.ascontiguousarray(filt.rule3.Wc, dtype=float),
        bool(filt.circular),
    )


#: The kernel's description of a filter's prediction, or None when the kernel does not
#: reproduce it.
predict_kernel_spec = per_filter(_build_spec)


_last_variances: tuple = (None, None, None)


def noise_variances(params, dt: float) -> tuple[tuple, np.ndarray, np.ndarray]:
    """The shape of ``params.odometry_std``, its variances as 2-D rows and the floor's
    ``floor^2 dt`` as the kernel takes them, kept for the last ``params`` object (frozen)
    and ``dt`` (the shapes are checked by the caller)."""
    global _last_variances
    ref, key, variances = _last_variances
    if ref is not None and ref() is params and key == dt:
        return variances
    odometry = np.asarray(params.odometry_std, dtype=float)
    floor = np.asarray(params.process_floor_std, dtype=float)
    variances = (
        odometry.shape,
        np.ascontiguousarray(np.atleast_2d(odometry**2)),
        np.ascontiguousarray(floor**2 * dt),
    )
    try:
        _last_variances = (weakref.ref(params), dt, variances)
    except TypeError:  # not weakly referenceable: no cache
        _last_variances = (None, None, None)
    return variances


def fast_predict(filt, x, P, u, dt, params, buffers=None) -> tuple[np.ndarray, np.ndarray] | None:
    """The whole :func:`~resloc.cl.step.predict` in one compiled pass over the robots.

    Returns None (nothing computed) when the backend is numpy, the filter has no compiled
    twin, the shapes are not the documented ones, or a covariance is not positive definite
    even with jitter (the reference path then raises the explanatory error).

    Parameters (``buffers`` checked by the caller) and returns as
    :func:`resloc.cl.step.predict`.
    """
    if backend() != "numba":
        return None
    spec = predict_kernel_spec(filt)
    if spec is None:
        return None
    x = np.asarray(x)
    P = np.asarray(P)
    u = np.asarray(u)
    B = x.shape[0] if x.ndim == 2 else -1
    if x.shape != (B, 3) or P.shape != (B, 3, 3) or u.shape != (B, 2):
        return None
    odometry_shape, odometry_var, floor_var = noise_variances(params, dt)
    if odometry_shape not in ((2,), (B, 2)) or floor_var.shape != (3,):
        return None
    if buffers is None:
        x_out = np.empty((B, 3))
        P_out = np.empty((B, 3, 3))
    else:
        x_out, P_out = buffers
    args = (
        np.ascontiguousarray(x, dtype=float),
        np.ascontiguousarray(P, dtype=float),
        np.ascontiguousarray(u, dtype=float),
        float(dt),
        odometry_var,
        floor_var,
        spec,
        _JITTER,
        x_out,
        P_out,
    )
    # The one choice of the prediction's loop: lanes (kernels_predict_lanes) for sigma
    # points from LANES_MIN_ROBOTS robots on, else (or when they fall back) robot by robot.
    status = FALLBACK
    if not spec.linearized and B >= LANES_MIN_ROBOTS:
        status = predict_lanes(*args)
        PREDICT_RUNS["lanes" if status != FALLBACK else "lanes_fallback"] += 1
    if status == FALLBACK:
        PREDICT_RUNS["robots"] += 1
        status = _predict_robots(*args)
    if status != OK:
        return None
    return x_out, P_out


@jit
def odometry_process_noise(c, s, dt, m0, m1, floor_var, Q):
    """``Q = G M G^T + diag(floor^2 dt)`` at a heading with cosine ``c`` and sine ``s``
    into ``Q`` (3 x 3). Twin: :func:`resloc.models.motion.process_noise`."""
    g0 = c * dt
    g1 = s * dt
    Q[0, 0] = g0 * m0 * g0 + floor_var[0]
    Q[0, 1] = g0 * m0 * g1
    Q[1, 0] = g1 * m0 * g0
    Q[1, 1] = g1 * m0 * g1 + floor_var[1]
    Q[2, 2] = dt * m1 * dt + floor_var[2]
    Q[0, 2] = 0.0
    Q[1, 2] = 0.0
    Q[2, 0] = 0.0
    Q[2, 1] = 0.0


@jit
def _predict_robots(x, P, u, dt, odometry_var, floor_var, spec, jitter, x_out, P_out):
    """Every robot's prediction; writes ``x_out: (B, 3)``, ``P_out: (B, 3, 3)``.
    Returns the status (on NOT_PD the outputs are partial and must be discarded)."""
    linearized, unit, mirror, Wm, Wc, circular = spec
    m = unit.shape[0]
    per_robot_noise = odometry_var.shape[0] > 1
    L = np.zeros((3, 3))
    Pb = np.zeros((3, 3))
    Q = np.zeros((3, 3))
    F = np.zeros((3, 3))
    T = np.zeros((3, 3))
    Xf = np.zeros((m, 3))
    sin_off = np.zeros(m)
    cos_off = np.zeros(m)
    for b in range(x.shape[0]):
        x0 = x[b, 0]
        x1 = x[b, 1]
        x2 = x[b, 2]
        v = u[b, 0]
        w = u[b, 1]
        s2 = math.sin(x2)
        c2 = math.cos(x2)
        r = b if per_robot_noise else 0
        odometry_process_noise(c2, s2, dt, odometry_var[r, 0], odometry_var[r, 1], floor_var, Q)
        if linearized:
            # x = f(x, u), P = F P F^T + Q (twin: ExtendedFilter.predict)
            x_out[b, 0] = x0 + v * c2 * dt
            x_out[b, 1] = x1 + v * s2 * dt
            x_out[b, 2] = wrap(x2 + w * dt)
            for a in range(3):
                for c in range(3):
                    F[a, c] = 1.0 if a == c else 0.0
            F[0, 2] = -v * s2 * dt
            F[1, 2] = v * c2 * dt
            for a in range(3):
                for c in range(3):
                    t = 0.0
                    for k in range(3):
                        t += F[a, k] * P[b, k, c]
                    T[a, c] = t
            for a in range(3):
                for c in range(3):
                    t = 0.0
                    for k in range(3):
                        t += T[a, k] * F[c, k]
                    Q[a, c] += t
        else:
            # Points x + L xi_k through the unicycle, their weighted (circular) mean and
            # covariance (twin: SigmaPointFilter.predict).
            for a in range(3):  # a scratch copy: a view would update reference counts
                for c in range(3):
                    Pb[a, c] = P[b, a, c]
            if not chol3(Pb, L, jitter):
                return NOT_PD
            sw, cw = small_angle_sincos(w * dt)
            mean0 = 0.0
            mean1 = 0.0
            ssin = 0.0
            scos = 0.0
            mean2 = 0.0
            for k in range(m):
                o0 = L[0, 0] * unit[k, 0] + L[0, 1] * unit[k, 1] + L[0, 2] * unit[k, 2]
                o1 = L[1, 0] * unit[k, 0] + L[1, 1] * unit[k, 1] + L[1, 2] * unit[k, 2]
                o2 = L[2, 0] * unit[k, 0] + L[2, 1] * unit[k, 1] + L[2, 2] * unit[k, 2]
                th = x2 + o2
                # sin, cos of the point's heading th = x2 + o2 by angle addition
                if mirror[k] >= 0:
                    so = -sin_off[mirror[k]]
                    co = cos_off[mirror[k]]
                elif o2 == 0.0:
                    so = 0.0
                    co = 1.0
                else:
                    so, co = small_angle_sincos(o2)
                sin_off[k] = so
                cos_off[k] = co
                sn = s2 * co + c2 * so
                cs = c2 * co - s2 * so
                Xf[k, 0] = (x0 + o0) + v * cs * dt
                Xf[k, 1] = (x1 + o1) + v * sn * dt
                Xf[k, 2] = wrap(th + w * dt)
                mean0 += Xf[k, 0] * Wm[k]
                mean1 += Xf[k, 1] * Wm[k]
                if circular:
                    # the heading after the move: th + w dt
                    ssin += (sn * cw + cs * sw) * Wm[k]
                    scos += (cs * cw - sn * sw) * Wm[k]
                else:
                    mean2 += Xf[k, 2] * Wm[k]
            mean2 = wrap(fast_atan2(ssin, scos)) if circular else wrap(mean2)
            x_out[b, 0] = mean0
            x_out[b, 1] = mean1
            x_out[b, 2] = mean2
            for k in range(m):
                d0 = Xf[k, 0] - mean0
                d1 = Xf[k, 1] - mean1
                d2 = wrap(Xf[k, 2] - mean2)
                wc = Wc[k]
                Q[0, 0] += d0 * wc * d0
                Q[0, 1] += d0 * wc * d1
                Q[0, 2] += d0 * wc * d2
                Q[1, 0] += d1 * wc * d0
                Q[1, 1] += d1 * wc * d1
                Q[1, 2] += d1 * wc * d2
                Q[2, 0] += d2 * wc * d0
                Q[2, 1] += d2 * wc * d1
                Q[2, 2] += d2 * wc * d2
        for a in range(3):
            for c in range(3):
                P_out[b, a, c] = 0.5 * (Q[a, c] + Q[c, a])
    return OK


stamp_with_pieces(_predict_robots, _kernels_math, _kernels_trig)
