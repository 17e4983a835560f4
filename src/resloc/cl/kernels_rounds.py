"""The compiled CL link loop in rounds: many robots' links at once, in SIMD lanes.

:func:`resloc.cl.kernels_links.correct_links` walks the links in row order, one link after
the other: a link's sigma points depend on the robot's estimate as its previous link left
it, so the transcendental functions of a link (13 ``atan2``, 12 ``sin``/``cos`` for the
CKF) are scalar libm calls, most of a link's time. But robots are independent within a
step: only the order of a robot's own links matters. :func:`correct_rounds` therefore
takes the robots in chunks of :data:`CHUNK` and, within a chunk, processes round ``r``
(every robot's ``r``-th link) before round ``r + 1``. Within a round the robots are
independent, so every stage is a loop over *lanes* (one robot each) on arrays of one
component each (structure of arrays), which LLVM compiles to SIMD instructions; the
transcendentals inside are branch-free polynomials (:mod:`resloc.cl.kernels_lanes`).
A robot's links are fused in the same order as by the row-order loop, so the results are
the same up to floating-point rounding (tested to 1e-9), and the working arrays are the
chunk's only (a few tens of kilobytes, whatever the number of robots).

Stages of one round (each a named function, twin in ``correct_links``):

=======================  ===================================  ===========================
function                 paper                                block of ``correct_links``
=======================  ===================================  ===========================
``_gather_lanes``        Algorithm 1 (points' factors)        ``chol3`` of ``P_i``, ``P_j``
``_points_lanes``        eq. (3), sigma points                the points' range, bearing
``_moments_lanes``       eq. (3), moments                     ``zh``, ``S``, ``P^xz``
``_update_lanes``        eqs. (8)-(11), Algorithm 1 (gain)    detector to Schur update
=======================  ===================================  ===========================

Coverage (:func:`rounds_cover`): sigma-point filters whose 6-D points have at most one
non-zero entry (the CKF and the UKF), the Kalman update (``naive``), the detector gate and
the event trigger with any norms and either threshold innovation, transmitted neighbour
estimates. The stateful options (CUSUM stages, robot defence, gauge bookkeeping, the
stealthy attacker, cached estimates, covariance intersection) and the EKF run in the
row-order loop. A lane that needs a special case of the row-order loop (Cholesky jitter
is handled here; a point at the robot's own position, a heading offset above ``pi/4``,
non-finite values are not) makes :func:`correct_rounds` return :data:`FALLBACK` and
:func:`run_link_loop` runs the row-order loop from the start instead.

:func:`run_link_loop` is the one place that chooses: the rounds for at least
:data:`ROUNDS_MIN_LINKS` links of a covered configuration, else the row-order loop.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from resloc.cl import kernels_lanes as _kernels_lanes
from resloc.cl import kernels_links as _kernels_links
from resloc.cl import kernels_math as _kernels_math
from resloc.cl import kernels_trig as _kernels_trig
from resloc.cl.backend import HAVE_NUMBA
from resloc.cl.kernels_fusion import CI
from resloc.cl.kernels_lanes import (
    SINCOS_LANES_MAX,
    atan2_lanes,
    sincos_lanes,
    wrap_lanes,
)
from resloc.cl.kernels_links import (
    NOT_PD,
    OK,
    correct_links,
    decide_link,
    event_threshold_of_link,
    gate_link,
    innovation_norm_of_link,
    schur_update,
)
from resloc.cl.kernels_math import chol2, chol3, is_pd3, repair3, solve2, stamp_with_pieces, wrap

if HAVE_NUMBA:  # the optional extra ``fast``
    import numba

    # error_model="numpy": a float division is IEEE (no ZeroDivisionError branch), which
    # the loop vectorizer needs.
    _jit = numba.njit(cache=True, nogil=True, error_model="numpy")
else:  # pragma: no cover - exercised only where numba is absent

    def _jit(func):
        return func


__all__ = [
    "CHUNK",
    "FALLBACK",
    "LOOP_RUNS",
    "ROUNDS_MIN_LINKS",
    "correct_rounds",
    "rounds_cover",
    "run_link_loop",
]

#: Status of :func:`correct_rounds`: a lane needs the row-order loop's special cases; the
#: outputs are partial and must be discarded.
FALLBACK = 2
#: Robots per chunk (lanes of a round): the chunk's working arrays stay in the L1/L2 cache.
CHUNK = 256
#: The rounds run from this many links on (below, the row-order loop: measured equal or
#: faster there, and the chunks' set-up is not amortized).
ROUNDS_MIN_LINKS = 64
#: How many corrections each loop ran (``rounds``, ``rounds_fallback``: the rounds gave
#: way to the row-order loop, ``row_order``), for tests and benchmarks.
LOOP_RUNS: Counter = Counter()

def rounds_cover(filt, options, fusion, detection, defence, gauge, tamper) -> bool:
    """Whether :func:`correct_rounds` implements this configuration (arguments as those of
    :func:`~resloc.cl.kernels_links.correct_links`)."""
    linearized, nz_idx, nz_val, nz_cnt = filt[:4]
    return not (
        linearized
        or np.any(nz_cnt > 1)
        or fusion[0] == CI
        or gauge[0]
        or tamper[0]
        or detection[0]  # link CUSUM
        or detection[6]  # mean-shift CUSUM
        or defence[0]  # robot CUSUM
        or defence[5]  # recovery
        or options[9]  # cached neighbour estimates
    )


def run_link_loop(
    x, P, x_out, P_out, links, robots, filt, options, fusion, detection, defence, gauge, tamper,
    out,
):  # fmt: skip
    """Every link of one step into ``x_out``, ``P_out`` (copies of ``x``, ``P`` on entry):
    by rounds (:func:`correct_rounds`) where they cover the configuration and there are at
    least :data:`ROUNDS_MIN_LINKS` links, else (or when the rounds fall back) in row order
    (:func:`~resloc.cl.kernels_links.correct_links`). Returns the loop's status."""
    args = (links, robots, filt, options, fusion, detection, defence, gauge, tamper, out)
    if len(links[0]) >= ROUNDS_MIN_LINKS and rounds_cover(
        filt, options, fusion, detection, defence, gauge, tamper
    ):
        status = correct_rounds(x_out, P_out, *args)
        if status != FALLBACK:
            LOOP_RUNS["rounds"] += 1
            return status
        LOOP_RUNS["rounds_fallback"] += 1
        x_out[...] = x
        P_out[...] = P
        out.flags[...] = False
    LOOP_RUNS["row_order"] += 1
    return correct_links(x_out, P_out, *args)


