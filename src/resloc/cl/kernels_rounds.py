"""The compiled CL link loop in rounds: many robots' links at once, in SIMD lanes.

:func:`resloc.cl.kernels_links.correct_links` walks the links in row order, one link after
the other: a link's sigma points depend on the robot's estimate as its previous link left
it, so the transcendental functions of a link (13 ``atan2``, 12 ``sin``/``cos`` for the
CKF) are scalar libm calls, most of a link's time. But robots are independent within a
step: only the order of a robot's own links matters. :func:`correct_rounds` therefore
takes the robots in chunks of ``CHUNK`` (:mod:`resloc.cl.kernels_lanes`) and, within a
chunk, processes round ``r`` (every robot's ``r``-th link) before round ``r + 1``.
Within a round the robots are independent, so every stage is a loop over *lanes* (one
robot each) on arrays of one component each (structure of arrays), which LLVM compiles to
SIMD instructions; the transcendentals inside are branch-free polynomials
(:mod:`resloc.cl.kernels_lanes`).
A robot's links are fused in the same order as by the row-order loop, so the results are
the same up to floating-point rounding (tested to 1e-9), and the working arrays are the
chunk's only (a few tens of kilobytes, whatever the number of robots).

Stages of one round (each a named function of :mod:`resloc.cl.kernels_link_stages`, twin
in ``correct_links``):

=======================  ===================================  ===========================
function                 paper                                block of ``correct_links``
=======================  ===================================  ===========================
``gather_lanes``         Algorithm 1 (points' factors)        ``chol3`` of ``P_i``, ``P_j``
``points_lanes``         eq. (3), sigma points                the points' range, bearing
``moments_lanes``        eq. (3), moments                     ``zh``, ``S``, ``P^xz``
``kalman_lanes``         eq. (9), Algorithm 1 (gain)          innovation to Schur update
``norms_lanes``          eq. (9), detector norms              ``_innovation_norm``
``decide_lanes``         eqs. (8), (10), (11), detector       gate, threshold, trigger
``apply_lanes``          Algorithm 1                          outputs, the update
=======================  ===================================  ===========================

Coverage (:func:`rounds_cover`): sigma-point filters whose 6-D points have at most one
non-zero entry (the CKF and the UKF), the Kalman update (``naive``, ``gauge`` with its
bookkeeping), ``ci`` and ``split_ci``, the detector gate and the event trigger with any
norms and either threshold innovation, the NIS and mean-shift CUSUMs, the robot CUSUM,
the recovery (its second pass on ``f P_i`` too), the stealthy attacker, transmitted and
cached neighbour estimates (:mod:`resloc.cl.kernels_round_cached`). The options' per-link
stages run lane by lane after the vectorized moments
(:mod:`resloc.cl.kernels_round_stages`). The ``tracked`` and ``factorized`` joints and
the EKF run in the row-order loop. A lane that needs a
special case of the row-order loop (the Cholesky jitter of ``P_i``, ``P_j`` is handled
here; a point at the robot's own position, an ``S`` that needs jitter, a measured bearing
outside ``(-2 pi, 2 pi)``, non-finite values, rows not sorted by observer are not) makes
:func:`correct_rounds` return ``FALLBACK`` (with the options' stores put back as they
were) and :func:`run_link_loop` runs the row-order loop from the start instead.

:func:`run_link_loop` is the one place that chooses: the rounds for at least
:data:`ROUNDS_MIN_LINKS` links of a covered configuration, else the row-order loop.
"""

from __future__ import annotations

import contextlib
from collections import Counter

import numpy as np

