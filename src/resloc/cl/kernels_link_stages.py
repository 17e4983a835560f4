"""The stages of the link rounds (:func:`resloc.cl.kernels_rounds.correct_rounds`): each a
loop over lanes (one robot each) on arrays of one component each, written so that LLVM
compiles it to SIMD instructions (no calls, selects instead of branches, rows of an array
a compile-time stride ``CHUNK`` apart where a loop stores to several rows). Each names its
twin block of :func:`resloc.cl.kernels_links.correct_links`.
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl.kernels_lanes import CHUNK, SINCOS_LANES_MAX, atan2_lanes, sincos_lanes, wrap_lanes
from resloc.cl.kernels_links import (
    decide_link,
    event_threshold_of_link,
    gate_link,
    innovation_norm_of_link,
)
from resloc.cl.kernels_math import chol3, jit_inline, jit_lanes, repair3, wrap

_jit = jit_lanes


__all__ = [
    "UPDATE_ROWS",
    "apply_lanes",
    "chol_jitter_lanes",
    "chol_lanes",
    "decide_lanes",
    "gather_lanes",
    "kalman_lanes",
    "load_covariances",
    "load_lane",
    "load_robot_covariances",
    "moment_scratch",
    "moments_lanes",
    "norms_lanes",
    "point_axes",
    "points_lanes",
    "robot_lanes",
]


#: Rows of :func:`kalman_lanes`'s ``update``.
UPDATE_ROWS = 22


@_jit
def moment_scratch(C, m):
    """The lanes' scratch of one chunk of ``C`` links' moments (``m`` sigma points), as
    :func:`gather_lanes`, :func:`load_covariances`, :func:`chol_lanes`, :func:`points_lanes`
    and :func:`moments_lanes` take it: ``(lane_e, obs, src, xi, xr, zl, sin_cos, Li, Lj,
    cov, ok_i, ok_j, bad, Z0, Z1, sums, moments, pxz, mean)``; ``Li``, ``Lj`` zeroed (their
    upper triangles are never written)."""
    return (
        np.empty(C, np.int64),
        np.empty(C, np.int64),
        np.empty(C, np.int64),
        np.empty((3, C)),
        np.empty((2, C)),
        np.empty((2, C)),
        np.empty((2, C)),
        np.zeros((3, 3, C)),
        np.zeros((3, 3, C)),
        np.empty((7, C)),
        np.empty(C),
        np.empty(C),
        np.empty(C),
        np.empty((m, C)),
        np.empty((m, C)),
        np.empty((4, C)),
        np.empty((5, C)),
        np.empty((6, C)),
        np.empty((3, C)),
    )


@_jit
def point_axes(nz_idx, nz_val, nz_cnt):
    """Each point's one non-zero coordinate (``-1``: the centre) and its value."""
    m = nz_cnt.shape[0]
    axis = np.full(m, -1, np.int64)
    value = np.zeros(m)
    for k in range(m):
        if nz_cnt[k] == 1:
            axis[k] = nz_idx[k, 0]
            value[k] = nz_val[k, 0]
    return axis, value


@_jit
def chol_lanes(A, n, L, ok):
    """Lower Cholesky factors of the lanes' ``A = (a00, a10, a20, a11, a21, a22, finite)``
    (a symmetric 3 x 3 matrix per lane, and whether all its nine entries are finite) into
    ``L[:, :, c]`` for lanes ``c < n`` without jitter, and whether each succeeded (1.0)
    (the first level of :func:`~resloc.cl.kernels_math.chol3`: same operations, same
    order)."""
    for c in range(n):
        a00 = A[0, c]
        a10 = A[1, c]
        a20 = A[2, c]
        l00 = math.sqrt(a00)
        l10 = a10 / l00
        l20 = a20 / l00
        s1 = A[3, c] - l10 * l10
        l11 = math.sqrt(s1)
        l21 = (A[4, c] - l20 * l10) / l11
        s2 = A[5, c] - l20 * l20 - l21 * l21
        l22 = math.sqrt(s2)
        L[0, 0, c] = l00
        L[1, 0, c] = l10
        L[2, 0, c] = l20
        L[1, 1, c] = l11
        L[2, 1, c] = l21
        L[2, 2, c] = l22
        good = (A[6, c] == 1.0) & (a00 > 0.0) & (s1 > 0.0) & (s2 > 0.0)
        ok[c] = 1.0 if good else 0.0


@_jit
def load_covariances(P, rows, n, A):
    """The lower triangle of ``P[rows[c]]`` per lane, and whether all nine entries are
    finite (what :func:`chol_lanes` factors)."""
    for c in range(n):
        load_lane(P, rows[c], c, A)