@_jit
def _point_axes(nz_idx, nz_val, nz_cnt):
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
def _chol_lanes(A, n, L, ok):
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
def _load_covariances(P, rows, n, A):
    """The lower triangle of ``P[rows[c]]`` per lane, and whether all nine entries are
    finite (what :func:`_chol_lanes` factors)."""
    for c in range(n):
        r = rows[c]
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
def _chol_jitter_lanes(A, rows, n, L, ok, jitter, scratch_in, scratch_out):
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
def _gather_lanes(x, li, nb, x_ref, lane_e, n, obs, src, xi, xr, sin_cos, bad):
    """Robot ``i``'s running estimate, ``j``'s transmitted one and the sine and cosine of
    ``i``'s heading, per lane (``bad``: 1.0 where the heading is out of range)."""
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
    for c in range(n):
        h = xi[2, c]
        sn, cs = sincos_lanes(h)
        sin_cos[0, c] = sn
        sin_cos[1, c] = cs
        bad[c] = 0.0 if abs(h) <= SINCOS_LANES_MAX else 1.0


@_jit
def _points_lanes(axis, value, Wm, n, xi, xr, sin_cos, Li, Lj, Z0, Z1, sums, bad):
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
                sums[1, c] += ((dy * cs - dx * sn) / r) * w
                sums[2, c] += ((dx * cs + dy * sn) / r) * w
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
                sums[1, c] += ((dy * cs - dx * sn) / r) * w
                sums[2, c] += ((dx * cs + dy * sn) / r) * w
                sums[3, c] += bearing * w
                good = (r > 0.0) & (r < math.inf)
                bad[c] += 0.0 if good else 1.0