from resloc.cl import kernels_round_cached as _kernels_round_cached
from resloc.cl import kernels_round_stages as _kernels_round_stages
from resloc.cl import kernels_trig as _kernels_trig
from resloc.cl import kernels_zone as _kernels_zone
from resloc.cl import kernels_zone_verdicts as _kernels_zone_verdicts
from resloc.cl.kernels_fusion import CI, NAIVE_UPDATE, SPLIT_CI
from resloc.cl.kernels_joint_links import JOINT_FORM, NO_JOINT
from resloc.cl.kernels_joint_rounds import correct_joint_rounds, joint_rounds_cover
from resloc.cl.kernels_lanes import CHUNK, FALLBACK
from resloc.cl.kernels_link_stages import (
    UPDATE_ROWS,
    apply_lanes,
    chol_jitter_lanes,
    chol_lanes,
    decide_lanes,
    gather_lanes,
    kalman_lanes,
    load_covariances,
    load_robot_covariances,
    moment_scratch,
    moments_lanes,
    norms_lanes,
    point_axes,
    points_lanes,
    robot_lanes,
)
from resloc.cl.kernels_links import NOT_PD, OK, correct_links
from resloc.cl.kernels_math import jit_inline, jit_lanes, stamp_with_pieces
from resloc.cl.kernels_round_cached import (
    cached_lanes,
    fresh_covariances,
    fresh_lanes,
    lanes_ahead,
    pad_gathered,
    padded_lanes,
    sent_lanes,
    take_fresh,
    transmitted_lanes,
)
from resloc.cl.kernels_round_stages import (
    gauge_lanes,
    inflated_moments,
    intersect_lanes,
    link_scratch,
    restore_state,
    retry_lanes,
    save_state,
    screen_lanes,
    tamper_lanes,
)
from resloc.cl.kernels_split_lanes import split_lane_scratch
from resloc.cl.kernels_zone_verdicts import withhold_lanes, zone_lanes
from resloc.cl.links import LinkBatch

_jit = jit_lanes


__all__ = [
    "LOOP_RUNS",
    "ROUNDS_MIN_LINKS",
    "beyond_paper",
    "correct_rounds",
    "every_stage",
    "rounds_cover",
    "run_link_loop",
]

#: The rounds run from this many links on; below, the row-order loop (measured, CKF, one
#: correction: 28 links 1.09x the row order's time, 64 links 0.94x, 313 links 0.41x).
ROUNDS_MIN_LINKS = 64
#: How many corrections each loop ran (``rounds``; ``joint_rounds``: the ``tracked`` /
#: ``factorized`` joints' rounds, :mod:`resloc.cl.kernels_joint_rounds`;
#: ``rounds_fallback``: the rounds gave way to the row-order loop; ``row_order``), for
#: tests and benchmarks.
LOOP_RUNS: Counter = Counter()


def rounds_cover(filt, options, fusion, detection, defence, gauge, tamper) -> bool:
    """Whether :func:`correct_rounds` implements this configuration (arguments as those of
    :func:`~resloc.cl.kernels_links.correct_links`)."""
    del options, detection, defence, gauge, tamper  # every stage of theirs is a stage of them
    linearized, nz_cnt = filt[0], filt[3]
    return not (
        linearized
        or np.any(nz_cnt > 1)
        or fusion[0] not in (NAIVE_UPDATE, CI, SPLIT_CI)  # the tracked / factorized joints
    )


def beyond_paper(options, fusion, detection, defence, gauge, tamper):
    """The link loops' switch for the options' stages (arguments as those of
    :func:`~resloc.cl.kernels_links.correct_links`): None when every option is off (the
    paper's method), else True.

    Both loops take it as their last argument, and every option's stage sits behind
    ``beyond is not None``; numba prunes such a branch before typing when the argument is
    None, so the paper's method runs a form of each loop compiled without the options'
    stages (the first run of a fresh clone compiles only that), and any option runs the
    form with every option's stage, each behind its own runtime flag as before (compiled
    once for all options, on the first run that needs it). The ``tracked`` and
    ``factorized`` joints run a third form, switch
    :data:`~resloc.cl.kernels_joint_links.JOINT_FORM` (equal to True)."""
    on = (
        tamper[0]  # the stealthy attacker
        or detection[0]  # NIS CUSUM
        or detection[6]  # mean-shift CUSUM
        or detection[11].shape[0] > 0  # the redundancy pre-pass's verdicts
        or detection[13].shape[0] > 0  # the witness stage's verdicts
        or detection[12][0]  # zone-aware trust
        or defence[0]  # robot CUSUM
        or defence[5]  # recovery
        or fusion[0] != NAIVE_UPDATE  # ci, split_ci, the tracked / factorized joints
        or gauge[0]  # gauge bookkeeping
        or options[9]  # cached neighbour estimates
    )
    if not on:
        return None
    return JOINT_FORM if fusion[3][0] != NO_JOINT else True  # the joints: their own form


#: Set by :func:`every_stage` (the warm-up): the loops run the form with every option's
#: stage whatever the options.
_EVERY_STAGE = [False]


@contextlib.contextmanager
def every_stage():
    """Within: :func:`run_link_loop` runs the loops' form with every option's stage (to
    compile it, or load it from the cache, with the paper's structures)."""
    _EVERY_STAGE[0] = True
    try:
        yield
    finally:
        _EVERY_STAGE[0] = False