@jit_inline
def load_lane(P, r, c, A):
    """Lane ``c`` of ``A``: the lower triangle of ``P[r]`` (rows 0-5) and whether all nine
    entries are finite (row 6: 1 or 0)."""
    A[0, c] = P[r, 0, 0]
    A[1, c] = P[r, 1, 0]
    A[2, c] = P[r, 2, 0]
    A[3, c] = P[r, 1, 1]
    A[4, c] = P[r, 2, 1]
    A[5, c] = P[r, 2, 2]
    finite = True
    for a in range(3):
        for b in range(3):
            finite = finite and math.isfinite(P[r, a, b])
    A[6, c] = 1.0 if finite else 0.0


@_jit
def chol_jitter_lanes(A, rows, n, L, ok, jitter, scratch_in, scratch_out):
    """The lanes whose factor needed jitter, by :func:`chol3` itself. False: one failed."""
    for c in range(n):
        if ok[c] == 1.0:
            continue
        r = rows[c]
        for a in range(3):
            for b in range(3):
                scratch_in[a, b] = A[r, a, b]
        if not chol3(scratch_in, scratch_out, jitter):
            return False
        for a in range(3):
            for b in range(a + 1):
                L[a, b, c] = scratch_out[a, b]
    return True


@_jit
def gather_lanes(x, li, nb, x_ref, z, lane_e, n, obs, src, xi, xr, zl, sin_cos, bad):
    """Robot ``i``'s running estimate, ``j``'s transmitted one, the measurement and the sine
    and cosine of ``i``'s heading, per lane (``bad``: 1.0 where the heading is out of
    range)."""
    for c in range(n):
        e = lane_e[c]
        i = li[e]
        s = nb[e]
        obs[c] = i
        src[c] = s
        xi[0, c] = x[i, 0]
        xi[1, c] = x[i, 1]
        xi[2, c] = x[i, 2]
        xr[0, c] = x_ref[s, 0]
        xr[1, c] = x_ref[s, 1]
        zl[0, c] = z[e, 0]
        zl[1, c] = z[e, 1]
    for c in range(n):
        h = xi[2, c]
        sn, cs = sincos_lanes(h)
        sin_cos[0, c] = sn
        sin_cos[1, c] = cs
        bad[c] = 0.0 if abs(h) <= SINCOS_LANES_MAX else 1.0


@_jit
def points_lanes(axis, value, Wm, n, xi, xr, sin_cos, Li, Lj, Z0, Z1, sums, bad):
    """Range and bearing of every sigma point (eq. 3) and their weighted sums
    ``sums = (range, sin, cos, bearing)`` per lane (``bad``: 1.0 added where a point needs
    the row-order loop's special cases). Twin: the points' block of ``correct_links`` (the
    bearing's sine and cosine by angle addition from the heading's and the offset's)."""
    for c in range(n):
        sums[0, c] = 0.0
        sums[1, c] = 0.0
        sums[2, c] = 0.0
        sums[3, c] = 0.0
    for k in range(axis.shape[0]):
        b = axis[k]
        w = Wm[k]
        if 0 <= b < 3:  # a point of robot i's half: offsets its position and heading
            u = value[k]
            for c in range(n):
                dx = xr[0, c] - (xi[0, c] + Li[0, b, c] * u)
                dy = xr[1, c] - (xi[1, c] + Li[1, b, c] * u)
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
                w_r = w / r  # one division for both sums
                sums[1, c] += (dy * cs - dx * sn) * w_r
                sums[2, c] += (dx * cs + dy * sn) * w_r
                sums[3, c] += bearing * w
                good = (r > 0.0) & (r < math.inf) & (abs(o2) <= SINCOS_LANES_MAX)
                bad[c] += 0.0 if good else 1.0
        else:  # a point of j's half (offsets j's position), or the centre (u = 0)
            bj = b - 3 if b >= 3 else 0
            u = value[k] if b >= 3 else 0.0
            for c in range(n):
                dx = (xr[0, c] + Lj[0, bj, c] * u) - xi[0, c]
                dy = (xr[1, c] + Lj[1, bj, c] * u) - xi[1, c]
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


