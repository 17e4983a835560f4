"""The options' stages of the link rounds (:func:`resloc.cl.kernels_rounds.correct_rounds`).

The rounds compute every lane's moments, innovation and Kalman update in SIMD loops
(:mod:`resloc.cl.kernels_link_stages`); what an option adds to a link is scalar, per-link
code that runs lane by lane after them, with the same pieces as the row-order loop
(:func:`resloc.cl.kernels_links.correct_links`). Within a round each robot holds one lane,
and round ``r`` holds every robot's ``r``-th link, so state keyed by the link (the CUSUMs)
or by the robot (the robot CUSUM, the recovery's runs, split CI's independent parts, the
gauge bookkeeping) sees a robot's links in the row order's sequence.

==========================  =================================  =============================
function                    option                             piece of ``correct_links``
==========================  =================================  =============================
:func:`tamper_lanes`        stealthy attacker                  ``stealthy_measurement``
:func:`screen_lanes`        CUSUMs, robot CUSUM, recovery      ``detect_link``,
                                                               ``defend_link``
:func:`inflated_moments`    recovery (re-admission,            the second pass
                            ``f > 1``), ``cached`` (delivered)
:func:`intersect_lanes`     ``ci``, ``split_ci``               ``ci_update``,
                                                               ``split_ci_update``
:func:`gauge_lanes`         ``gauge``                          ``gauge_record``
:func:`save_state`          (fallback)                         ``DetectorState.undo``
==========================  =================================  =============================

The stages write the per-link and per-robot stores in place; when the rounds give way to
the row-order loop (``FALLBACK``), :func:`restore_state` puts back what :func:`save_state`
copied, so that the row-order loop starts from the same state.
"""

from __future__ import annotations

import numpy as np

from resloc.cl import kernels_ci_lanes as _kernels_ci_lanes
from resloc.cl import kernels_ci_update as _kernels_ci_update
from resloc.cl import kernels_ci_weight as _kernels_ci_weight
from resloc.cl import kernels_defence as _kernels_defence
from resloc.cl import kernels_detection as _kernels_detection
from resloc.cl import kernels_fusion as _kernels_fusion
from resloc.cl import kernels_gauge as _kernels_gauge
from resloc.cl import kernels_joint as _kernels_joint
from resloc.cl import kernels_lanes as _kernels_lanes
from resloc.cl import kernels_link_stages as _kernels_link_stages
from resloc.cl import kernels_links as _kernels_links
from resloc.cl import kernels_math as _kernels_math
from resloc.cl import kernels_points as _kernels_points
from resloc.cl import kernels_split as _kernels_split
from resloc.cl import kernels_split_lanes as _kernels_split_lanes
from resloc.cl import kernels_tamper as _kernels_tamper
from resloc.cl import kernels_zone as _kernels_zone
from resloc.cl import kernels_zone_verdicts as _kernels_zone_verdicts
from resloc.cl.kernels_ci_lanes import ci_lanes
from resloc.cl.kernels_ci_update import ci_update
from resloc.cl.kernels_defence import recovery_step, robot_cusum_step
from resloc.cl.kernels_detection import (
    NIS_CODE,
    cusum_step,
    gain_at,
    mean_cusum_step,
    nis_of_white,
    whiten_of,
)
from resloc.cl.kernels_fusion import CI, SPLIT_CI
from resloc.cl.kernels_gauge import gauge_record, range_bearing_jacobians_into
from resloc.cl.kernels_lanes import FALLBACK
from resloc.cl.kernels_link_stages import UPDATE_ROWS, kalman_lanes
from resloc.cl.kernels_links import NOT_PD, OK, decide_link, point_offsets
from resloc.cl.kernels_math import (
    chol3,
    jit_lanes,
    stamp_with_pieces,
    store_covariance,
    wrap,
)
from resloc.cl.kernels_points import POINT_ROWS, point_moments
from resloc.cl.kernels_split import split_ci_update
from resloc.cl.kernels_split_lanes import split_ci_lanes
from resloc.cl.kernels_tamper import stealthy_measurement
from resloc.cl.kernels_zone_verdicts import SUBSTITUTED, WITHHELD