@_jit
def _moments_lanes(axis, value, Wm, Wc, circular, n, Li, Z0, Z1, sums, moments, pxz, mean, bad):
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
def _update_lanes(
    x, P, lane_e, n, obs, moments, pxz, z, channel_ok, last_norm, robots, options, out, K, Pn, T3
):  # fmt: skip
    """Innovation (eq. 9), detector gate, event threshold (eq. 11), trigger (eq. 10),
    channel (eq. 8), and for a delivered measurement the Kalman update of ``x``, ``P`` (the
    gain by the Cholesky factor of ``S``, then ``P - K S K^T`` symmetrized, repaired if not
    positive definite), per lane in turn. Returns the status.
    Twin: the decision and update blocks of ``correct_links`` (same pieces)."""
    risk_s, risk_c, lambda2, rho, alpha, gamma, zeta_s, zeta_c = robots
    R, noise_std, detector, trigger, det_norm, trig_norm, risk_floor, last_sent = options[:8]
    jitter = options[8]
    out_norm, out_threshold, flags = out
    std0 = noise_std[0]
    std1 = noise_std[1]
    for c in range(n):
        e = lane_e[c]
        i = obs[c]
        S00 = moments[2, c] + R[0, 0]
        S01 = 0.5 * ((moments[3, c] + R[0, 1]) + (moments[3, c] + R[1, 0]))
        S11 = moments[4, c] + R[1, 1]
        nu0 = z[e, 0] - moments[0, c]
        nu1 = wrap(z[e, 1] - moments[1, c])
        l00, l10, l11 = chol2(S00, S01, S11, jitter)
        if l00 == 0.0:
            return NOT_PD
        n_trig = innovation_norm_of_link(trig_norm, nu0, nu1, std0, std1, l00, l10, l11)
        if det_norm == trig_norm:
            n_det = n_trig
        else:
            n_det = innovation_norm_of_link(det_norm, nu0, nu1, std0, std1, l00, l10, l11)
        a_i = alpha[i] if alpha.shape[0] > 1 else alpha[0]
        g_i = gamma[i] if gamma.shape[0] > 1 else gamma[0]
        zs_i = zeta_s[i] if zeta_s.shape[0] > 1 else zeta_s[0]
        zc_i = zeta_c[i] if zeta_c.shape[0] > 1 else zeta_c[0]
        rho_i = rho[i] if rho.shape[0] > 1 else rho[0]
        delta = event_threshold_of_link(
            a_i, lambda2[i], g_i, last_norm[e] if last_sent else n_trig,
            zs_i, risk_s[i], zc_i, risk_c[i], risk_floor,
        )  # fmt: skip
        detected = gate_link(n_det, detector, rho_i)
        triggered, delivered = decide_link(detected, n_trig, delta, trigger, channel_ok[e])
        out_norm[e] = n_trig
        out_threshold[e] = math.nan if detected else delta
        flags[0, e] = detected
        flags[1, e] = triggered
        flags[2, e] = delivered
        flags[3, e] = delivered
        if not delivered:
            continue
        for a in range(3):
            k0, k1 = solve2(l00, l10, l11, pxz[2 * a, c], pxz[2 * a + 1, c])
            K[a, 0] = k0
            K[a, 1] = k1
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        x[i, 0] = xi0 + (K[0, 0] * nu0 + K[0, 1] * nu1)
        x[i, 1] = xi1 + (K[1, 0] * nu0 + K[1, 1] * nu1)
        x[i, 2] = wrap(xi2 + (K[2, 0] * nu0 + K[2, 1] * nu1))
        schur_update(P[i], K, S00, S01, S11, Pn)
        for a in range(3):
            for b in range(3):
                T3[a, b] = 0.5 * (Pn[a, b] + Pn[b, a])
        if not is_pd3(T3):
            repair3(T3)
            flags[4, e] = True
        for a in range(3):
            for b in range(3):
                P[i, a, b] = T3[a, b]
    return OK


