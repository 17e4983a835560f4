"""Compiled twin of the ``summed`` update (``UpdateMode.SUMMED``: Algorithm 1 literally).

In the summed update every link of a step is judged and fused from the *predicted*
estimates: the gains are computed from ``x_i,k|k-1``, ``P_i,k|k-1`` and the updates added
per robot (``np.add.at`` in :func:`resloc.cl.step.correct`), then one positive-definiteness
repair per robot. The detector stages judge all of a robot's rows in one call, so the
per-robot stages see them together: the robot CUSUM adds the excesses of all the robot's
rows before it judges any, and the recovery reads the robot's run count, spread and applied
inflation as they were before the step (:func:`robot_block_stages`).

:func:`correct_summed` walks each robot's rows (rows sorted by observer) in three passes:
per row the moments at the prediction, the innovation, the norms, the threshold and the
per-link stages (:func:`~resloc.cl.kernels_detection.detect_link`: the gate, the CUSUMs,
the pre-passes' verdicts); then the per-robot stages over the robot's rows; then per row
the re-admitted rows' moments from the inflated covariance, the event trigger and channel,
and the fused rows' updates, accumulated into the robot's estimate. Coverage
(:func:`resloc.cl.backend.kernel_refusal`): naive fusion, transmitted or cached neighbour
estimates (with ``cached``, the first reception triggers and a delivered row's moments are
taken again from the transmitted estimate, beside the re-admitted rows'), any filter and
detector stage the row-order loop covers (zone trust's verdicts and position fixes at the
predicted estimates, its withheld rows kept from the per-robot stages), the stealthy
attacker's compiled form. The rows' moments at the prediction come from SIMD lanes where
they can (:mod:`resloc.cl.kernels_summed_lanes`).

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`link_moments`           ``fusion.moments`` (naive: the filter's relative moments)
:func:`robot_block_stages`     ``RobotCusum.discard`` and ``RejectionRecovery.discard``
                               on one call's rows of one robot
:func:`correct_summed`         the ``summed`` branch of ``resloc.cl.step._correct_reference``
                               (with ``_decide`` on every row at once)
=============================  ==========================================================
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from resloc.cl import kernels_defence as _kernels_defence
from resloc.cl import kernels_detection as _kernels_detection
from resloc.cl import kernels_links as _kernels_links
from resloc.cl import kernels_math as _kernels_math
from resloc.cl import kernels_points as _kernels_points
from resloc.cl import kernels_tamper as _kernels_tamper
from resloc.cl import kernels_zone as _kernels_zone
from resloc.cl import kernels_zone_verdicts as _kernels_zone_verdicts
from resloc.cl.kernels_detection import detect_link, gain_at, nis_of
from resloc.cl.kernels_fusion import NAIVE_UPDATE
from resloc.cl.kernels_links import (
    NOT_PD,
    OK,
    cached_decision,
    decide_link,
    event_threshold_of_link,
    gate_link,
    innovation_norm_of_link,
    joseph_update,
    linearized_moments,
    point_offsets,
    schur_update,
)
from resloc.cl.kernels_math import (
    chol2,
    chol3,
    jit,
    jit_inline,
    solve2,
    stamp_with_pieces,
    store_covariance,
    wrap,
)
from resloc.cl.kernels_points import POINT_ROWS, point_moments
from resloc.cl.kernels_rounds import LOOP_RUNS
from resloc.cl.kernels_summed_lanes import (
    SUMMED_LANES_MIN_LINKS,
    summed_lanes_cover,
    summed_moments_lanes,
)
from resloc.cl.kernels_tamper import stealthy_measurement
from resloc.cl.kernels_zone_verdicts import (
    SUBSTITUTED,
    WITHHELD,
    position_fix_of_link,
    zone_verdict,
)

__all__ = [
    "SUMMED_RUNS",
    "UNSORTED",
    "correct_summed",
    "link_moments",
    "robot_block_stages",
    "run_summed_loop",
]

#: Status: the rows are not sorted by observer (the reference path then runs the step).
UNSORTED = 3
#: How many corrections the summed loop ran, for tests and benchmarks.
SUMMED_RUNS: Counter = Counter()


@jit_inline
def link_moments(
    linearized, nz_idx, nz_val, nz_cnt, Wm, Wc, circular, xi0, xi1, xi2, Pi, xr0, xr1, Pr,
    R, jitter, Li, Lj, off, Zp, Pxz, Hi, Hj, T3,
):  # fmt: skip
    """The moments of one link's measurement (eq. 3) at robot i's ``(xi, Pi)`` and j's
    ``(xr, Pr)``: ``(ok, zh0, zh1, S00, S01, S11, re00, re01, re11)`` (``re``: the EKF's
    ``R_eff``; ``Pxz``, ``Hi`` filled). Twin: the block of
    :func:`~resloc.cl.kernels_links.correct_links` (``SigmaPointFilter.relative_moments``,
    ``ExtendedFilter.relative_moments``)."""
    if linearized:
        zh0, zh1, S00, S01, S11, re00, re01, re11 = linearized_moments(
            xi0, xi1, xi2, Pi, xr0, xr1, Pr, R, Hi, Hj, T3, Pxz
        )
        return True, zh0, zh1, S00, S01, S11, re00, re01, re11
    if not chol3(Pi, Li, jitter) or not chol3(Pr, Lj, jitter):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    point_offsets(Li, Lj, nz_idx, nz_val, nz_cnt, off)
    sin_i = math.sin(xi2)
    cos_i = math.cos(xi2)
    zh0, zh1, S00, S01, S11 = point_moments(
        off, Wm, Wc, circular, xi0, xi1, xi2, xr0, xr1, sin_i, cos_i, R, Zp, Pxz
    )
    return True, zh0, zh1, S00, S01, S11, 0.0, 0.0, 0.0


@jit_inline
def robot_block_stages(defence, start, stop, i, P_i, gated, detected, stat, inflation, withheld):
    """The per-robot stages on robot ``i``'s rows ``start:stop`` of one summed call
    (``P_i``: its predicted covariance; ``stat``: the rows' NIS): the robot CUSUM adds all
    the rows' excesses (the rows the gate passed) before it judges any, then the recovery,
    from the robot's run count, spread and applied inflation before the call, re-admits
    discarded rows (``detected``, ``inflation`` updated in place). Twin:
    ``RobotCusum.discard`` (:func:`~resloc.cl.detection_robot.robot_cusum`) and
    ``RejectionRecovery.discard`` (``update_rejection_runs``, ``_record_applied``) on rows
    that repeat a robot. The rows zone trust ``withheld`` are not theirs (no stage but
    zone trust sees them: :func:`resloc.cl.detection.detect`)."""
    robot, rk, rh, rg, rslot, recovery, after, gate, cap = defence[:9]
    runs, runs_slot, spread, sslot, applied, aslot = defence[9:]
    if robot:
        k = gain_at(rk, i)
        h = gain_at(rh, i)
        slot = rslot[start]
        excess = 0.0
        fed = False
        for e in range(start, stop):  # np.bincount: the rows' sum, then added to g
            if not gated[e] and not withheld[e]:
                excess += stat[e] - k
                fed = True
        g = rg[slot]
        if fed:
            g = g + excess
            if g < 0.0:
                g = 0.0
            if g > 2.0 * h:
                g = 2.0 * h
            rg[slot] = g
        for e in range(start, stop):
            if g > h and stat[e] > k:
                detected[e] = True
    if not recovery:
        return
    R = gain_at(after, i)
    f_max = gain_at(cap, i)
    n = runs[runs_slot[start]]
    f = math.nan
    if n >= R:
        f = np.exp2((n - R) / R)
        if f > f_max:
            f = f_max
    trace = P_i[0, 0] + P_i[1, 1]
    before = spread[sslot[start]]
    growth = trace / before if before > 0.0 else math.inf
    if growth < 1.0:
        growth = 1.0
    if f > growth:  # False for a NaN f: not in recovery stays NaN, as np.minimum keeps it
        f = growth
    A = applied[aslot[start]]
    remaining = (f_max * f_max) / (A if A > 1.0 else 1.0)
    if remaining < 1.0:
        remaining = 1.0
    if f > remaining:
        f = remaining
    passed = False
    readmitted = False
    discarded = 0.0
    for e in range(start, stop):
        if withheld[e]:
            continue
        if not detected[e]:
            passed = True
        elif math.isfinite(f) and stat[e] / f <= gain_at(gate, i):
            detected[e] = False
            inflation[e] = f
            readmitted = True
        else:
            discarded += 1.0
    if passed:  # an ordinary acceptance: the spread restarts, nothing applied, no run
        spread[sslot[start]] = trace
        applied[aslot[start]] = 0.0
        runs[runs_slot[start]] = 0.0
    elif readmitted:  # stays in recovery at the same count
        applied[aslot[start]] = (A if A > 1.0 else 1.0) * f
    else:
        runs[runs_slot[start]] = n + discarded


@jit
def correct_summed(
    x_pred, P_pred, x, P, links, robots, filt, options, detection, defence, tamper, out,
    lanes,
):  # fmt: skip
    """Every link of one step from the predicted estimates ``x_pred: (B, 3)``,
    ``P_pred: (B, 3, 3)``, the updates added per robot into ``x``, ``P`` (copies of the
    predictions on entry), one repair per robot. Arguments as
    :func:`~resloc.cl.kernels_links.correct_links` (naive fusion);
    ``lanes = (done, zh, s, Pxz)``: the rows' moments the SIMD lanes computed
    (:func:`~resloc.cl.kernels_summed_lanes.summed_moments_lanes`; ``done`` empty: none),
    ``Pxz: (E, 3, 2)`` also the working array of the rows' cross-covariances. Returns
    ``OK``, ``NOT_PD`` or :data:`UNSORTED` (then the outputs are partial and must be
    discarded). Twin: the ``summed`` branch of ``resloc.cl.step._correct_reference``."""
    # x_ref, P_ref: the estimates of j the first pass uses (cached: j's last received, per
    # link; else the transmitted rows x_nb, P_nb themselves)
    li, z, x_nb, P_nb, nb, channel_ok, last_norm, x_ref, P_ref, known = links
    risk_s, risk_c, lambda2, rho, alpha, gamma, zeta_s, zeta_c = robots
    linearized, nz_idx, nz_val, nz_cnt, Wm, Wc, circular = filt
    R, noise_std, detector, trigger, det_norm, trig_norm, risk_floor, last_sent = options[:8]
    jitter, cached, update_without_transmission = options[8], options[9], options[10]
    out_norm, out_threshold, flags = out
    zone = detection[12]  # zone-aware trust (kernels_zone): verdicts at the prediction
    zoned = zone[0]
    z_rec = zone[2]
    defending = defence[0] or defence[5]
    tampered = tamper[0]
    attacked = tamper[3]
    std0 = noise_std[0]
    std1 = noise_std[1]
    m = Wm.shape[0]
    E = li.shape[0]
    Li = np.zeros((3, 3))
    Lj = np.zeros((3, 3))
    off = np.zeros((6, m))
    Zp = np.zeros((POINT_ROWS, m))
    Hj = np.zeros((2, 3))
    T3 = np.zeros((3, 3))
    A3 = np.zeros((3, 3))
    K = np.zeros((3, 2))
    Pn = np.zeros((3, 3))
    Pinf = np.zeros((3, 3))
    # per row: the first pass's results, read by the robot's stages and the update
    zu = np.empty((E, 2))  # the reading as received (the stealthy attacker's, if any)
    nu = np.empty((E, 2))
    cov = np.empty((E, 3))  # S
    chol = np.empty((E, 3))  # S = L L^T
    done, zh_rows, s_rows, Pxz = lanes
    pre = done.shape[0] == E
    Hi = np.zeros((E, 2, 3))
    reff = np.zeros((E, 3))
    n_trig = np.empty(E)
    delta = np.empty(E)
    stat = np.empty(E)
    gated = np.zeros(E, np.bool_)
    detected = np.zeros(E, np.bool_)
    inflation = np.ones(E)
    withheld = np.zeros(E, np.bool_)
    any_fused = False
    start = 0
    while start < E:
        i = li[start]
        if start > 0 and i < li[start - 1]:
            return UNSORTED
        stop = start + 1
        while stop < E and li[stop] == i:
            stop += 1
        Pi = P_pred[i]
        xi0 = x_pred[i, 0]
        xi1 = x_pred[i, 1]
        xi2 = x_pred[i, 2]
        for e in range(start, stop):  # 1. moments, innovation, norms, per-link stages
            n = nb[e]
            if pre and done[e]:  # the lanes' moments (Pxz[e] filled): S as point_moments
                zh0 = zh_rows[e, 0]
                zh1 = zh_rows[e, 1]
                S00 = s_rows[e, 0] + R[0, 0]
                S01 = 0.5 * ((s_rows[e, 1] + R[0, 1]) + (s_rows[e, 1] + R[1, 0]))
                S11 = s_rows[e, 2] + R[1, 1]
                re00 = re01 = re11 = 0.0
            else:
                ok, zh0, zh1, S00, S01, S11, re00, re01, re11 = link_moments(
                    linearized, nz_idx, nz_val, nz_cnt, Wm, Wc, circular, xi0, xi1, xi2, Pi,
                    x_ref[n, 0], x_ref[n, 1], P_ref[n], R, jitter, Li, Lj, off, Zp, Pxz[e],
                    Hi[e], Hj, T3,
                )  # fmt: skip
                if not ok:
                    return NOT_PD
            reff[e, 0] = re00
            reff[e, 1] = re01
            reff[e, 2] = re11
            zu0 = z[e, 0]
            zu1 = z[e, 1]
            nu0 = zu0 - zh0
            nu1 = wrap(zu1 - zh1)
            l00, l10, l11 = chol2(S00, S01, S11, jitter)
            if l00 == 0.0:
                return NOT_PD
            if tampered and attacked[e]:  # the stealthy attacker sees z_hat and S
                zt0, zt1 = stealthy_measurement(
                    tamper, i, z[e, 0], z[e, 1], nu0, nu1, l00, l10, l11
                )
                zu0 = zt0
                zu1 = wrap(zt1)
                nu0 = zu0 - zh0
                nu1 = wrap(zu1 - zh1)
            if zoned:  # twin: substitute_reciprocal, ZoneTrust.discard at x_i,k|k-1
                verdict = zone_verdict(zone, e, xi0, xi1, x_nb[n, 0], x_nb[n, 1])
                withheld[e] = verdict == WITHHELD
                if verdict == SUBSTITUTED:  # the partner's position fix of i
                    nu0, nu1, S00, S01, S11, re00, re01, re11 = position_fix_of_link(
                        xi0, xi1, Pi, 1.0, x_nb[n, 0], x_nb[n, 1], x_nb[n, 2], P_nb[n],
                        z_rec[e, 0], z_rec[e, 1], R, Pxz[e], Hi[e],
                    )  # fmt: skip
                    l00, l10, l11 = chol2(S00, S01, S11, jitter)
                    if l00 == 0.0:
                        return NOT_PD
                    reff[e, 0] = re00
                    reff[e, 1] = re01
                    reff[e, 2] = re11
            zu[e, 0] = zu0
            zu[e, 1] = zu1
            nu[e, 0] = nu0
            nu[e, 1] = nu1
            cov[e, 0] = S00
            cov[e, 1] = S01
            cov[e, 2] = S11
            chol[e, 0] = l00
            chol[e, 1] = l10
            chol[e, 2] = l11
            nt = innovation_norm_of_link(trig_norm, nu0, nu1, std0, std1, l00, l10, l11)
            nd = nt
            if det_norm != trig_norm:
                nd = innovation_norm_of_link(det_norm, nu0, nu1, std0, std1, l00, l10, l11)
            n_trig[e] = nt
            delta[e] = event_threshold_of_link(
                gain_at(alpha, i), lambda2[i], gain_at(gamma, i), last_norm[e] if last_sent
                else nt, gain_at(zeta_s, i), risk_s[i], gain_at(zeta_c, i), risk_c[i],
                risk_floor,
            )  # fmt: skip
            g = gate_link(nd, detector, gain_at(rho, i))
            if withheld[e]:  # discarded, and no other stage sees it
                gated[e] = False
                detected[e] = True
            else:
                gated[e] = g
                detected[e] = detect_link(detection, e, i, g, nu0, nu1, nd, det_norm, l00, l10, l11)
            stat[e] = nis_of(nu0, nu1, l00, l10, l11)
        if defending:  # 2. the per-robot stages over the robot's rows
            robot_block_stages(
                defence, start, stop, i, Pi, gated, detected, stat, inflation, withheld
            )
        first = -1
        for e in range(start, stop):  # 3. trigger, channel and the fused rows' updates
            triggered, delivered = decide_link(
                detected[e], n_trig[e], delta[e], trigger, channel_ok[e]
            )
            fuse = delivered
            if cached:  # the first reception triggers; a cached estimate may be fused
                triggered, delivered, fuse = cached_decision(
                    detected[e], triggered, delivered, known[e], trigger, channel_ok[e],
                    update_without_transmission,
                )  # fmt: skip
            out_norm[e] = n_trig[e]
            out_threshold[e] = math.nan if detected[e] else delta[e]
            flags[0, e] = detected[e]
            flags[1, e] = triggered
            flags[2, e] = delivered
            flags[3, e] = fuse
            if not fuse:
                continue
            # a delivered message carries j's current estimate: fused with that (cached)
            fresh = cached and delivered and known[e]
            Pu = Pi
            l00 = chol[e, 0]
            l10 = chol[e, 1]
            l11 = chol[e, 2]
            nu0 = nu[e, 0]
            nu1 = nu[e, 1]
            re00 = reff[e, 0]
            re01 = reff[e, 1]
            re11 = reff[e, 2]
            S00 = cov[e, 0]
            S01 = cov[e, 1]
            S11 = cov[e, 2]
            if inflation[e] > 1.0 or fresh:  # the moments again, from f P_i or fresh x_j
                if inflation[e] > 1.0:  # re-admitted: from the inflated covariance
                    for a in range(3):
                        for c in range(3):
                            Pinf[a, c] = Pi[a, c] * inflation[e]
                    Pu = Pinf
                n = nb[e]
                if zoned and zone[3][e] == SUBSTITUTED:  # the position fix from f P_i
                    nu0, nu1, S00, S01, S11, re00, re01, re11 = position_fix_of_link(
                        xi0, xi1, Pu, 1.0, x_nb[n, 0], x_nb[n, 1], x_nb[n, 2], P_nb[n],
                        z_rec[e, 0], z_rec[e, 1], R, Pxz[e], Hi[e],
                    )  # fmt: skip
                else:
                    xr_, Pr = (x_nb, P_nb) if fresh else (x_ref, P_ref)
                    ok, zh0, zh1, S00, S01, S11, re00, re01, re11 = link_moments(
                        linearized, nz_idx, nz_val, nz_cnt, Wm, Wc, circular, xi0, xi1, xi2,
                        Pu, xr_[n, 0], xr_[n, 1], Pr[n], R, jitter, Li, Lj, off, Zp, Pxz[e],
                        Hi[e], Hj, T3,
                    )  # fmt: skip
                    if not ok:
                        return NOT_PD
                    nu0 = zu[e, 0] - zh0
                    nu1 = wrap(zu[e, 1] - zh1)
                l00, l10, l11 = chol2(S00, S01, S11, jitter)
                if l00 == 0.0:
                    return NOT_PD
            # Kalman gain K = P^xz S^-1 (twin: kalman_gain), then the update of x_i,k|k-1
            for a in range(3):
                k0, k1 = solve2(l00, l10, l11, Pxz[e, a, 0], Pxz[e, a, 1])
                K[a, 0] = k0
                K[a, 1] = k1
            if linearized:  # Joseph form with R_eff (twin: kalman_update)
                joseph_update(Pu, K, Hi[e], re00, re01, re11, A3, T3, Pn)
            else:  # P - K S K^T
                schur_update(Pu, K, S00, S01, S11, Pn)
            # np.add.at: the robot's estimate moves by each update's step from the prediction
            x[i, 0] += (xi0 + (K[0, 0] * nu0 + K[0, 1] * nu1)) - xi0
            x[i, 1] += (xi1 + (K[1, 0] * nu0 + K[1, 1] * nu1)) - xi1
            x[i, 2] += wrap(xi2 + (K[2, 0] * nu0 + K[2, 1] * nu1)) - xi2
            for a in range(3):
                for b in range(3):
                    P[i, a, b] += 0.5 * (Pn[a, b] + Pn[b, a]) - Pi[a, b]
            if first < 0:
                first = e
        if first >= 0:  # one repair per robot, flagged on its first fused row
            any_fused = True
            for a in range(3):
                for b in range(3):
                    Pn[a, b] = P[i, a, b]
            if store_covariance(P, i, Pn, T3):
                flags[4, first] = True
        start = stop
    if any_fused:
        for b in range(x.shape[0]):
            x[b, 2] = wrap(x[b, 2])
    return OK


stamp_with_pieces(
    correct_summed,
    _kernels_math,
    _kernels_points,
    _kernels_links,
    _kernels_detection,
    _kernels_defence,
    _kernels_tamper,
    _kernels_zone,
    _kernels_zone_verdicts,
)


def run_summed_loop(
    x, P, x_out, P_out, links, robots, filt, options, fusion, detection, defence, gauge, tamper,
    out,
):  # fmt: skip
    """The summed update of one step into ``x_out``, ``P_out`` (copies of ``x``, ``P`` on
    entry), arguments as :func:`~resloc.cl.kernels_rounds.run_link_loop` (``fusion`` and
    ``gauge``: naive, none): the rows' moments in SIMD lanes where they cover the filter
    and there are at least :data:`~resloc.cl.kernels_summed_lanes.SUMMED_LANES_MIN_LINKS`
    links (counted as ``rounds`` in :data:`~resloc.cl.kernels_rounds.LOOP_RUNS`, else
    ``row_order``), then :func:`correct_summed`. Returns the status."""
    del gauge
    if fusion[0] != NAIVE_UPDATE:
        return NOT_PD  # (summed_refusal keeps other fusions out: never reached)
    SUMMED_RUNS["summed"] += 1
    E = len(links[0])
    Pxz = np.zeros((E, 3, 2))
    if E >= SUMMED_LANES_MIN_LINKS and summed_lanes_cover(filt):  # the moments in lanes
        done = np.empty(E, np.bool_)
        zh = np.empty((E, 2))
        s = np.empty((E, 3))
        summed_moments_lanes(x, P, links, filt, zh, s, Pxz, done)
        LOOP_RUNS["rounds"] += 1
    else:
        done, zh, s = _NO_LANES
        LOOP_RUNS["row_order"] += 1
    return correct_summed(
        x,
        P,
        x_out,
        P_out,
        links,
        robots,
        filt,
        options,
        detection,
        defence,
        tamper,
        out,
        (done, zh, s, Pxz),
    )


_NO_LANES = (np.zeros(0, np.bool_), np.zeros((0, 2)), np.zeros((0, 3)))