def run_link_loop(
    x, P, x_out, P_out, links, robots, filt, options, fusion, detection, defence, gauge, tamper,
    out,
):  # fmt: skip
    """Every link of one step into ``x_out``, ``P_out`` (copies of ``x``, ``P`` on entry):
    by rounds (:func:`correct_rounds`) where they cover the configuration and there are at
    least :data:`ROUNDS_MIN_LINKS` links, else (or when the rounds fall back) in row order
    (:func:`~resloc.cl.kernels_links.correct_links`). Each loop runs in the form
    :func:`beyond_paper` chooses (within :func:`every_stage`: the form with every option's
    stage). Returns the loop's status."""
    beyond = beyond_paper(options, fusion, detection, defence, gauge, tamper)
    if _EVERY_STAGE[0] and beyond is None:
        beyond = True
    args = (links, robots, filt, options, fusion, detection, defence, gauge, tamper, out, beyond)
    if len(links[0]) >= ROUNDS_MIN_LINKS and joint_rounds_cover(*args[2:-2]):
        # the tracked / factorized joints' rounds (kernels_joint_rounds)
        status = correct_joint_rounds(x_out, P_out, *args)
        if status != FALLBACK:
            LOOP_RUNS["joint_rounds"] += 1
            return status
        LOOP_RUNS["rounds_fallback"] += 1
        x_out[...] = x
        P_out[...] = P
        out.flags[...] = False
    elif len(links[0]) >= ROUNDS_MIN_LINKS and rounds_cover(
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


@jit_inline
def retried_lanes(n, inflation, decision, fresh):
    """Whether a lane of the round needs :func:`~resloc.cl.kernels_round_stages.
    inflated_moments`' second pass (delivered, and re-admitted with ``f > 1`` or fused with
    a cached estimate's fresh moments: the lanes that function selects)."""
    for c in range(n):
        if decision[3, c] == 1.0 and (inflation[c] > 1.0 or fresh[c] == 1.0):
            return True
    return False


@_jit
def correct_rounds(
    x, P, links, robots, filt, options, fusion, detection, defence, gauge, tamper, out,
    beyond,
):  # fmt: skip
    """Every link of one step, robots in chunks of ``CHUNK`` and each chunk in rounds
    (round ``r``: every robot's ``r``-th link); updates ``x: (B, 3)``, ``P: (B, 3, 3)`` in
    place. Arguments as :func:`~resloc.cl.kernels_links.correct_links` (the configuration
    must be one :func:`rounds_cover` accepts; ``beyond``: :func:`beyond_paper`'s switch).
    Returns the status: ``OK``, ``NOT_PD`` or ``FALLBACK`` (on both, the outputs are
    partial and must be discarded; on ``FALLBACK`` the options' stores are as they were on
    entry). Twin: :func:`resloc.cl.kernels_links.correct_links`."""
    if beyond is not None:  # the paper's method alone keeps no store to put back
        saved = save_state(detection, defence, fusion, gauge)
    status = _rounds(
        x, P, links, robots, filt, options, fusion, detection, defence, gauge, tamper, out,
        beyond,
    )  # fmt: skip
    if beyond is not None and status == FALLBACK:
        restore_state(saved, detection, defence, fusion, gauge)
    return status


@_jit
def _rounds(
    x, P, links, robots, filt, options, fusion, detection, defence, gauge, tamper, out, beyond
):  # fmt: skip
    """The body of :func:`correct_rounds` (which puts the stores back on ``FALLBACK``).
    Every option's stage sits behind ``beyond is not None``: with ``beyond = None`` numba
    prunes them before typing, and this form compiles the paper's stages only."""
    # x_ref, P_ref: the estimates of j the first pass uses (cached: the last received,
    # per link; else the transmitted rows x_nb, P_nb themselves)
    li, z, x_nb, P_nb, nb, channel_ok, last_norm, x_ref, P_ref, known = links
    nz_idx, nz_val, nz_cnt, Wm, Wc, circular = filt[1:]
    R, jitter = options[0], options[8]
    tampered = tamper[0]
    screening = detection[0] or detection[6] or detection[11].shape[0] > 0 or defence[0]
    screening = screening or defence[5] or detection[13].shape[0] > 0
    recovering = defence[5]
    cached = options[9]
    # cached: the second pass in the first pass's lanes (kernels_round_cached), unless the
    # attacker or zone trust change the lanes between the two
    ahead = cached and not tamper[0] and not detection[12][0]
    kalman = fusion[0] == NAIVE_UPDATE
    record_gauge = gauge[0]
    axis, value = point_axes(nz_idx, nz_val, nz_cnt)
    m = axis.shape[0]
    C = CHUNK
    block_start = np.empty(C, np.int64)
    block_count = np.empty(C, np.int64)
    lane_first = np.empty(C, np.int64)
    (lane_e, obs, src, xi, xr, zl, sin_cos, Li, Lj, cov, ok_i, ok_j, bad, Z0, Z1, sums,
     moments, pxz, mean) = moment_scratch(C, m)  # fmt: skip
    scratch_in = np.empty((3, 3))
    scratch_out = np.empty((3, 3))
    Pi = np.empty((9, C))
    update = np.empty((UPDATE_ROWS, C))
    norms = np.empty((2, C))
    inputs = np.empty((10, C))
    decision = np.empty((4, C))
    inflation = np.ones(C)
    T3 = np.empty((3, 3))
    zone = detection[12]
    zoned = zone[0]
    if beyond is not None:
        retry = retry_lanes(m, C if recovering or cached else 1)
        sent = np.empty(C)  # cached: delivered (decision[3] then holds fused)
        fresh = np.zeros(C)  # cached: delivered with a cached estimate (stays 0 otherwise)
        work = link_scratch()
        split_lanes = split_lane_scratch(fusion)  # the CI updates in SIMD (no columns else)
        zone_pxz = np.empty((3, 2))
        zone_h = np.empty((2, 3))
    E = li.shape[0]
    p = 0
    while p < E:
        blocks = 0
        rounds = 0
        while p < E and blocks < C:  # the next chunk: up to C robots' rows
            if p > 0 and li[p] < li[p - 1]:
                return FALLBACK  # rows not sorted by observer: a robot could be two lanes
            q = p + 1
            while q < E and li[q] == li[p]:
                q += 1
            block_start[blocks] = p
            block_count[blocks] = q - p
            rounds = max(rounds, q - p)
            blocks += 1
            p = q
        for r in range(rounds):
            # np.int64, not the literal 0: a call typed while n is still Literal[int](0)
            # would compile every stage a second time, for that literal
            n = np.int64(0)
            for b in range(blocks):
                if block_count[b] > r:
                    lane_e[n] = block_start[b] + r
                    lane_first[n] = block_start[b]
                    n += 1
            gather_lanes(x, li, nb, x_ref, z, lane_e, n, obs, src, xi, xr, zl, sin_cos, bad)
            # n2: the lanes of the vectorized stages; cached: lanes n .. 2n - 1 are the
            # second pass with j's transmitted estimate, ahead of the decisions (padded);
            # otherwise (the paper's form too): lanes n .. n2 - 1 copies of lane 0, never
            # read (the SIMD bodies take whole blocks of lanes,
            # kernels_round_cached.padded_lanes; the paper's 17 lanes ran one by one)
            n2 = n
            nj = n  # the lanes whose j is the first pass's (P_ref)
            if beyond is not None and ahead:
                n2 = lanes_ahead(n, C)
            else:
                n2 = padded_lanes(n, C)
                nj = n2
                pad_gathered(n, n2, obs, src, xi, xr, zl, sin_cos, bad)
            if beyond is not None and ahead and n2 > n:
                fresh_lanes(x_nb, n, n2, obs, src, xi, xr, zl, sin_cos, bad)
            load_covariances(P, obs, n2, cov)
            chol_lanes(cov, n2, Li, ok_i)
            load_covariances(P_ref, src, nj, cov)
            if beyond is not None and ahead and n2 > n:
                fresh_covariances(P_nb, src, n, n2, cov)
            chol_lanes(cov, n2, Lj, ok_j)
            if not chol_jitter_lanes(P, obs, n2, Li, ok_i, jitter, scratch_in, scratch_out):
                return NOT_PD
            if not chol_jitter_lanes(P_ref, src, nj, Lj, ok_j, jitter, scratch_in, scratch_out):
                return NOT_PD
            points_lanes(axis, value, Wm, n2, xi, xr, sin_cos, Li, Lj, Z0, Z1, sums, bad)
            moments_lanes(
                axis, value, Wm, Wc, circular, n2, Li, Z0, Z1, sums, moments, pxz, mean, bad
            )
            load_robot_covariances(P, obs, n2, Pi)
            kalman_lanes(n2, zl, R, moments, pxz, Pi, update)
            for c in range(n):
                if bad[c] != 0.0 or update[15, c] != 0.0:
                    return FALLBACK
            if beyond is not None and tampered:
                tamper_lanes(tamper, z, lane_e, obs, n, zl, moments, update)
            if beyond is not None and zoned:  # the verdicts, the partners' fixes
                if zone_lanes(
                    zone, x_nb, P_nb, P, obs, src, lane_e, n, xi, update, inflation,
                    decision, False, R, zone_pxz, zone_h,
                ) != OK:  # fmt: skip
                    return FALLBACK
            norms_lanes(n, update, options, norms)
            robot_lanes(obs, lane_e, n, channel_ok, last_norm, robots, options, norms, inputs)
            decide_lanes(n, options, norms, inputs, decision)
            if beyond is not None and zoned:
                withhold_lanes(zone, lane_e, n, decision, inflation)
            if beyond is not None and screening:
                screen_lanes(
                    P, lane_e, obs, n, channel_ok, options, detection, defence, update, norms,
                    decision, inflation,
                )  # fmt: skip
            if beyond is not None and cached:  # decision[3]: fused from here on
                cached_lanes(lane_e, n, known, channel_ok, options, decision, sent, fresh)
                if ahead and n2 > n:  # the delivered lanes' second pass from lanes n .. 2n - 1
                    take_fresh(n, inflation, decision, fresh, ok_j, bad, moments, pxz, update)
            # the second pass only in a round that has a lane for it: a call of
            # inflated_moments takes ~40 arrays (a reference count up and down each), ~0.7
            # us, 16 rounds a step; a step of the full defence re-admits a link rarely
            if (
                beyond is not None
                and (recovering or cached)
                and retried_lanes(n, inflation, decision, fresh)
            ):
                status = inflated_moments(
                    P, obs, src, n, inflation, decision, fresh, xi, xr, zl, sin_cos, Li, Lj,
                    moments, pxz, update, retry, filt, R, jitter, x_nb, P_nb,
                )  # fmt: skip
                if status != OK:
                    return status
                # (its lanes: substituted ones among the second pass's re-admitted)
                if zoned and zone_lanes(
                    zone, x_nb, P_nb, P, obs, src, lane_e, n, xi, update, inflation,
                    decision, True, R, zone_pxz, zone_h,
                ) != OK:  # fmt: skip
                    return FALLBACK
            if beyond is not None and cached:  # the update stages see j's transmitted x
                transmitted_lanes(x_nb, src, n, xr)
            apply_lanes(x, P, lane_e, n, obs, xi, update, norms, decision, out, T3, kalman)
            if beyond is not None and cached:
                sent_lanes(lane_e, n, sent, out)
            if beyond is not None and not kalman and not intersect_lanes(
                x, P, P_nb, lane_e, obs, src, n, xi, xr, update, moments, pxz, inflation,
                decision, options, fusion, out, work, filt[0], split_lanes,
            ):  # fmt: skip
                return NOT_PD
            if beyond is not None and record_gauge:
                gauge_lanes(
                    gauge, lane_e, lane_first, obs, n, xi, xr, update, decision, R, out, work
                )
    return OK


for _dispatcher in (correct_rounds, _rounds):
    stamp_with_pieces(
        _dispatcher,
        _kernels_trig,
        _kernels_round_stages,
        _kernels_round_cached,
        _kernels_zone,
        _kernels_zone_verdicts,
        *_kernels_round_stages.PIECE_MODULES,
    )


def rounds_warm_up_batch():
    """``(x, P, links)``: a ring of :data:`ROUNDS_MIN_LINKS` robots, each observing the
    next, enough links for :func:`run_link_loop` to take the rounds (compiled, or loaded
    from the cache, outside any timed section)."""
    n = ROUNDS_MIN_LINKS
    angle = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    x = np.column_stack([3.0 * np.cos(angle), 3.0 * np.sin(angle), angle - np.pi])
    P = np.broadcast_to(0.01 * np.eye(3), (n, 3, 3)).copy()
    i = np.arange(n)
    j = (i + 1) % n
    z = np.tile([0.3, 1.6], (n, 1))
    ok = np.ones(n, dtype=bool)
    links = LinkBatch(i, j, z, x[j], P[j], ok, np.zeros(n), np.zeros(n), np.ones(n))
    return x, P, links