_jit = jit_lanes


__all__ = [
    "PIECE_MODULES",
    "gauge_lanes",
    "inflated_moments",
    "intersect_lanes",
    "link_scratch",
    "restore_state",
    "retry_lanes",
    "save_state",
    "screen_lanes",
    "tamper_lanes",
]


@_jit
def save_state(detection, defence, fusion, gauge):
    """Copies of the stores the options' stages write in place: the CUSUMs' statistics,
    the robot CUSUM's, the recovery's runs, spreads and applied inflations, split CI's
    independent parts, the gauge's ``A``, ``N`` and ``B_ij`` (empty for an option that is
    off)."""
    return (
        detection[4].copy(),
        detection[9].copy(),
        defence[3].copy(),
        defence[9].copy(),
        defence[11].copy(),
        defence[13].copy(),
        fusion[4].copy(),
        gauge[1].copy(),
        gauge[2].copy(),
        gauge[3].copy(),
    )


@_jit
def restore_state(saved, detection, defence, fusion, gauge):
    """Put back the stores :func:`save_state` copied (element loops: numba's generic
    array assignment costs seconds of compilation per array kind)."""
    _put_back_1d(detection[4], saved[0])
    _put_back_2d(detection[9], saved[1])
    _put_back_1d(defence[3], saved[2])
    _put_back_1d(defence[9], saved[3])
    _put_back_1d(defence[11], saved[4])
    _put_back_1d(defence[13], saved[5])
    _put_back_3d(fusion[4], saved[6])
    _put_back_3d(gauge[1], saved[7])
    _put_back_3d(gauge[2], saved[8])
    _put_back_3d(gauge[3], saved[9])


@_jit
def _put_back_1d(store, copy):
    for a in range(store.shape[0]):
        store[a] = copy[a]


@_jit
def _put_back_2d(store, copy):
    for a in range(store.shape[0]):
        for b in range(store.shape[1]):
            store[a, b] = copy[a, b]


@_jit
def _put_back_3d(store, copy):
    for a in range(store.shape[0]):
        for b in range(store.shape[1]):
            for c in range(store.shape[2]):
                store[a, b, c] = copy[a, b, c]


@_jit
def tamper_lanes(tamper, z, lane_e, obs, n, zl, moments, update):
    """The stealthy attacker on the lanes of the links it controls: it sees ``z_hat`` and
    ``S`` (the lane's factor), and the lane's measurement, innovation and Kalman change of
    ``x`` become the falsified measurement's. Twin: the ``tampered`` block of
    ``correct_links`` (``z``: the honest measurements)."""
    attacked = tamper[3]
    for c in range(n):
        e = lane_e[c]
        if not attacked[e]:
            continue
        zt0, zt1 = stealthy_measurement(
            tamper, obs[c], z[e, 0], z[e, 1], update[0, c], update[1, c], update[2, c],
            update[3, c], update[4, c],
        )  # fmt: skip
        zu1 = wrap(zt1)
        nu0 = zt0 - moments[0, c]
        nu1 = wrap(zu1 - moments[1, c])
        zl[0, c] = zt0
        zl[1, c] = zu1
        update[0, c] = nu0
        update[1, c] = nu1
        update[5, c] = update[16, c] * nu0 + update[17, c] * nu1
        update[6, c] = update[18, c] * nu0 + update[19, c] * nu1
        update[7, c] = update[20, c] * nu0 + update[21, c] * nu1