@_jit
def moments_lanes(axis, value, Wm, Wc, circular, n, Li, Z0, Z1, sums, moments, pxz, mean, bad):
    """``z_hat`` and the innovation covariance without ``R`` of eq. (3), ``moments = (zh0,
    zh1, s00, s01, s11)``, and ``P^xz``, ``pxz = (00, 01, 10, 11, 20, 21)``, per lane
    (``mean``: scratch for the mean of the points' offsets of ``x_i``).
    Twin: the moments' block of ``correct_links``."""
    m = axis.shape[0]
    if circular:
        for c in range(n):
            ssin = sums[1, c]
            scos = sums[2, c]
            bad[c] += 1.0 if (ssin == 0.0) & (scos == 0.0) else 0.0
            moments[1, c] = wrap_lanes(atan2_lanes(ssin, scos))
    else:
        for c in range(n):
            moments[1, c] = wrap(sums[3, c])
    for c in range(n):
        moments[0, c] = sums[0, c]
        for a in range(2, 5):
            moments[a, c] = 0.0
        for a in range(6):
            pxz[a, c] = 0.0
        for a in range(3):
            mean[a, c] = 0.0
    for k in range(m):
        b = axis[k]
        if 0 <= b < 3:
            u = value[k]
            w = Wm[k]
            for a in range(3):
                for c in range(n):
                    mean[a, c] += (Li[a, b, c] * u) * w
    for k in range(m):
        # the point's offset of x_i: L_i's column b times u (zero for j's half, the centre)
        b = axis[k] if 0 <= axis[k] < 3 else 0
        u = value[k] if 0 <= axis[k] < 3 else 0.0
        w = Wc[k]
        for c in range(n):
            d0 = Z0[k, c] - moments[0, c]
            d1 = wrap_lanes(Z1[k, c] - moments[1, c])
            g0 = Li[0, b, c] * u - mean[0, c]
            g1 = Li[1, b, c] * u - mean[1, c]
            g2 = Li[2, b, c] * u - mean[2, c]
            moments[2, c] += d0 * w * d0
            moments[3, c] += d0 * w * d1
            moments[4, c] += d1 * w * d1
            pxz[0, c] += g0 * w * d0
            pxz[1, c] += g0 * w * d1
            pxz[2, c] += g1 * w * d0
            pxz[3, c] += g1 * w * d1
            pxz[4, c] += g2 * w * d0
            pxz[5, c] += g2 * w * d1


@_jit
def load_robot_covariances(P, rows, n, Pi):
    """All nine entries of ``P[rows[c]]`` per lane (the update reads the full matrix, as
    the row-order loop does)."""
    for c in range(n):
        r = rows[c]
        for a in range(3):
            for b in range(3):
                Pi[3 * a + b, c] = P[r, a, b]


