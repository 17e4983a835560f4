"""The ``tracked`` and ``factorized`` joints in the link rounds: many robots' links at once.

The row-order loop (:func:`resloc.cl.kernels_links.correct_links`, form
:data:`~resloc.cl.kernels_joint_links.JOINT_FORM`) fuses one link after the other, and a
link's sigma points cost it 13 scalar ``atan2`` and 12 ``sin``/``cos`` calls, most of its
time. :func:`correct_joint_rounds` runs the correlated joint in rounds as
:func:`resloc.cl.kernels_rounds.correct_rounds` runs the other methods (round ``r``: every
robot's ``r``-th link, one robot per lane): the points' range and bearing, their moments,
the innovation, gain and decisions are the SIMD stages of
:mod:`resloc.cl.kernels_link_stages`; what the joint adds is per lane, with the row-order
loop's own pieces (:mod:`resloc.cl.kernels_joint_links`), so the numbers are the same:

=============================  =========================================  =====================
function                       what                                       piece of
                                                                          ``correct_links``
=============================  =========================================  =====================
:func:`joint_factor_lanes`     the joint's blocks ``P_i``, ``C_ij``,       ``joint_cross``,
                               ``P_j`` and its 6 x 6 Cholesky factor      ``correlated_offsets``
:func:`correlated_points_lanes`  eq. (3): every point's range and         ``point_moments`` on
                               bearing (SIMD)                             the correlated offsets
:func:`joint_record_lanes`     the update's record (``tracked``: the      ``joint_record``
                               covariance the joint gives ``P_i``)
=============================  =========================================  =====================

The factor of ``[[P_i, C], [C^T, P_j]]`` is ``[[L_i, 0], [X, L_s]]``: ``L_i`` the factor of
``P_i``, ``X = C^T L_i^-T``, ``L_s`` the factor of the Schur complement ``P_j - X X^T``. A
point on one of i's axes therefore moves j's position too (by ``X``'s column), a point on
one of j's axes moves j only (by ``L_s``'s): :func:`correlated_points_lanes` is
:func:`~resloc.cl.kernels_link_stages.points_lanes` with that term, and the moments
(``P^xz`` reads i's offsets only) are :func:`~resloc.cl.kernels_link_stages.moments_lanes`
as they are.

Per robot the joint keeps what the row-order loop keeps for the robot whose rows it is on
(``tracked``: the covariance ``P_i`` the joint gives after each update, ``now``; both: the
link's blocks until its record, ``blocks``). Coverage (:func:`joint_rounds_cover`): the
CKF and the UKF, the detector gate, the trigger, the CUSUMs, the robot CUSUM and the
stealthy attacker; the EKF, the recovery, ``cached`` neighbour estimates and zone trust
run the row-order loop. A lane that needs a special case (:mod:`resloc.cl.kernels_rounds`)
makes the rounds return ``FALLBACK`` with the stores and the joint's working copies put
back (:func:`reset_joint`).
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl import kernels_joint_links as _kernels_joint_links
from resloc.cl import kernels_round_stages as _kernels_round_stages
from resloc.cl.kernels_joint_links import (
    NO_JOINT,
    TRACKED,
    chol6,
    factorized_cross,
    factorized_record,
    joint6,
    tracked_cross,
    tracked_record,
)
from resloc.cl.kernels_lanes import (
    CHUNK,
    FALLBACK,
    SINCOS_LANES_MAX,
    atan2_lanes,
    sincos_lanes,
    wrap_lanes,
)
from resloc.cl.kernels_link_stages import (
    UPDATE_ROWS,
    apply_lanes,
    decide_lanes,
    gather_lanes,
    kalman_lanes,
    load_robot_covariances,
    moment_scratch,
    moments_lanes,
    norms_lanes,
    point_axes,
    robot_lanes,
)
from resloc.cl.kernels_links import NOT_PD, OK
from resloc.cl.kernels_math import jit_lanes, stamp_with_pieces, store_covariance
from resloc.cl.kernels_round_stages import (
    link_scratch,
    restore_state,
    save_state,
    screen_lanes,
    tamper_lanes,
)

_jit = jit_lanes

__all__ = [
    "chol6_lanes",
    "correct_joint_rounds",
    "correlated_points_lanes",
    "joint_factor_lanes",
    "joint_record_lanes",
    "joint_rounds_cover",
    "reset_joint",
]


def joint_rounds_cover(filt, options, fusion, detection, defence, gauge, tamper) -> bool:
    """Whether :func:`correct_joint_rounds` implements this configuration (arguments as
    those of :func:`~resloc.cl.kernels_links.correct_links`): a correlated joint, a
    sigma-point filter whose points have at most one non-zero entry, and none of the
    recovery, ``cached`` neighbour estimates, zone trust, the gauge bookkeeping."""
    del tamper  # the stealthy attacker is a stage of the rounds
    linearized, nz_cnt = filt[0], filt[3]
    return bool(
        fusion[3][0] != NO_JOINT
        and not linearized
        and not np.any(nz_cnt > 1)
        and not options[9]  # cached
        and not defence[5]  # recovery
        and not detection[12][0]  # zone trust
        and not gauge[0]
    )


@_jit
def reset_joint(joint):
    """The joint's working copies as :func:`~resloc.cl.kernels_joint.joint_state` made them
    (no update recorded): the row-order loop starts from them after a ``FALLBACK``."""
    A, noise, Bij, fused, gains = joint[5], joint[4], joint[6], joint[10], joint[13]
    for b in range(A.shape[0]):
        for p in range(3):
            for q in range(3):
                A[b, p, q] = 1.0 if p == q else 0.0
    for b in range(noise.shape[0]):
        for p in range(3):
            for q in range(3):
                noise[b, p, q] = 0.0
    for e in range(Bij.shape[0]):
        for p in range(3):
            for q in range(3):
                Bij[e, p, q] = 0.0
    for e in range(gains.shape[0]):
        for p in range(3):
            for q in range(3):
                gains[e, p, q] = 0.0
    for b in range(fused.shape[0]):
        for m in range(fused.shape[1]):
            fused[b, m] = False


@_jit
def joint_factor_lanes(
    joint, P, P_ref, lane_e, lane_first, obs, src, n, fused, jitter, now, blocks, J, L, ok,
    Li, X, Ls,
):  # fmt: skip
    """Per lane: the blocks of the correlated joint (:func:`joint_cross`, kept in
    ``blocks: (27, C)`` for the record) and the Cholesky factor of the joint
    (:func:`chol6`, the row-order loop's), split into ``Li``, ``X`` and ``Ls`` (3, 3, C)
    (``Li``, ``Ls``: lower triangles). ``tracked``: robot i's covariance now comes from
    ``now`` after its first link and goes back there. The factors by :func:`chol6_lanes`
    (SIMD), the lanes that need jitter by :func:`chol6` itself. False when a covariance or
    the joint has no Cholesky factor. Twin: ``joint_cross`` and ``correlated_offsets`` of
    ``correct_links``."""
    tracked = joint[0] == TRACKED
    work = joint[11]
    J6 = joint[12]
    for c in range(n):
        e = lane_e[c]
        i = obs[c]
        # a loop per method (the lane's method is the step's), each inlining its own cross:
        # the two in one loop cost 7x (kernels_joint_links.tracked_cross)
        if tracked:
            if e != lane_first[c]:
                for a in range(3):
                    for b in range(3):
                        work[4, a, b] = now[i, a, b]
            tracked_cross(joint, e, lane_first[c], fused, i)
            for a in range(3):
                for b in range(3):
                    now[i, a, b] = work[4, a, b]
        elif not factorized_cross(joint, e, i, P[i], P_ref[src[c]], jitter):
            return False
        for k in range(3):
            for a in range(3):
                for b in range(3):
                    blocks[9 * k + 3 * a + b, c] = work[k, a, b]
        joint6(work, J6)
        for r in range(6):  # its lower triangle, row by row (chol6_lanes' layout)
            for b in range(r + 1):
                J[r * (r + 1) // 2 + b, c] = J6[0, r, b]
    chol6_lanes(J, n, L, ok)
    for c in range(n):
        if ok[c] != 1.0:  # the jitter's levels: chol6 itself
            for r in range(6):
                for b in range(r + 1):
                    J6[0, r, b] = J6[0, b, r] = J[r * (r + 1) // 2 + b, c]
            if not chol6(J6, jitter):
                return False
            for r in range(6):
                for b in range(r + 1):
                    L[r * (r + 1) // 2 + b, c] = J6[1, r, b]
        for a in range(3):
            for b in range(a + 1):
                Li[a, b, c] = L[a * (a + 1) // 2 + b, c]
                Ls[a, b, c] = L[(3 + a) * (4 + a) // 2 + 3 + b, c]
            for b in range(3):
                X[a, b, c] = L[(3 + a) * (4 + a) // 2 + b, c]
    return True


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


@_jit
def joint_record_lanes(
    joint, P, lane_e, lane_first, obs, n, xi, xr, update, decision, R, out, work, now, blocks
):  # fmt: skip
    """The record of every fused lane's update (its gain, i's estimate before the update,
    j's transmitted one, the link's blocks of :func:`joint_factor_lanes`); ``tracked``:
    robot i's covariance becomes the joint's (into ``P``, repaired where not positive
    definite, and ``now``). Twin: the ``joint_record`` call of ``correct_links`` and its
    ``store_covariance``."""
    flags = out[2]
    fused = flags[3]
    K, Hi, Hj, T3, Pn, G3 = work[2], work[3], work[4], work[6], work[7], work[8]
    jwork = joint[11]
    tracked = joint[0] == TRACKED
    for c in range(n):
        if decision[3, c] != 1.0:
            continue
        e = lane_e[c]
        i = obs[c]
        for k in range(3):
            for a in range(3):
                for b in range(3):
                    jwork[k, a, b] = blocks[9 * k + 3 * a + b, c]
        for a in range(3):
            K[a, 0] = update[16 + 2 * a, c]
            K[a, 1] = update[17 + 2 * a, c]
        if tracked:  # (each method's record inlined apart, see joint_factor_lanes)
            tracked_record(
                joint, e, lane_first[c], fused, i, xi[0, c], xi[1, c], xr[0, c], xr[1, c], K,
                R, Hi, Hj, G3, T3, Pn,
            )  # fmt: skip
            # the Schur update apply_lanes stored gives way to the joint's
            for a in range(3):
                for b in range(3):
                    now[i, a, b] = jwork[4, a, b]
            flags[4, e] = store_covariance(P, i, Pn, T3)
        else:
            factorized_record(
                joint, e, i, xi[0, c], xi[1, c], xr[0, c], xr[1, c], K, Hi, Hj, G3, T3
            )


@_jit
def correct_joint_rounds(
    x, P, links, robots, filt, options, fusion, detection, defence, gauge, tamper, out
):  # fmt: skip
    """Every link of one step of ``tracked`` or ``factorized`` fusion in rounds; arguments
    and statuses as :func:`resloc.cl.kernels_rounds.correct_rounds` (the configuration must
    be one :func:`joint_rounds_cover` accepts). On ``FALLBACK`` the options' stores and
    the joint's working copies are as they were on entry. Twin:
    :func:`resloc.cl.kernels_links.correct_links` (form ``JOINT_FORM``)."""
    saved = save_state(detection, defence, fusion, gauge)
    status = _joint_rounds(
        x, P, links, robots, filt, options, fusion, detection, defence, gauge, tamper, out
    )
    if status == FALLBACK:
        restore_state(saved, detection, defence, fusion, gauge)
        reset_joint(fusion[3])
    return status


@_jit
def _joint_rounds(
    x, P, links, robots, filt, options, fusion, detection, defence, gauge, tamper, out
):  # fmt: skip
    """The body of :func:`correct_joint_rounds`: the chunks and rounds of
    :func:`resloc.cl.kernels_rounds.correct_rounds` with the joint's stages."""
    li, z, _, _, nb, channel_ok, last_norm, x_ref, P_ref, _ = links
    nz_idx, nz_val, nz_cnt, Wm, Wc, circular = filt[1:]
    R, jitter = options[0], options[8]
    tampered = tamper[0]
    screening = detection[0] or detection[6] or detection[11].shape[0] > 0 or defence[0]
    joint = fusion[3]
    fused = out[2][3]
    axis, value = point_axes(nz_idx, nz_val, nz_cnt)
    m = axis.shape[0]
    C = CHUNK
    block_start = np.empty(C, np.int64)
    block_count = np.empty(C, np.int64)
    lane_first = np.empty(C, np.int64)
    (lane_e, obs, src, xi, xr, zl, sin_cos, Li, Ls, _, _, _, bad, Z0, Z1, sums, moments,
     pxz, mean) = moment_scratch(C, m)  # fmt: skip
    X = np.zeros((3, 3, C))
    blocks = np.empty((27, C))
    J = np.empty((21, C))  # the lanes' 6 x 6 joints and factors (chol6_lanes)
    L = np.empty((21, C))
    ok = np.empty(C)
    now = np.empty((P.shape[0], 3, 3))  # tracked: each robot's covariance under the joint
    Pi = np.empty((9, C))
    update = np.empty((UPDATE_ROWS, C))
    norms = np.empty((2, C))
    inputs = np.empty((10, C))
    decision = np.empty((4, C))
    inflation = np.ones(C)
    T3 = np.empty((3, 3))
    work = link_scratch()
    E = li.shape[0]
    p = 0
    while p < E:
        count = 0
        rounds = 0
        while p < E and count < C:  # the next chunk: up to C robots' rows
            if p > 0 and li[p] < li[p - 1]:
                return FALLBACK  # rows not sorted by observer: a robot could be two lanes
            q = p + 1
            while q < E and li[q] == li[p]:
                q += 1
            block_start[count] = p
            block_count[count] = q - p
            rounds = max(rounds, q - p)
            count += 1
            p = q
        for r in range(rounds):
            n = np.int64(0)
            for b in range(count):
                if block_count[b] > r:
                    lane_e[n] = block_start[b] + r
                    lane_first[n] = block_start[b]
                    n += 1
            gather_lanes(x, li, nb, x_ref, z, lane_e, n, obs, src, xi, xr, zl, sin_cos, bad)
            if not joint_factor_lanes(
                joint, P, P_ref, lane_e, lane_first, obs, src, n, fused, jitter, now, blocks,
                J, L, ok, Li, X, Ls,
            ):  # fmt: skip
                return NOT_PD
            correlated_points_lanes(
                axis, value, Wm, n, xi, xr, sin_cos, Li, X, Ls, Z0, Z1, sums, bad
            )
            moments_lanes(
                axis, value, Wm, Wc, circular, n, Li, Z0, Z1, sums, moments, pxz, mean, bad
            )
            load_robot_covariances(P, obs, n, Pi)
            kalman_lanes(n, zl, R, moments, pxz, Pi, update)
            for c in range(n):
                if bad[c] != 0.0 or update[15, c] != 0.0:
                    return FALLBACK
            if tampered:
                tamper_lanes(tamper, z, lane_e, obs, n, zl, moments, update)
            norms_lanes(n, update, options, norms)
            robot_lanes(obs, lane_e, n, channel_ok, last_norm, robots, options, norms, inputs)
            decide_lanes(n, options, norms, inputs, decision)
            if screening:
                screen_lanes(
                    P, lane_e, obs, n, channel_ok, options, detection, defence, update, norms,
                    decision, inflation,
                )  # fmt: skip
            apply_lanes(x, P, lane_e, n, obs, xi, update, norms, decision, out, T3, True)
            joint_record_lanes(
                joint, P, lane_e, lane_first, obs, n, xi, xr, update, decision, R, out, work,
                now, blocks,
            )  # fmt: skip
    return OK


for _dispatcher in (
    reset_joint,
    joint_factor_lanes,
    chol6_lanes,
    correlated_points_lanes,
    joint_record_lanes,
    correct_joint_rounds,
    _joint_rounds,
):
    stamp_with_pieces(_dispatcher, _kernels_joint_links, *_kernels_round_stages.PIECE_MODULES)