@_jit
def screen_lanes(
    P, lane_e, obs, n, channel_ok, options, detection, defence, update, norms, decision,
    inflation,
):  # fmt: skip
    """The detector stages with state after the gate (link CUSUM, mean-shift CUSUM, robot
    CUSUM, recovery) per lane, then the trigger and channel again on their verdict:
    rewrites ``decision``'s ``(detected, triggered, delivered)`` and gives each lane's
    covariance ``inflation`` (1: none; the recovery's re-admission: ``f > 1``).

    Twin: the ``detect_link``, ``defend_link`` and ``decide_link`` calls of
    ``correct_links``, with the same scalar steps. The structures are unpacked once, here,
    and the loop passes no array to a function: each array a piece receives costs a
    reference-count update per link (measured: the pieces that take the structures, 0.5 us
    a link for the full defence; this loop, 0.05 us)."""
    trigger, det_norm = options[3], options[4]
    cusum, ck, ch, ccap, cg, cslot, mean, mk, mh, mg, mslot, fixes, zone, witness = detection
    fixed = fixes.shape[0] > 0  # the redundancy pre-pass's verdict (kernels_redundancy)
    convicted = witness.shape[0] > 0  # the witness stage's verdict (kernels_witness)
    zoned = zone[0]  # zone-aware trust's verdicts (kernels_zone_verdicts.zone_lanes)
    verdict = zone[3]
    robot, rk, rh, rg, rslot, recovery, after, gate, cap = defence[:9]
    runs, runs_slot, spread, sslot, applied, aslot = defence[9:]
    whitened = mean or robot or recovery or (cusum and det_norm != NIS_CODE)
    for c in range(n):
        e = lane_e[c]
        i = obs[c]
        if zoned and verdict[e] == WITHHELD:  # no stage sees it (withhold_lanes)
            inflation[c] = 1.0
            continue
        gated = decision[1, c] == 1.0
        nu0 = update[0, c]
        nu1 = update[1, c]
        l00 = update[2, c]
        l10 = update[3, c]
        l11 = update[4, c]
        # (not on a row zone trust substituted: fused as the partner's fix)
        detected = gated or (fixed and fixes[e] and not (zoned and verdict[e] == SUBSTITUTED))
        detected = detected or (convicted and witness[e])
        # the whitened innovation once for the stages that read it (whiten_of; the NIS
        # from it: nis_of's operations, the same bits)
        y0 = y1 = 0.0
        if whitened:
            y0, y1 = whiten_of(nu0, nu1, l00, l10, l11)
        if cusum:  # detect_link: the NIS CUSUM of the link
            if det_norm == NIS_CODE:
                stat = norms[1, c] * norms[1, c]
            else:
                stat = nis_of_white(nu0, nu1, y0, y1, l00, l10, l11)
            s = cslot[e]
            cg[s], discard = cusum_step(
                cg[s], stat, gain_at(ck, i), gain_at(ch, i), gain_at(ccap, i)
            )
            detected = detected or discard
        if mean:  # detect_link: the signed CUSUMs of the link
            s = mslot[e]
            mg[s, 0], mg[s, 1], mg[s, 2], mg[s, 3], discard = mean_cusum_step(
                mg[s, 0], mg[s, 1], mg[s, 2], mg[s, 3], y0, y1, gain_at(mk, i),
                gain_at(mh, i), not gated,
            )  # fmt: skip
            detected = detected or discard
        f = 1.0
        if robot or recovery:  # defend_link
            stat = nis_of_white(nu0, nu1, y0, y1, l00, l10, l11)
        if robot:
            s = rslot[e]
            rg[s], discard = robot_cusum_step(
                rg[s], stat, gain_at(rk, i), gain_at(rh, i), not gated
            )
            detected = detected or discard
        if recovery:
            trace = P[i, 0, 0] + P[i, 1, 1]
            a = runs_slot[e]
            b = sslot[e]
            d = aslot[e]
            detected, f, runs[a], spread[b], applied[d] = recovery_step(
                runs[a], spread[b], applied[d], detected, stat, trace, gain_at(after, i),
                gain_at(gate, i), gain_at(cap, i),
            )  # fmt: skip
        triggered, delivered = decide_link(
            detected, norms[0, c], decision[0, c], trigger, channel_ok[e]
        )
        decision[1, c] = 1.0 if detected else 0.0
        decision[2, c] = 1.0 if triggered else 0.0
        decision[3, c] = 1.0 if delivered else 0.0
        inflation[c] = f