@_jit
def kalman_lanes(n, zl, R, moments, pxz, Pi, update):
    """Per lane (``zl``: the measurements): the innovation (eq. 9), the Cholesky factor
    of ``S`` (its first level, no jitter), and the Kalman update the link would make if
    fused: the gain by the factor of ``S``, the change of ``x`` and ``P - K S K^T``
    symmetrized, and whether that is positive definite (Sylvester). ``update = (nu0, nu1,
    l00, l10, l11, dx0, dx1, dx2, P00, P01, P02, P11, P12, P22, pd, bad, K00, K01, K10,
    K11, K20, K21)`` (:data:`UPDATE_ROWS` rows); ``bad``: 1.0 where ``S`` needs jitter or
    the measured bearing is out of ``(-2 pi, 2 pi)``; the gain ``K`` for the stages that
    change the innovation or record the update (:mod:`resloc.cl.kernels_round_stages`).
    The arrays have CHUNK columns. Twin: the innovation, gain and Schur update blocks of
    ``correct_links`` (same operations, same order)."""
    # Flat views, rows CHUNK apart: with the row stride a compile-time constant, LLVM
    # proves the rows' stores independent and vectorizes the loop.
    zf = zl.reshape(zl.size)
    mf = moments.reshape(moments.size)
    pf = pxz.reshape(pxz.size)
    Pf = Pi.reshape(Pi.size)
    uf = update.reshape(update.size)
    r00 = R[0, 0]
    r01 = R[0, 1]
    r10 = R[1, 0]
    r11 = R[1, 1]
    for c in range(n):
        z0 = zf[c]
        z1 = zf[1 * CHUNK + c]
        s00 = mf[2 * CHUNK + c] + r00
        s01 = 0.5 * ((mf[3 * CHUNK + c] + r01) + (mf[3 * CHUNK + c] + r10))
        s11 = mf[4 * CHUNK + c] + r11
        nu0 = z0 - mf[c]
        nu1 = wrap_lanes(z1 - mf[1 * CHUNK + c])
        # chol2's first level (eps = 0)
        l00 = math.sqrt(s00)
        l10 = s01 / l00
        q = s11 - l10 * l10
        l11 = math.sqrt(q)
        finite = (abs(s00) < math.inf) & (abs(s01) < math.inf) & (abs(s11) < math.inf)
        good = finite & (s00 > 0.0) & (q > 0.0) & (abs(z1) < 2.0 * math.pi)
        # K = P^xz S^-1 row by row (solve2's operations)
        y0 = pf[c] / l00
        k01 = ((pf[1 * CHUNK + c] - l10 * y0) / l11) / l11
        k00 = (y0 - l10 * k01) / l00
        y0 = pf[2 * CHUNK + c] / l00
        k11 = ((pf[3 * CHUNK + c] - l10 * y0) / l11) / l11
        k10 = (y0 - l10 * k11) / l00
        y0 = pf[4 * CHUNK + c] / l00
        k21 = ((pf[5 * CHUNK + c] - l10 * y0) / l11) / l11
        k20 = (y0 - l10 * k21) / l00
        # P - K S K^T (schur_update), then symmetrized
        t00 = k00 * s00 + k01 * s01
        t01 = k00 * s01 + k01 * s11
        t10 = k10 * s00 + k11 * s01
        t11 = k10 * s01 + k11 * s11
        t20 = k20 * s00 + k21 * s01
        t21 = k20 * s01 + k21 * s11
        n00 = Pf[c] - (t00 * k00 + t01 * k01)
        n01 = Pf[1 * CHUNK + c] - (t00 * k10 + t01 * k11)
        n02 = Pf[2 * CHUNK + c] - (t00 * k20 + t01 * k21)
        n10 = Pf[3 * CHUNK + c] - (t10 * k00 + t11 * k01)
        n11 = Pf[4 * CHUNK + c] - (t10 * k10 + t11 * k11)
        n12 = Pf[5 * CHUNK + c] - (t10 * k20 + t11 * k21)
        n20 = Pf[6 * CHUNK + c] - (t20 * k00 + t21 * k01)
        n21 = Pf[7 * CHUNK + c] - (t20 * k10 + t21 * k11)
        n22 = Pf[8 * CHUNK + c] - (t20 * k20 + t21 * k21)
        p00 = 0.5 * (n00 + n00)
        p01 = 0.5 * (n01 + n10)
        p02 = 0.5 * (n02 + n20)
        p11 = 0.5 * (n11 + n11)
        p12 = 0.5 * (n12 + n21)
        p22 = 0.5 * (n22 + n22)
        # is_pd3 on the symmetrized matrix
        m2 = p00 * p11 - p01 * p01
        det = (
            p00 * (p11 * p22 - p12 * p12)
            - p01 * (p01 * p22 - p12 * p02)
            + p02 * (p01 * p12 - p11 * p02)
        )
        pd = (p00 > 0.0) & (m2 > 0.0) & (det > 0.0) & (abs(det) < math.inf)
        uf[c] = nu0
        uf[1 * CHUNK + c] = nu1
        uf[2 * CHUNK + c] = l00
        uf[3 * CHUNK + c] = l10
        uf[4 * CHUNK + c] = l11
        uf[5 * CHUNK + c] = k00 * nu0 + k01 * nu1
        uf[6 * CHUNK + c] = k10 * nu0 + k11 * nu1
        uf[7 * CHUNK + c] = k20 * nu0 + k21 * nu1
        uf[8 * CHUNK + c] = p00
        uf[9 * CHUNK + c] = p01
        uf[10 * CHUNK + c] = p02
        uf[11 * CHUNK + c] = p11
        uf[12 * CHUNK + c] = p12
        uf[13 * CHUNK + c] = p22
        uf[14 * CHUNK + c] = 1.0 if pd else 0.0
        uf[15 * CHUNK + c] = 0.0 if good else 1.0
        uf[16 * CHUNK + c] = k00
        uf[17 * CHUNK + c] = k01
        uf[18 * CHUNK + c] = k10
        uf[19 * CHUNK + c] = k11
        uf[20 * CHUNK + c] = k20
        uf[21 * CHUNK + c] = k21


@_jit
def norms_lanes(n, update, options, norms):
    """The innovation's size in the trigger's and the detector's norms (eq. 9) per lane:
    ``norms = (trigger, detector)``. A loop of its own: the Euclidean norm is libm's
    ``hypot`` (as the reference's ``np.hypot``), a call the other stages must not contain."""
    noise_std, det_norm, trig_norm = options[1], options[4], options[5]
    std0 = noise_std[0]
    std1 = noise_std[1]
    for c in range(n):
        nu0 = update[0, c]
        nu1 = update[1, c]
        l00 = update[2, c]
        l10 = update[3, c]
        l11 = update[4, c]
        n_trig = innovation_norm_of_link(trig_norm, nu0, nu1, std0, std1, l00, l10, l11)
        norms[0, c] = n_trig
        if det_norm == trig_norm:
            norms[1, c] = n_trig
        else:
            norms[1, c] = innovation_norm_of_link(det_norm, nu0, nu1, std0, std1, l00, l10, l11)


