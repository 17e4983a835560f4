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
                               covariance the joint gives ``P_i``;
                               the rounds run ``tracked_record_lanes``)
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

import numpy as np

from resloc.cl import kernels_joint_lanes as _kernels_joint_lanes
from resloc.cl import kernels_joint_links as _kernels_joint_links
from resloc.cl import kernels_joint_records as _kernels_joint_records
from resloc.cl import kernels_round_cached as _kernels_round_cached
from resloc.cl import kernels_round_stages as _kernels_round_stages
from resloc.cl import kernels_tracked_lanes as _kernels_tracked_lanes
from resloc.cl.kernels_joint_lanes import (
    CROSS_INPUT_ROWS,
    LANE_STRIDE,
    chol6_lanes,
    correlated_points_lanes,
    factorized_cross_lanes,
)
from resloc.cl.kernels_joint_links import (
    NO_JOINT,
    TRACKED,
    chol6,
    factorized_cross,
    joint6,
)
from resloc.cl.kernels_joint_records import factorized_record, tracked_record
from resloc.cl.kernels_lanes import (
    CHUNK,
    FALLBACK,
)
from resloc.cl.kernels_link_stages import (
    UPDATE_ROWS,
    apply_lanes,
    decide_lanes,
    gather_lanes,
    kalman_lanes,
    load_robot_covariances,
    moments_lanes,
    norms_lanes,
    point_axes,
    robot_lanes,
)
from resloc.cl.kernels_links import NOT_PD, OK
from resloc.cl.kernels_math import jit_inline, jit_lanes, stamp_with_pieces, store_covariance
from resloc.cl.kernels_round_cached import padded_lanes
from resloc.cl.kernels_round_stages import (
    link_scratch,
    restore_state,
    save_state,
    screen_lanes,
    tamper_lanes,
)
from resloc.cl.kernels_tracked_lanes import (
    RECORD_INPUT_ROWS,
    RECORD_OUTPUT_ROWS,
    tracked_cross_lanes,
    tracked_record_lanes,
)

_jit = jit_lanes

__all__ = [
    "correct_joint_rounds",
    "joint_factor_lanes",
    "joint_record_lanes",
    "joint_rounds_cover",
    "pad_lanes",
    "reset_joint",
]


def joint_rounds_cover(filt, options, fusion, detection, defence, gauge, tamper) -> bool:
    """Whether :func:`correct_joint_rounds` implements this configuration (arguments as
    those of :func:`~resloc.cl.kernels_links.correct_links`): a correlated joint, a
    sigma-point filter whose points have at most one non-zero entry, and none of the
    recovery, ``cached`` neighbour estimates, zone trust, the gauge bookkeeping."""
    del tamper  # the stealthy attacker is a stage of the rounds
    if fusion[3][0] == NO_JOINT or filt[0]:  # (filt[0]: linearized, the EKF)
        return False
    if options[9] or defence[5] or detection[12][0] or gauge[0]:
        return False  # cached, the recovery, zone trust, gauge
    return _one_axis_points(filt[3])


_ONE_AXIS: list = [None, False]