@_jit
def retry_lanes(m, columns):
    """Working arrays of :func:`inflated_moments` for ``m`` sigma points (``columns``:
    ``CHUNK`` where the recovery or cached estimates are on, else 1: never used)."""
    return (
        np.empty(columns, np.int64),  # the retried lane of each column
        np.empty((2, columns)),  # z
        np.empty((5, columns)),  # moments
        np.empty((6, columns)),  # P^xz
        np.empty((9, columns)),  # f P_i by lane
        np.empty((UPDATE_ROWS, columns)),  # update
        np.empty((3, 3)),  # f P_i
        np.zeros((3, 3)),  # its factor
        np.zeros((3, 3)),  # P_j's factor
        np.empty((3, 3)),  # P_j
        np.zeros((6, m)),  # the points' offsets
        np.zeros((POINT_ROWS, m)),  # the points' range and bearing
        np.zeros((3, 2)),  # P^xz of one lane
        np.zeros((2, 2)),  # no R: the moments' spread alone (R is kalman_lanes's)
    )


@_jit
def inflated_moments(
    P, obs, src, n, inflation, decision, fresh, xi, xr, zl, sin_cos, Li, Lj, moments, pxz,
    update, retry, filt, R, jitter, x_nb, P_nb,
):  # fmt: skip
    """The second pass of the fused lanes (``decision[3]``) whose update uses other
    moments than the first pass: those the recovery re-admitted with robot ``i``'s
    covariance inflated (``f = inflation[c] > 1``), and those delivered while the first
    pass used ``j``'s cached estimate (``fresh[c] == 1``: the moments with the transmitted
    one, ``x_nb``, ``P_nb`` at row ``src[c]``). The moments from ``f P_i`` lane by lane by
    the row-order loop's scalar pieces (a round has few such lanes: the SIMD stages would
    run mostly their scalar remainder), then the innovation and Kalman update of all of
    them at once (:func:`kalman_lanes`), written over the lanes' ``moments``, ``pxz`` and
    ``update`` (the first pass's factors ``Li``, ``Lj`` and heading's ``sin_cos`` where
    they serve). ``filt``: the filter's description. Returns ``OK``, ``NOT_PD`` (a
    covariance has no factor) or ``FALLBACK`` (a special case of the row-order loop).
    Twin: ``attempt == 1`` of ``correct_links``."""
    lane, zl_r, mom_r, pxz_r, Pi_r, upd_r, Pf, Li_s, Lj_s, Pj, off, Zp, Pxz_s, R0 = retry
    nz_idx, nz_val, nz_cnt, Wm, Wc, circular = filt[1:]
    k = np.int64(0)  # not the literal 0 (see _rounds): one compiled form of each stage
    for c in range(n):
        if not (decision[3, c] == 1.0 and (inflation[c] > 1.0 or fresh[c] == 1.0)):
            continue
        lane[k] = c
        i = obs[c]
        f = inflation[c]
        for a in range(3):
            for b in range(3):
                Pf[a, b] = P[i, a, b] * f  # f = 1: P_i itself
                Pi_r[3 * a + b, k] = Pf[a, b]
        if f > 1.0:
            if not chol3(Pf, Li_s, jitter):
                return NOT_PD
        else:  # the first pass's factor of the same P_i
            for a in range(3):
                for b in range(3):
                    Li_s[a, b] = Li[a, b, c]
        xr0 = xr[0, c]
        xr1 = xr[1, c]
        if fresh[c] == 1.0:  # j's transmitted estimate, its factor by chol3 (as the loop)
            s = src[c]
            xr0 = x_nb[s, 0]
            xr1 = x_nb[s, 1]
            for a in range(3):
                for b in range(3):
                    Pj[a, b] = P_nb[s, a, b]
            if not chol3(Pj, Lj_s, jitter):
                return NOT_PD
        else:  # the first pass's factor of the same P_j
            for a in range(3):
                for b in range(3):
                    Lj_s[a, b] = Lj[a, b, c]
        point_offsets(Li_s, Lj_s, nz_idx, nz_val, nz_cnt, off)
        zh0, zh1, s00, s01, s11 = point_moments(
            off, Wm, Wc, circular, xi[0, c], xi[1, c], xi[2, c], xr0, xr1, sin_cos[0, c],
            sin_cos[1, c], R0, Zp, Pxz_s,
        )  # fmt: skip
        mom_r[0, k] = zh0
        mom_r[1, k] = zh1
        mom_r[2, k] = s00
        mom_r[3, k] = s01
        mom_r[4, k] = s11
        for a in range(3):
            pxz_r[2 * a, k] = Pxz_s[a, 0]
            pxz_r[2 * a + 1, k] = Pxz_s[a, 1]
        zl_r[0, k] = zl[0, c]
        zl_r[1, k] = zl[1, c]
        k += 1
    if k == 0:
        return OK
    kalman_lanes(k, zl_r, R, mom_r, pxz_r, Pi_r, upd_r)
    for t in range(k):
        if upd_r[15, t] != 0.0:
            return FALLBACK
        c = lane[t]
        for a in range(5):
            moments[a, c] = mom_r[a, t]
        for a in range(6):
            pxz[a, c] = pxz_r[a, t]
        for a in range(UPDATE_ROWS):
            update[a, c] = upd_r[a, t]
    return OK