@_jit
def correct_rounds(
    x, P, links, robots, filt, options, fusion, detection, defence, gauge, tamper, out
):  # fmt: skip
    """Every link of one step, robots in chunks of :data:`CHUNK` and each chunk in rounds
    (round ``r``: every robot's ``r``-th link); updates ``x: (B, 3)``, ``P: (B, 3, 3)`` in
    place. Arguments as :func:`~resloc.cl.kernels_links.correct_links` (the configuration
    must be one :func:`rounds_cover` accepts). Returns the status: ``OK``, ``NOT_PD`` or
    :data:`FALLBACK` (on both, the outputs are partial and must be discarded).
    Twin: :func:`resloc.cl.kernels_links.correct_links`."""
    # fusion, detection, defence, gauge, tamper: off (see rounds_cover)
    li, z, x_nb, P_nb, nb, channel_ok, last_norm, x_ref, P_ref, known = links
    nz_idx, nz_val, nz_cnt, Wm, Wc, circular = filt[1:]
    jitter = options[8]
    axis, value = _point_axes(nz_idx, nz_val, nz_cnt)
    m = axis.shape[0]
    C = CHUNK
    block_start = np.empty(C, np.int64)
    block_count = np.empty(C, np.int64)
    lane_e = np.empty(C, np.int64)
    obs = np.empty(C, np.int64)
    src = np.empty(C, np.int64)
    xi = np.empty((3, C))
    xr = np.empty((2, C))
    sin_cos = np.empty((2, C))
    Li = np.zeros((3, 3, C))
    Lj = np.zeros((3, 3, C))
    cov = np.empty((7, C))
    ok_i = np.empty(C)
    ok_j = np.empty(C)
    bad = np.empty(C)
    Z0 = np.empty((m, C))
    Z1 = np.empty((m, C))
    sums = np.empty((4, C))
    moments = np.empty((5, C))
    pxz = np.empty((6, C))
    mean = np.empty((3, C))
    scratch_in = np.empty((3, 3))
    scratch_out = np.empty((3, 3))
    K = np.empty((3, 2))
    Pn = np.empty((3, 3))
    T3 = np.empty((3, 3))
    E = li.shape[0]
    p = 0
    while p < E:
        blocks = 0
        rounds = 0
        while p < E and blocks < C:  # the next chunk: up to C robots' rows
            q = p + 1
            while q < E and li[q] == li[p]:
                q += 1
            block_start[blocks] = p
            block_count[blocks] = q - p
            rounds = max(rounds, q - p)
            blocks += 1
            p = q
        for r in range(rounds):
            n = 0
            for b in range(blocks):
                if block_count[b] > r:
                    lane_e[n] = block_start[b] + r
                    n += 1
            _gather_lanes(x, li, nb, x_ref, lane_e, n, obs, src, xi, xr, sin_cos, bad)
            _load_covariances(P, obs, n, cov)
            _chol_lanes(cov, n, Li, ok_i)
            _load_covariances(P_ref, src, n, cov)
            _chol_lanes(cov, n, Lj, ok_j)
            if not _chol_jitter_lanes(P, obs, n, Li, ok_i, jitter, scratch_in, scratch_out):
                return NOT_PD
            if not _chol_jitter_lanes(P_ref, src, n, Lj, ok_j, jitter, scratch_in, scratch_out):
                return NOT_PD
            _points_lanes(axis, value, Wm, n, xi, xr, sin_cos, Li, Lj, Z0, Z1, sums, bad)
            _moments_lanes(axis, value, Wm, Wc, circular, n, Li, Z0, Z1, sums, moments, pxz, mean, bad)
            for c in range(n):
                if bad[c] != 0.0:
                    return FALLBACK
            status = _update_lanes(
                x, P, lane_e, n, obs, moments, pxz, z, channel_ok, last_norm, robots, options,
                out, K, Pn, T3,
            )  # fmt: skip
            if status != OK:
                return status
    return OK


stamp_with_pieces(
    correct_rounds, _kernels_math, _kernels_trig, _kernels_lanes, _kernels_links
)
