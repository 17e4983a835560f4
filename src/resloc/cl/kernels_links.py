"""The compiled CL link loop: every link of one step in one call (twin of
:func:`resloc.cl.step.correct`; the dispatch and its inputs are in :mod:`resloc.cl.kernels`).

The loop walks the links in row order (robot ``i``'s links in ascending ``j``). Robots are
independent within a step (a link reads only robot ``i``'s running estimate and ``j``'s
transmitted estimate), so the row-order loop gives exactly the rounds of the reference
path. Each piece of a link's work is a named function beside the numpy function it twins
(``docs/algorithm.md`` maps every equation to both); the scalar primitives are in
:mod:`resloc.cl.kernels_math`, the sigma points' range, bearing and moments (all points at
once, in SIMD polynomials) in :mod:`resloc.cl.kernels_points`, the options' pieces in their
own modules (detector stages:
:mod:`resloc.cl.kernels_detection`, gauge bookkeeping: :mod:`resloc.cl.kernels_gauge`,
the stealthy attacker: :mod:`resloc.cl.kernels_tamper`).
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl import kernels_ci_update as _kernels_ci_update
from resloc.cl import kernels_ci_weight as _kernels_ci_weight
from resloc.cl import kernels_defence as _kernels_defence
from resloc.cl import kernels_detection as _kernels_detection
from resloc.cl import kernels_fusion as _kernels_fusion
from resloc.cl import kernels_gauge as _kernels_gauge
from resloc.cl import kernels_joint_links as _kernels_joint_links
from resloc.cl import kernels_joint_records as _kernels_joint_records
from resloc.cl import kernels_math as _kernels_math
from resloc.cl import kernels_points as _kernels_points
from resloc.cl import kernels_split as _kernels_split
from resloc.cl import kernels_tamper as _kernels_tamper
from resloc.cl import kernels_zone as _kernels_zone
from resloc.cl import kernels_zone_verdicts as _kernels_zone_verdicts
from resloc.cl.kernels_ci_update import ci_update
from resloc.cl.kernels_defence import defend_link
from resloc.cl.kernels_detection import detect_link
from resloc.cl.kernels_fusion import CI, SPLIT_CI
from resloc.cl.kernels_gauge import gauge_record, range_bearing_jacobians_into
from resloc.cl.kernels_joint_links import (
    NO_JOINT,
    correlated_linearized_moments,
    correlated_offsets,
    joint_cross,
    joint_form,
)
from resloc.cl.kernels_joint_records import joint_record
from resloc.cl.kernels_math import (
    chol2,
    chol3,
    jit,
    jit_inline,
    sandwich,
    solve2,
    stamp_with_pieces,
    store_covariance,
    wrap,
)
from resloc.cl.kernels_points import POINT_ROWS, point_moments
from resloc.cl.kernels_split import split_ci_update
from resloc.cl.kernels_tamper import stealthy_measurement
from resloc.cl.kernels_zone_verdicts import (
    SUBSTITUTED,
    WITHHELD,
    position_fix_of_link,
    zone_verdict,
)

#: Kernel status codes.
OK = 0
NOT_PD = 1  # a Cholesky factorization failed even with the largest jitter, or NaN/inf


@jit_inline
def _innovation_norm(kind, nu0, nu1, std0, std1, l00, l10, l11):
    """Size of the innovation ``Lambda_ij`` of eq. (9) in the norm ``kind`` (a
    :data:`NORM_CODE`). Twin: :func:`resloc.cl.detector.innovation_norm`."""
    if kind == 0:
        return math.hypot(nu0, nu1)
    if kind == 1:
        return math.hypot(nu0 / std0, nu1 / std1)
    w0, w1 = solve2(l00, l10, l11, nu0, nu1)
    q = nu0 * w0 + nu1 * w1
    return math.sqrt(q if q > 0.0 else 0.0)


@jit_inline
def _linearized_moments(xi0, xi1, xi2, Pi, xj0, xj1, Pj, R, Hi, Hj, T3, Pxz):
    """First-order moments of eq. (3) with the range/bearing Jacobians at the means; fills
    ``work.Pxz`` and ``work.Hi``.

    Twin: :meth:`resloc.filters.ekf.ExtendedFilter.relative_moments`.
    Returns ``(zh0, zh1, S00, S01, S11, re00, re01, re11)`` with ``R_eff = H_j P_j H_j^T + R``
    (``T3``: scratch).
    """
    dx = xj0 - xi0
    dy = xj1 - xi1
    range_bearing_jacobians_into(xi0, xi1, xj0, xj1, Hi, Hj)
    zh0 = math.hypot(dx, dy)
    zh1 = wrap(math.atan2(dy, dx) - xi2)
    # R_eff = Hj Pj Hj^T + R ; S = Hi Pi Hi^T + R_eff (then both symmetrized)
    rj00, rj01, rj10, rj11 = sandwich(Hj, Pj, T3)
    rj00 += R[0, 0]
    rj01 += R[0, 1]
    rj10 += R[1, 0]
    rj11 += R[1, 1]
    si00, si01, si10, si11 = sandwich(Hi, Pi, T3)
    S00 = si00 + rj00
    S01 = 0.5 * ((si01 + rj01) + (si10 + rj10))
    S11 = si11 + rj11
    for a in range(3):
        for b in range(2):
            s = 0.0
            for c in range(3):
                s += Pi[a, c] * Hi[b, c]
            Pxz[a, b] = s
    return zh0, zh1, S00, S01, S11, rj00, 0.5 * (rj01 + rj10), rj11


@jit_inline
def _event_threshold(alpha, lambda2, gamma, size, zeta_s, risk_s, zeta_c, risk_c, floor):
    """Adaptive threshold ``delta_ij`` of eq. (11) of one link (the observer's gains, risks
    and ``lambda2``; ``size``: the innovation size in the threshold).
    Twin: :func:`resloc.cl.trigger.event_threshold`."""
    risk = 1.0 - zeta_s * risk_s - zeta_c * risk_c
    if risk < floor:
        risk = floor
    scale = alpha / lambda2 if lambda2 > 0.0 else math.inf
    delta = scale * (1.0 + gamma * size) * risk
    if math.isnan(delta):
        delta = math.inf
    return delta


@jit_inline
def _gate_link(n_det, detector, rho):
    """Attack detection of Algorithm 1: discard when the detector norm exceeds ``rho``.
    Twin: :func:`resloc.cl.detector.attack_detected` (the ``gate`` stage)."""
    return detector and n_det > rho


@jit_inline
def _decide_link(detected, n_trig, delta, trigger, channel_ok):
    """Event condition (eq. 10) and channel (eq. 8) of one link the detector judged:
    ``(triggered, delivered)``. Twin: ``resloc.cl.step._decide``."""
    fire = (n_trig > delta) if trigger else True
    triggered = (not detected) and fire
    return triggered, triggered and channel_ok


@jit_inline
def _cached_decision(
    detected, triggered, delivered, known, trigger, channel_ok, update_without_transmission
):  # fmt: skip
    """``(triggered, delivered, fused)`` of a link with ``cached`` neighbour estimates: the
    trigger fires at the first reception (nothing to compare against), and with
    ``update_without_transmission`` an accepted, untriggered link with a cached estimate is
    fused with it. Twin: ``resloc.cl.step._decide`` (its ``cached`` branches)."""
    if trigger and not detected and not known:
        triggered = True
        delivered = channel_ok
    fused = delivered or (update_without_transmission and not detected and not triggered and known)
    return triggered, delivered, fused


@jit_inline
def point_offsets(Li, Lj, nz_idx, nz_val, nz_cnt, off):
    """The joint points' offsets ``off[:, k] = blockdiag(L_i, L_j) u_k`` (``off: (6, m)``)
    from the non-zero entries of the unit points (``FilterKernelSpec``). Twin: the points of
    :class:`resloc.filters.sigma_points.SigmaPointFilter` over ``[x_i; x_j]``."""
    for k in range(nz_cnt.shape[0]):
        for a in range(6):
            off[a, k] = 0.0
        for t in range(nz_cnt[k]):
            b = nz_idx[k, t]
            u = nz_val[k, t]
            if b < 3:
                for a in range(3):
                    off[a, k] += Li[a, b] * u
            else:
                for a in range(3):
                    off[3 + a, k] += Lj[a, b - 3] * u


@jit_inline
def joseph_update(Pi, K, H, re00, re01, re11, A3, T3, Pn):
    """``(I - K H) P (I - K H)^T + K R_eff K^T`` into ``Pn`` (EKF; ``R_eff`` symmetric, its
    entries ``re00, re01, re11``; ``A3``, ``T3``: 3x3 scratch). Twin:
    :func:`resloc.filters.update.kalman_update`."""
    for a in range(3):
        for b in range(3):
            KH = K[a, 0] * H[0, b] + K[a, 1] * H[1, b]
            A3[a, b] = (1.0 if a == b else 0.0) - KH
    for a in range(3):
        for b in range(3):
            s = 0.0
            for c in range(3):
                s += A3[a, c] * Pi[c, b]
            T3[a, b] = s
    for a in range(3):
        t0 = K[a, 0] * re00 + K[a, 1] * re01
        t1 = K[a, 0] * re01 + K[a, 1] * re11
        for b in range(3):
            s = 0.0
            for c in range(3):
                s += T3[a, c] * A3[b, c]
            Pn[a, b] = s + (t0 * K[b, 0] + t1 * K[b, 1])


@jit_inline
def schur_update(Pi, K, S00, S01, S11, Pn):
    """``P - K S K^T`` into ``Pn`` (sigma-point filters).
    Twin: :func:`resloc.filters.update.kalman_update`."""
    for a in range(3):
        t0 = K[a, 0] * S00 + K[a, 1] * S01
        t1 = K[a, 0] * S01 + K[a, 1] * S11
        for b in range(3):
            Pn[a, b] = Pi[a, b] - (t0 * K[b, 0] + t1 * K[b, 1])


@jit
def correct_links(
    x, P, links, robots, filt, options, fusion, detection, defence, gauge, tamper, out, beyond
):
    """Every link of one step in row order (Algorithm 1's correction: eqs. (3), (8)-(11));
    updates ``x: (B, 3)``, ``P: (B, 3, 3)`` in place. Twin: :func:`resloc.cl.step.correct`.
    ``beyond``: :func:`resloc.cl.kernels_rounds.beyond_paper`'s switch; every option's
    block sits behind ``beyond is not None`` (pruned before typing when it is None).

    The structures are unpacked once, here: a field read inside the loop would cost a
    reference-count update per field and link. For the same reason the pieces that would
    take many arrays (the gain, the Joseph update) are blocks of this loop, each citing its
    twin; measured, as functions they cost 15-20% of the correction. The sigma points'
    moments are the exception (:func:`~resloc.cl.kernels_points.point_moments`): compiled
    for SIMD with IEEE division, they cannot be inlined into this loop, and their SIMD
    evaluation outweighs the call. Returns the status; on a non-OK status the outputs are
    partial and must be discarded.
    """
    li, z, x_nb, P_nb, nb, channel_ok, last_norm, x_ref, P_ref, known = links
    risk_s, risk_c, lambda2, rho, alpha, gamma, zeta_s, zeta_c = robots
    linearized, nz_idx, nz_val, nz_cnt, Wm, Wc, circular = filt
    R, noise_std, detector, trigger, det_norm, trig_norm, risk_floor, last_sent = options[:8]
    jitter, cached, update_without_transmission = options[8], options[9], options[10]
    out_norm, out_threshold, flags = out
    m = Wm.shape[0]
    Li = np.zeros((3, 3))
    Lj = np.zeros((3, 3))
    off = np.zeros((6, m))  # the points' offsets of [x_i; x_j], a row per coordinate
    Zp = np.zeros((POINT_ROWS, m))
    Pxz = np.zeros((3, 2))
    K = np.zeros((3, 2))
    Hi = np.zeros((2, 3))
    Hj = np.zeros((2, 3))
    Pn = np.zeros((3, 3))
    T3 = np.zeros((3, 3))
    A3 = np.zeros((3, 3))
    G3 = np.zeros((3, 3))
    Pinf = np.zeros((3, 3))
    defending = defence[0] or defence[5]
    # the detector stages' block only where one is on (else its verdict is the gate's):
    # inlined, it unpacks its structure, a reference count per array and link
    detecting = detection[0] or detection[6] or detection[11].shape[0] > 0
    detecting = detecting or detection[13].shape[0] > 0  # the witness stage's verdicts
    fusion_code = fusion[0]
    # tracked / factorized: moments under a correlated joint (kernels_joint_links)
    joint = fusion[3]
    # (their own compiled form: kernels_joint_links.JOINT_FORM; another form refuses them)
    correlated = joint_form(beyond) and joint[0] != NO_JOINT
    if beyond is not None and joint[0] != NO_JOINT and not correlated:
        return NOT_PD  # the caller's reference path records the joint
    std0 = noise_std[0]
    std1 = noise_std[1]
    record_gauge = gauge[0]
    tampered = tamper[0]
    attacked = tamper[3]
    zone = detection[12]  # zone-aware trust (kernels_zone)
    zoned = zone[0]
    fused = flags[3]
    first = 0  # robot i's first row
    for e in range(li.shape[0]):
        i = li[e]
        if e > 0 and li[e - 1] != i:
            first = e
        n = nb[e]  # j's transmitted estimate, read by index: no per-link copy
        Pi = P[i]
        Pj = P_nb[n]
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        sin_i = 0.0
        cos_i = 1.0
        if not linearized:  # the points' headings turn from robot i's (kernels_points)
            sin_i = math.sin(xi2)
            cos_i = math.cos(xi2)
        xj0 = x_nb[n, 0]
        xj1 = x_nb[n, 1]
        # The estimate of j the moments use: transmitted, or the last one received (cached;
        # then the rows are per link and n = e)
        xr0 = x_ref[n, 0]
        xr1 = x_ref[n, 1]
        Pr = P_ref[n]
        zu0 = z[e, 0]
        zu1 = z[e, 1]
        inflation = 1.0
        verdict = 0
        if beyond is not None and zoned:  # at robot i's running estimate
            verdict = zone_verdict(zone, e, xi0, xi1, xj0, xj1)
        substituted = verdict == SUBSTITUTED
        # A second pass only for a fused measurement whose update uses other moments (twin:
        # _decide): the recovery re-admitted it with robot i's covariance inflated, or it was
        # delivered while the first pass used j's cached estimate.
        for attempt in range(2):
            re00 = 0.0
            re01 = 0.0
            re11 = 0.0
            if (
                beyond is not None
                and correlated
                and not joint_cross(joint, e, first, fused, i, Pi, Pr, jitter)
            ):
                return NOT_PD
            if beyond is not None and linearized and correlated:
                zh0, zh1, S00, S01, S11 = correlated_linearized_moments(
                    joint, xi0, xi1, xi2, xr0, xr1, R, Hi, Hj, Pxz
                )
            elif linearized:
                zh0, zh1, S00, S01, S11, re00, re01, re11 = _linearized_moments(
                    xi0, xi1, xi2, Pi, xr0, xr1, Pr, R, Hi, Hj, T3, Pxz
                )
            else:
                # Moments of z_ij (eq. 3) from the filter's sigma points over [x_i; x_j] with
                # P = blockdiag(P_i, P_j) (twin: SigmaPointFilter.relative_moments).
                if beyond is not None and correlated:
                    if not correlated_offsets(joint, nz_idx, nz_val, nz_cnt, off, jitter):
                        return NOT_PD
                elif not chol3(Pi, Li, jitter) or not chol3(Pr, Lj, jitter):
                    return NOT_PD
                else:
                    point_offsets(Li, Lj, nz_idx, nz_val, nz_cnt, off)
                # the points' range and bearing, all points at once (kernels_points)
                zh0, zh1, S00, S01, S11 = point_moments(
                    off, Wm, Wc, circular, xi0, xi1, xi2, xr0, xr1, sin_i, cos_i, R, Zp, Pxz
                )
            # innovation, eq. (9)
            nu0 = zu0 - zh0
            nu1 = wrap(zu1 - zh1)
            l00, l10, l11 = chol2(S00, S01, S11, jitter)
            if l00 == 0.0:
                return NOT_PD
            if beyond is not None and substituted and attempt == 1:  # the fix, from f P_i
                nu0, nu1, S00, S01, S11, re00, re01, re11 = position_fix_of_link(
                    xi0, xi1, Pi, 1.0, xj0, xj1, x_nb[n, 2], Pj, zone[2][e, 0], zone[2][e, 1],
                    R, Pxz, Hi,
                )  # fmt: skip
                l00, l10, l11 = chol2(S00, S01, S11, jitter)
                if l00 == 0.0:
                    return NOT_PD
            if attempt == 1:
                break
            # the stealthy attacker sees z_hat and S (twin: tamper)
            if beyond is not None and tampered and attacked[e]:
                zt0, zt1 = stealthy_measurement(
                    tamper, i, z[e, 0], z[e, 1], nu0, nu1, l00, l10, l11
                )
                zu0 = zt0
                zu1 = wrap(zt1)
                nu0 = zu0 - zh0
                nu1 = wrap(zu1 - zh1)
            if beyond is not None and substituted:  # the partner's position fix of i
                nu0, nu1, S00, S01, S11, re00, re01, re11 = position_fix_of_link(
                    xi0, xi1, Pi, 1.0, xj0, xj1, x_nb[n, 2], Pj, zone[2][e, 0], zone[2][e, 1],
                    R, Pxz, Hi,
                )  # fmt: skip
                l00, l10, l11 = chol2(S00, S01, S11, jitter)
                if l00 == 0.0:
                    return NOT_PD
            n_trig = _innovation_norm(trig_norm, nu0, nu1, std0, std1, l00, l10, l11)
            if det_norm == trig_norm:
                n_det = n_trig
            else:
                n_det = _innovation_norm(det_norm, nu0, nu1, std0, std1, l00, l10, l11)
            a_i = alpha[i] if alpha.shape[0] > 1 else alpha[0]
            g_i = gamma[i] if gamma.shape[0] > 1 else gamma[0]
            zs_i = zeta_s[i] if zeta_s.shape[0] > 1 else zeta_s[0]
            zc_i = zeta_c[i] if zeta_c.shape[0] > 1 else zeta_c[0]
            rho_i = rho[i] if rho.shape[0] > 1 else rho[0]
            delta = _event_threshold(
                a_i, lambda2[i], g_i, last_norm[e] if last_sent else n_trig,
                zs_i, risk_s[i], zc_i, risk_c[i], risk_floor,
            )  # fmt: skip
            gated = _gate_link(n_det, detector, rho_i)
            detected = gated
            # zone trust's withheld rows: discarded, and no other stage sees them
            withheld = beyond is not None and verdict == WITHHELD
            if beyond is not None and detecting and not withheld:  # CUSUMs (kernels_detection)
                detected = detect_link(
                    detection, e, i, gated, nu0, nu1, n_det, det_norm, l00, l10, l11
                )
            # the per-robot stages (robot CUSUM, recovery: kernels_defence)
            if beyond is not None and defending and not withheld:
                detected, inflation = defend_link(
                    defence, e, i, detected, gated, Pi, nu0, nu1, l00, l10, l11
                )
            if withheld:
                detected = True
            triggered, delivered = _decide_link(detected, n_trig, delta, trigger, channel_ok[e])
            fuse = delivered
            if beyond is not None and cached:
                triggered, delivered, fuse = _cached_decision(
                    detected, triggered, delivered, known[e], trigger, channel_ok[e],
                    update_without_transmission,
                )  # fmt: skip
            out_norm[e] = n_trig
            out_threshold[e] = math.nan if detected else delta
            flags[0, e] = detected
            flags[1, e] = triggered
            flags[2, e] = delivered
            flags[3, e] = fuse
            fresh = delivered and cached and known[e]
            if not (fuse and (inflation > 1.0 or fresh)):
                break
            if inflation > 1.0:
                for a in range(3):
                    for c in range(3):
                        Pinf[a, c] = Pi[a, c] * inflation
                Pi = Pinf
            if fresh:  # a delivered message carries j's current estimate: fuse with that
                xr0 = xj0
                xr1 = xj1
                Pr = Pj
        if not fuse:
            continue
        if beyond is not None and fusion_code == CI:  # covariance intersection (kernels_fusion)
            range_bearing_jacobians_into(xi0, xi1, xj0, xj1, Hi, Hj)
            if not ci_update(
                x, i, xi0, xi1, xi2, Pi, Pj, nu0, nu1, S00, S01, S11, Pxz, linearized, Hi, Hj,
                re00, re01, re11, R, fusion, jitter, K, A3, T3, Pn,
            ):  # fmt: skip
                return NOT_PD
        elif beyond is not None and fusion_code == SPLIT_CI:  # split CI (kernels_split)
            range_bearing_jacobians_into(xi0, xi1, xj0, xj1, Hi, Hj)
            if not split_ci_update(
                x, e, i, xi0, xi1, xi2, Pi, Pj, nu0, nu1, S00, S01, S11, Pxz, linearized, Hi,
                Hj, re00, re01, re11, R, fusion, jitter, K, A3, T3, Pn,
            ):  # fmt: skip
                return NOT_PD
        else:
            # Kalman gain K = P^xz S^-1 by the Cholesky factor of S (twin: kalman_gain)
            for a in range(3):
                k0, k1 = solve2(l00, l10, l11, Pxz[a, 0], Pxz[a, 1])
                K[a, 0] = k0
                K[a, 1] = k1
            x[i, 0] = xi0 + (K[0, 0] * nu0 + K[0, 1] * nu1)
            x[i, 1] = xi1 + (K[1, 0] * nu0 + K[1, 1] * nu1)
            x[i, 2] = wrap(xi2 + (K[2, 0] * nu0 + K[2, 1] * nu1))
            if linearized and not correlated:  # Joseph form (EKF)
                joseph_update(Pi, K, Hi, re00, re01, re11, A3, T3, Pn)
            else:  # (the correlated joint's moments carry no Jacobian: P - K S K^T)
                schur_update(Pi, K, S00, S01, S11, Pn)
            if beyond is not None and correlated:  # tracked: Pn becomes the joint's P_i
                joint_record(
                    joint, e, first, fused, i, xi0, xi1, xj0, xj1, K, R, Hi, Hj, G3, T3, Pn
                )
        if store_covariance(P, i, Pn, T3):
            flags[4, e] = True
        if beyond is not None and record_gauge:
            gauge_record(gauge, e, first, fused, i, xi0, xi1, xj0, xj1, K, R, Hi, Hj, G3, T3)
    return OK


stamp_with_pieces(
    correct_links,
    _kernels_math,
    _kernels_points,
    _kernels_detection,
    _kernels_defence,
    _kernels_fusion,
    _kernels_ci_weight,
    _kernels_ci_update,
    _kernels_gauge,
    _kernels_joint_links,
    _kernels_joint_records,
    _kernels_split,
    _kernels_tamper,
    _kernels_zone,
    _kernels_zone_verdicts,
)

# The link's pieces by public names, for the loop over rounds (resloc.cl.kernels_rounds),
# which runs the same decisions and update lane by lane.
innovation_norm_of_link = _innovation_norm
event_threshold_of_link = _event_threshold
gate_link = _gate_link
decide_link = _decide_link
cached_decision = _cached_decision
linearized_moments = _linearized_moments  # (and for the summed update, kernels_summed)