@_jit
def link_scratch():
    """The 3 x 3 and 3 x 2 scratch matrices of the scalar update stages: ``(P_i, P^xz, K,
    H_i, H_j, A3, T3, Pn, G3)``."""
    return (
        np.empty((3, 3)),
        np.empty((3, 2)),
        np.empty((3, 2)),
        np.empty((2, 3)),
        np.empty((2, 3)),
        np.empty((3, 3)),
        np.empty((3, 3)),
        np.empty((3, 3)),
        np.empty((3, 3)),
    )


@_jit
def intersect_lanes(
    x, P, P_ref, lane_e, obs, src, n, xi, xr, update, moments, pxz, inflation, decision,
    options, fusion, out, work, linearized, lanes,
):  # fmt: skip
    """Covariance intersection (``ci``) or split CI of every delivered lane, with the
    lane's moments (and robot ``i``'s covariance times the recovery's ``inflation``), then
    the posterior symmetrized, repaired where not positive definite, stored. False when a
    covariance has no Cholesky factor. ``linearized``: the filter's flag (``filt[0]``,
    False wherever the rounds run), passed as the runtime bool it is so that
    ``split_ci_update`` has the signature of the row-order loop's call and is compiled
    once for both loops (a literal ``False`` would compile a second form of it).
    ``lanes``: :func:`~resloc.cl.kernels_split_lanes.split_lane_scratch`; split CI and
    ``ci`` with its columns run in SIMD stages (:func:`~resloc.cl.kernels_split_lanes.
    split_ci_lanes`, :func:`~resloc.cl.kernels_ci_lanes.ci_lanes`, the same results;
    without, lane by lane here).
    Twin: the ``ci_update`` / ``split_ci_update`` calls of ``correct_links`` and its
    tail."""
    code = fusion[0]
    if code == SPLIT_CI and lanes.shape[1] > 0 and not linearized:
        return split_ci_lanes(
            x, P, P_ref, lane_e, obs, src, n, xi, xr, update, moments, pxz, inflation,
            decision, options, fusion, out, work, linearized, lanes,
        )  # fmt: skip
    if code == CI and lanes.shape[1] > 0 and not linearized:
        return ci_lanes(
            x, P, P_ref, lane_e, obs, src, n, xi, xr, update, moments, pxz, inflation,
            decision, options, fusion, out, work, lanes,
        )  # fmt: skip
    R, jitter = options[0], options[8]
    flags = out[2]
    Pi, Pxz, K, Hi, Hj, A3, T3, Pn = work[:8]
    for c in range(n):
        if decision[3, c] != 1.0:
            continue
        e = lane_e[c]
        i = obs[c]
        f = inflation[c]
        for a in range(3):
            for b in range(3):
                Pi[a, b] = P[i, a, b] * f  # f = 1: P_i itself
        for a in range(3):
            Pxz[a, 0] = pxz[2 * a, c]
            Pxz[a, 1] = pxz[2 * a + 1, c]
        S00 = moments[2, c] + R[0, 0]
        S01 = 0.5 * ((moments[3, c] + R[0, 1]) + (moments[3, c] + R[1, 0]))
        S11 = moments[4, c] + R[1, 1]
        xi0 = xi[0, c]
        xi1 = xi[1, c]
        range_bearing_jacobians_into(xi0, xi1, xr[0, c], xr[1, c], Hi, Hj)
        if code == CI:
            done = ci_update(
                x, i, xi0, xi1, xi[2, c], Pi, P_ref[src[c]], update[0, c], update[1, c],
                S00, S01, S11, Pxz, False, Hi, Hj, 0.0, 0.0, 0.0, R, fusion, jitter, K, A3,
                T3, Pn,
            )  # fmt: skip
        else:
            done = split_ci_update(
                x, e, i, xi0, xi1, xi[2, c], Pi, P_ref[src[c]], update[0, c], update[1, c],
                S00, S01, S11, Pxz, linearized, Hi, Hj, 0.0, 0.0, 0.0, R, fusion, jitter, K,
                A3, T3, Pn,
            )  # fmt: skip
        if not done:
            return False
        if store_covariance(P, i, Pn, T3):
            flags[4, e] = True
    return True