def _one_axis_points(nz_cnt: np.ndarray) -> bool:
    """Every sigma point has at most one non-zero entry (``nz_cnt``: the filter spec's
    counts, the same array every step: the answer kept for the last one)."""
    if _ONE_AXIS[0] is not nz_cnt:
        _ONE_AXIS[0], _ONE_AXIS[1] = nz_cnt, not bool(np.any(nz_cnt > 1))
    return _ONE_AXIS[1]


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
    rows, sigma, N = joint[14], joint[3], joint[1]  # tracked: M = I, rows of Sigma
    for b in range(rows.shape[0]):
        for p in range(3):
            for q in range(rows.shape[2]):
                rows[b, p, q] = sigma[b // N, 3 * (b % N) + p, q]


@jit_inline
def _joint_into_lane(work, J6, blocks, J, c):
    """The blocks of :func:`joint_cross` (``work[0:3]``) into lane ``c`` of ``blocks``, and
    the lower triangle of their symmetrized joint (:func:`joint6`) into ``J``'s."""
    for k in range(3):
        for a in range(3):
            for b in range(3):
                blocks[9 * k + 3 * a + b, c] = work[k, a, b]
    joint6(work, J6)
    for r in range(6):  # its lower triangle, row by row (chol6_lanes' layout)
        for b in range(r + 1):
            J[r * (r + 1) // 2 + b, c] = J6[0, r, b]


@_jit
def joint_factor_lanes(
    joint, P, P_ref, lane_e, lane_first, obs, src, n, fused, jitter, now, blocks, J, L, ok,
    Li, X, Ls, cross_in,
):  # fmt: skip
    """Per lane: the blocks of the correlated joint (:func:`joint_cross`, kept in
    ``blocks: (27, C)`` for the record) and the Cholesky factor of the joint
    (:func:`chol6`, the row-order loop's), split into ``Li``, ``X`` and ``Ls`` (3, 3, C)
    (``Li``, ``Ls``: lower triangles). ``tracked``: robot i's covariance now comes from
    ``now`` after its first link and goes back there; ``factorized``: the cross of every
    lane at once where its certificate holds (:func:`factorized_cross_lanes`, SIMD;
    ``cross_in``: its scratch). The factors by :func:`chol6_lanes` (SIMD), the lanes that
    need jitter by :func:`chol6` itself. False when a covariance or the joint has no
    Cholesky factor. ``tracked``'s blocks by
    :func:`~resloc.cl.kernels_tracked_lanes.tracked_cross_lanes` (``C_ij`` from the rows of
    ``M Sigma`` the records keep). Twin: ``joint_cross`` and ``correlated_offsets`` of
    ``correct_links``."""
    tracked = joint[0] == TRACKED
    work = joint[11]
    J6 = joint[12]
    full = 0  # factorized: lanes whose cross needs factorized_cross itself (ok[c] = 0)
    if tracked:  # (the scalar twin: tracked_cross and _joint_into_lane, lane by lane)
        tracked_cross_lanes(joint, lane_e, lane_first, obs, n, now, blocks, J)
    else:
        full = factorized_cross_lanes(joint, P, P_ref, lane_e, obs, src, n, cross_in, blocks, J, ok)
    for c in range(n if full else 0):
        # the lanes the certificate did not cover, in a loop of their own (inlined into
        # a lane loop, factorized_cross made every lane 2.3x slower)
        if ok[c] == 0.0:
            if not factorized_cross(joint, lane_e[c], obs[c], P[obs[c]], P_ref[src[c]], jitter):
                return False
            _joint_into_lane(work, J6, blocks, J, c)
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
def joint_record_lanes(
    joint, P, lane_e, lane_first, obs, n, xi, xr, update, decision, R, out, work, now, blocks
):  # fmt: skip
    """The record of every fused lane's update (its gain, i's estimate before the update,
    j's transmitted one, the link's blocks of :func:`joint_factor_lanes`); ``tracked``:
    robot i's covariance becomes the joint's (into ``P``, repaired where not positive
    definite, and ``now``). Twin: the ``joint_record`` call of ``correct_links`` and its
    ``store_covariance``. The rounds run ``tracked``'s record over lanes
    (:func:`~resloc.cl.kernels_tracked_lanes.tracked_record_lanes`, the same values to the
    bit); its branch here is that stage's scalar twin."""
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
    x, P, links, robots, filt, options, fusion, detection, defence, gauge, tamper, out,
    beyond,
):  # fmt: skip
    """Every link of one step of ``tracked`` or ``factorized`` fusion in rounds; arguments
    and statuses as :func:`resloc.cl.kernels_rounds.correct_rounds` (the configuration must
    be one :func:`joint_rounds_cover` accepts; ``beyond``, the loops' switch, is
    :data:`~resloc.cl.kernels_joint_links.JOINT_FORM` here, taken for the loops' common
    call and not read: these rounds have one form). On ``FALLBACK`` the options' stores and
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
    (lane_e, obs, src, xi, xr, zl, sin_cos, bad, Z0, Z1, sums, moments, pxz,
     mean) = _joint_moment_scratch(C, m)  # fmt: skip
    # the joint's lane arrays, LANE_STRIDE columns (kernels_joint_lanes: not 2 KiB rows)
    S = LANE_STRIDE
    # the factors' lower triangles and X are written for every lane a stage reads
    # (joint_factor_lanes, pad_lanes): only the upper triangles need their zeros, not a
    # memset of the three arrays (57 KiB a step, more than the first-level cache), and
    # only in the lanes a round can use (a lane per observer, padded: padded_lanes)
    Li = np.empty((3, 3, S))
    X = np.empty((3, 3, S))
    Ls = np.empty((3, 3, S))
    used = padded_lanes(min(P.shape[0], C), C)
    for a in range(3):
        for b in range(a + 1, 3):
            for c in range(used):
                Li[a, b, c] = 0.0
                Ls[a, b, c] = 0.0
    blocks = np.empty((27, S))
    J = np.empty((21, S))  # the lanes' 6 x 6 joints and factors (chol6_lanes)
    L = np.empty((21, S))
    ok = np.empty(C)
    tracked = joint[0] == TRACKED
    # factorized_cross_lanes' gathered inputs (factorized only)
    cross_in = np.empty((0 if tracked else CROSS_INPUT_ROWS, S))
    now = np.empty((P.shape[0], 3, 3))  # tracked: each robot's covariance under the joint
    fused_lanes = np.empty(C, np.int64)  # tracked_record_lanes' fused lanes and rows
    record_in = np.empty((RECORD_INPUT_ROWS if tracked else 0, S))
    record_out = np.empty((RECORD_OUTPUT_ROWS if tracked else 0, S))
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
                J, L, ok, Li, X, Ls, cross_in,
            ):  # fmt: skip
                return NOT_PD
            # the vectorized stages on padded lanes (copies of lane 0, never read): their
            # SIMD bodies take blocks of lanes (kernels_round_cached.padded_lanes)
            n2 = padded_lanes(n, C)
            pad_lanes(n, n2, obs, xi, xr, zl, sin_cos, bad, Li, X, Ls)
            correlated_points_lanes(
                axis, value, Wm, n2, xi, xr, sin_cos, Li, X, Ls, Z0, Z1, sums, bad
            )
            moments_lanes(
                axis, value, Wm, Wc, circular, n2, Li, Z0, Z1, sums, moments, pxz, mean, bad
            )
            load_robot_covariances(P, obs, n2, Pi)
            kalman_lanes(n2, zl, R, moments, pxz, Pi, update)
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
            if tracked:  # the record's arithmetic over the fused lanes (SIMD)
                tracked_record_lanes(
                    joint, P, lane_e, obs, n, xi, xr, update, decision, R, out[2], now, blocks,
                    fused_lanes, record_in, record_out, work[8], work[7], T3,
                )  # fmt: skip
            else:
                joint_record_lanes(
                    joint, P, lane_e, lane_first, obs, n, xi, xr, update, decision, R, out,
                    work, now, blocks,
                )  # fmt: skip
    return OK


@jit_inline
def _joint_moment_scratch(C, m):
    """The arrays of :func:`~resloc.cl.kernels_link_stages.moment_scratch` the joints'
    rounds use (the same shapes), without the independent factors ``Li``, ``Lj`` it zeroes
    (36 KiB a step) and the other arrays these rounds do not read: ``(lane_e, obs, src, xi,
    xr, zl, sin_cos, bad, Z0, Z1, sums, moments, pxz, mean)``."""
    return (
        np.empty(C, np.int64),
        np.empty(C, np.int64),
        np.empty(C, np.int64),
        np.empty((3, C)),
        np.empty((2, C)),
        np.empty((2, C)),
        np.empty((2, C)),
        np.empty(C),
        np.empty((m, C)),
        np.empty((m, C)),
        np.empty((4, C)),
        np.empty((5, C)),
        np.empty((6, C)),
        np.empty((3, C)),
    )


@_jit
def pad_lanes(n, n2, obs, xi, xr, zl, sin_cos, bad, Li, X, Ls):
    """Lanes ``n .. n2 - 1`` copies of lane 0 (the inputs of the vectorized stages): work
    for the SIMD bodies whose results are never read."""
    for d in range(n, n2):
        obs[d] = obs[0]
        for a in range(3):
            xi[a, d] = xi[a, 0]
            for b in range(3):
                Li[a, b, d] = Li[a, b, 0]
                X[a, b, d] = X[a, b, 0]
                Ls[a, b, d] = Ls[a, b, 0]
        xr[0, d] = xr[0, 0]
        xr[1, d] = xr[1, 0]
        zl[0, d] = zl[0, 0]
        zl[1, d] = zl[1, 0]
        sin_cos[0, d] = sin_cos[0, 0]
        sin_cos[1, d] = sin_cos[1, 0]
        bad[d] = bad[0]


for _dispatcher in (
    pad_lanes,
    reset_joint,
    joint_factor_lanes,
    joint_record_lanes,
    correct_joint_rounds,
    _joint_rounds,
):
    stamp_with_pieces(
        _dispatcher,
        _kernels_joint_links,
        _kernels_joint_lanes,
        _kernels_joint_records,
        _kernels_tracked_lanes,
        _kernels_round_cached,
        *_kernels_round_stages.PIECE_MODULES,
    )