@_jit
def robot_lanes(obs, lane_e, n, channel_ok, last_norm, robots, options, norms, inputs):
    """What the decisions read per lane, gathered: ``inputs = (alpha, lambda2, gamma, size,
    zeta_s, risk_s, zeta_c, risk_c, rho, channel_ok)`` (``size``: the innovation size of
    the threshold: the last delivered one with ``last_sent``, else the trigger's norm)."""
    risk_s, risk_c, lambda2, rho, alpha, gamma, zeta_s, zeta_c = robots
    last_sent = options[7]
    for c in range(n):
        i = obs[c]
        e = lane_e[c]
        inputs[0, c] = alpha[i] if alpha.shape[0] > 1 else alpha[0]
        inputs[1, c] = lambda2[i]
        inputs[2, c] = gamma[i] if gamma.shape[0] > 1 else gamma[0]
        inputs[3, c] = last_norm[e] if last_sent else norms[0, c]
        inputs[4, c] = zeta_s[i] if zeta_s.shape[0] > 1 else zeta_s[0]
        inputs[5, c] = risk_s[i]
        inputs[6, c] = zeta_c[i] if zeta_c.shape[0] > 1 else zeta_c[0]
        inputs[7, c] = risk_c[i]
        inputs[8, c] = rho[i] if rho.shape[0] > 1 else rho[0]
        inputs[9, c] = 1.0 if channel_ok[e] else 0.0


@_jit
def decide_lanes(n, options, norms, inputs, decision):
    """Detector gate, event threshold (eq. 11), trigger (eq. 10) and channel (eq. 8) per
    lane: ``decision = (delta, detected, triggered, delivered)`` (flags as 0.0 / 1.0).
    Twin: the decision block of ``correct_links`` (same pieces)."""
    detector, trigger, risk_floor = options[2], options[3], options[6]
    nf = norms.reshape(norms.size)  # rows CHUNK apart (see kalman_lanes)
    inf = inputs.reshape(inputs.size)
    df = decision.reshape(decision.size)
    for c in range(n):
        delta = event_threshold_of_link(
            inf[c], inf[CHUNK + c], inf[2 * CHUNK + c], inf[3 * CHUNK + c],
            inf[4 * CHUNK + c], inf[5 * CHUNK + c], inf[6 * CHUNK + c], inf[7 * CHUNK + c],
            risk_floor,
        )  # fmt: skip
        detected = gate_link(nf[CHUNK + c], detector, inf[8 * CHUNK + c])
        triggered, delivered = decide_link(
            detected, nf[c], delta, trigger, inf[9 * CHUNK + c] == 1.0
        )
        df[c] = delta
        df[CHUNK + c] = 1.0 if detected else 0.0
        df[2 * CHUNK + c] = 1.0 if triggered else 0.0
        df[3 * CHUNK + c] = 1.0 if delivered else 0.0


@_jit
def apply_lanes(x, P, lane_e, n, obs, xi, update, norms, decision, out, T3, kalman):
    """The lanes' decisions into the outputs and, with ``kalman``, for a delivered
    measurement the update :func:`kalman_lanes` prepared (repaired where not positive
    definite; without, the fusion method's stage updates). Twin: the outputs and the update
    of ``correct_links``."""
    out_norm, out_threshold, flags = out
    for c in range(n):
        e = lane_e[c]
        detected = decision[1, c] == 1.0
        delivered = decision[3, c] == 1.0
        out_norm[e] = norms[0, c]
        out_threshold[e] = math.nan if detected else decision[0, c]
        flags[0, e] = detected
        flags[1, e] = decision[2, c] == 1.0
        flags[2, e] = delivered
        flags[3, e] = delivered
        if not (delivered and kalman):
            continue
        i = obs[c]
        x[i, 0] = xi[0, c] + update[5, c]
        x[i, 1] = xi[1, c] + update[6, c]
        x[i, 2] = wrap(xi[2, c] + update[7, c])
        T3[0, 0] = update[8, c]
        T3[0, 1] = T3[1, 0] = update[9, c]
        T3[0, 2] = T3[2, 0] = update[10, c]
        T3[1, 1] = update[11, c]
        T3[1, 2] = T3[2, 1] = update[12, c]
        T3[2, 2] = update[13, c]
        if update[14, c] != 1.0:
            repair3(T3)
            flags[4, e] = True
        for a in range(3):
            for b in range(3):
                P[i, a, b] = T3[a, b]