@_jit
def gauge_lanes(gauge, lane_e, lane_first, obs, n, xi, xr, update, decision, R, out, work):
    """The gauge bookkeeping of every delivered lane (its Kalman gain, robot ``i``'s
    estimate before the update, ``j``'s transmitted one; ``lane_first``: the row of
    robot ``i``'s first link). Twin: the ``gauge_record`` call of ``correct_links``."""
    fused = out[2][3]
    K, Hi, Hj, T3, G3 = work[2], work[3], work[4], work[6], work[8]
    for c in range(n):
        if decision[3, c] != 1.0:
            continue
        for a in range(3):
            K[a, 0] = update[16 + 2 * a, c]
            K[a, 1] = update[17 + 2 * a, c]
        gauge_record(
            gauge, lane_e[c], lane_first[c], fused, obs[c], xi[0, c], xi[1, c], xr[0, c],
            xr[1, c], K, R, Hi, Hj, G3, T3,
        )  # fmt: skip


#: The modules whose pieces the stages inline or call: an edit of one must recompile them
#: (and the rounds, which link them).
PIECE_MODULES = (
    _kernels_math,
    _kernels_lanes,
    _kernels_link_stages,
    _kernels_links,
    _kernels_detection,
    _kernels_defence,
    _kernels_fusion,
    _kernels_ci_weight,
    _kernels_ci_update,
    _kernels_split,
    _kernels_split_lanes,
    _kernels_ci_lanes,
    _kernels_joint,
    _kernels_gauge,
    _kernels_tamper,
    _kernels_zone,
    _kernels_zone_verdicts,
    _kernels_points,
)
for _dispatcher in (
    save_state,
    restore_state,
    _put_back_1d,
    _put_back_2d,
    _put_back_3d,
    tamper_lanes,
    screen_lanes,
    retry_lanes,
    inflated_moments,
    link_scratch,
    intersect_lanes,
    gauge_lanes,
):
    stamp_with_pieces(_dispatcher, *PIECE_MODULES)
