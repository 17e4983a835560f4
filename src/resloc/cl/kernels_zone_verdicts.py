"""Zone-aware trust's decisions inside the compiled link loops (the stage:
:mod:`resloc.cl.kernels_zone`): each row's verdict at the observer's *running* estimate
(:data:`OUTSIDE`, :data:`WITHHELD` or :data:`SUBSTITUTED`) and, for a substituted row, the
partner's position fix of the observer that takes the reading's place.

In row order (:func:`resloc.cl.kernels_links.correct_links`) :func:`zone_verdict` then
:func:`position_fix_of_link` on both passes of a link; in the rounds
(:func:`resloc.cl.kernels_rounds.correct_rounds`) :func:`zone_lanes` after the vectorized
update and again after the recovery's inflated second pass, :func:`withhold_lanes` after
the decisions. Each writes the row's verdict into
:attr:`~resloc.cl.kernels_zone.KernelZone.verdict`.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`inside_map`             :func:`~resloc.cl.detection_zone.inside_zone_map`
                               (:func:`inside_disc`: one disc)
:func:`zone_verdict`           :func:`~resloc.cl.detection_zone.substitute_reciprocal` and
                               ``ZoneTrust.discard`` (written out in :func:`zone_lanes`)
:func:`position_fix_of_link`   :func:`~resloc.cl.detection_zone.reciprocal_position_fix`
:func:`zone_lanes`             the ``position_fixes`` of ``resloc.cl.step._decide`` and the
                               Kalman update of the fix
:func:`withhold_lanes`         :func:`resloc.cl.detection.detect` (the withheld rows)
=============================  ==========================================================

The fix is a linear measurement of the observer's position, so the kernels cover it for the
Kalman update of the naive fusion only (``ZoneTrust.kernel_refusal`` names the rest).

The lane stages are inlined into the rounds (``jit_inline``): called, each passed its ~15
arrays per round, they cost 0.5 us a call in reference counts (measured: the rounds' step
121 -> 115 us with the stage on and an empty map, 98 us with it off).
"""

from __future__ import annotations

import math

from resloc.cl.kernels_lanes import FALLBACK
from resloc.cl.kernels_math import jit_inline

__all__ = [
    "OUTSIDE",
    "SUBSTITUTED",
    "WITHHELD",
    "inside_disc",
    "inside_map",
    "position_fix_of_link",
    "withhold_lanes",
    "zone_lanes",
    "zone_verdict",
]

#: A row's verdict (:attr:`~resloc.cl.kernels_zone.KernelZone.verdict`).
OUTSIDE = 0
WITHHELD = 1
SUBSTITUTED = 2
#: ``zone_lanes``'s status when every lane is done (the loops' ``OK``).
_OK = 0


@jit_inline
def inside_disc(px, py, cx, cy, r):
    """Whether ``(px, py)`` lies inside (or on) the disc of centre ``(cx, cy)`` and radius
    ``r``: ``hypot(px - cx, py - cy) - r <= 0``. Scalars only: a loop over lanes that
    passes an array to a function, even an inlined one, pays a reference count up and
    down (two atomic operations) per call."""
    dx = px - cx
    dy = py - cy
    # clearly outside or inside by the squares (exact to a few ulps: a margin of 1e-9
    # leaves no doubt where neither under- nor overflows), else by hypot itself; one
    # libm call a lane was a tenth of the stage
    d2 = dx * dx + dy * dy
    r2 = r * r
    if r > 0.0 and 1e-280 < d2 < 1e280 and 1e-280 < r2 < 1e280:
        if d2 > r2 * (1.0 + 1e-9):
            return False
        if d2 < r2 * (1.0 - 1e-9):
            return True
    return math.hypot(dx, dy) - r <= 0.0


@jit_inline
def inside_map(discs, px, py):
    """Whether ``(px, py)`` lies inside (or on) a disc of ``discs: (Z, 3)``
    (:func:`inside_disc`). Twin: :func:`~resloc.cl.detection_zone.inside_zone_map`."""
    for k in range(discs.shape[0]):
        if inside_disc(px, py, discs[k, 0], discs[k, 1], discs[k, 2]):
            return True
    return False


@jit_inline
def zone_verdict(zone, e, xi0, xi1, xj0, xj1):
    """Row ``e``'s verdict from its observer's running position ``(xi0, xi1)`` and its
    partner's transmitted one ``(xj0, xj1)``, stored in ``zone.verdict[e]`` and returned.
    Twin: :func:`~resloc.cl.detection_zone.substitute_reciprocal` and
    ``ZoneTrust.discard``."""
    discs = zone[1]
    z_rec = zone[2]
    verdict = OUTSIDE
    if inside_map(discs, xi0, xi1):
        verdict = WITHHELD
        finite = math.isfinite(z_rec[e, 0]) and math.isfinite(z_rec[e, 1])
        if finite and not inside_map(discs, xj0, xj1):
            verdict = SUBSTITUTED
    zone[3][e] = verdict
    return verdict


@jit_inline
def position_fix_of_link(xi0, xi1, Pi, f, xj0, xj1, xj2, Pj, r, b, R, Pxz, Hi):
    """Robot i's position as its partner j measured it (range ``r``, bearing ``b`` of i
    from j's pose ``(xj0, xj1, xj2)`` with covariance ``Pj``), a linear measurement of i's
    position: ``H = [I_2 0]`` into ``Hi``, ``P^xz = f P_i[:, :2]`` into ``Pxz`` (``f``: the
    recovery's inflation of ``P_i``, 1 without), and ``(nu0, nu1, S00, S01, S11, C00, C01,
    C11)``: the innovation ``p_fix - p_i`` (not an angle: never wrapped), ``S = f P_i,pos
    + C`` symmetrized and ``C = J_j P_j J_j^T + J_z R J_z^T`` (the ``R_eff`` of the EKF's
    Joseph form; its off-diagonal entry the mean of the two). Twin:
    :func:`~resloc.cl.detection_zone.reciprocal_position_fix` (same products, same
    order)."""
    a = xj2 + b
    c = math.cos(a)
    s = math.sin(a)
    g0 = -r * s  # J_j = [[1, 0, g0], [0, 1, g1]]
    g1 = r * c
    # A = J_j P_j (2 x 3), then A J_j^T
    a00 = Pj[0, 0] + g0 * Pj[2, 0]
    a01 = Pj[0, 1] + g0 * Pj[2, 1]
    a02 = Pj[0, 2] + g0 * Pj[2, 2]
    a10 = Pj[1, 0] + g1 * Pj[2, 0]
    a11 = Pj[1, 1] + g1 * Pj[2, 1]
    a12 = Pj[1, 2] + g1 * Pj[2, 2]
    j00 = a00 + a02 * g0
    j01 = a01 + a02 * g1
    j10 = a10 + a12 * g0
    j11 = a11 + a12 * g1
    # J_z = [[c, g0], [s, g1]]; B = J_z R, then B J_z^T
    b00 = c * R[0, 0] + g0 * R[1, 0]
    b01 = c * R[0, 1] + g0 * R[1, 1]
    b10 = s * R[0, 0] + g1 * R[1, 0]
    b11 = s * R[0, 1] + g1 * R[1, 1]
    C00 = j00 + (b00 * c + b01 * g0)
    C01 = j01 + (b00 * s + b01 * g1)
    C10 = j10 + (b10 * c + b11 * g0)
    C11 = j11 + (b10 * s + b11 * g1)
    S00 = Pi[0, 0] * f + C00
    S01 = 0.5 * ((Pi[0, 1] * f + C01) + (Pi[1, 0] * f + C10))
    S11 = Pi[1, 1] * f + C11
    for k in range(3):
        Pxz[k, 0] = Pi[k, 0] * f
        Pxz[k, 1] = Pi[k, 1] * f
        Hi[0, k] = 1.0 if k == 0 else 0.0
        Hi[1, k] = 1.0 if k == 1 else 0.0
    nu0 = (xj0 + r * c) - xi0
    nu1 = (xj1 + r * s) - xi1
    return nu0, nu1, S00, S01, S11, C00, 0.5 * (C01 + C10), C11


@jit_inline
def zone_lanes(
    zone, x_nb, P_nb, P, obs, src, lane_e, n, xi, update, inflation, decision, retried, R,
    Pxz, Hi,
):  # fmt: skip
    """The rounds' lanes (one link each): with ``retried`` False, every lane's verdict
    (:func:`zone_verdict`, at the lane's running estimate ``xi``) and, on a substituted
    lane, the ``update`` rows (:func:`~resloc.cl.kernels_link_stages.kalman_lanes`'s
    layout) of the partner's position fix in place of the reading's; with ``retried`` True,
    the fix again from ``f P_i`` on the substituted lanes the recovery re-admitted with
    ``f = inflation[c] > 1`` and that are delivered (after ``inflated_moments``). ``x_nb``,
    ``P_nb``: the transmitted estimates (rows ``src``); ``Pxz``, ``Hi``: scratch. Returns
    ``FALLBACK`` where the fix's ``S`` needs jitter (the row-order loop then runs the step),
    else 0. Twin: the zone blocks of ``correct_links`` (the Kalman update: ``kalman_lanes``'s
    operations)."""
    # the stage's arrays taken out of the tuple once, and the verdict (zone_verdict's)
    # written out below with no array passed to a function: per lane, each take or pass
    # of an array was a reference count up and down, ~20 us a step for 260 lanes
    discs = zone[1]
    z_rec = zone[2]
    verdict = zone[3]
    Z = discs.shape[0]
    for c in range(n):
        e = lane_e[c]
        s = src[c]
        f = 1.0
        if retried:
            if not (verdict[e] == SUBSTITUTED and inflation[c] > 1.0 and decision[3, c] == 1.0):
                continue
            f = inflation[c]
        else:
            v = OUTSIDE
            for k in range(Z):  # inside_map at the lane's running estimate
                if inside_disc(xi[0, c], xi[1, c], discs[k, 0], discs[k, 1], discs[k, 2]):
                    v = WITHHELD
                    break
            if v == WITHHELD and math.isfinite(z_rec[e, 0]) and math.isfinite(z_rec[e, 1]):
                v = SUBSTITUTED  # unless the partner's transmitted position is inside
                for k in range(Z):
                    if inside_disc(x_nb[s, 0], x_nb[s, 1], discs[k, 0], discs[k, 1], discs[k, 2]):
                        v = WITHHELD
                        break
            verdict[e] = v
            if v != SUBSTITUTED:
                continue
        i = obs[c]
        Pi = P[i]
        nu0, nu1, s00, s01, s11, _c00, _c01, _c11 = position_fix_of_link(
            xi[0, c], xi[1, c], Pi, f, x_nb[s, 0], x_nb[s, 1], x_nb[s, 2], P_nb[s],
            z_rec[e, 0], z_rec[e, 1], R, Pxz, Hi,
        )  # fmt: skip
        # chol2's first level (eps = 0), as kalman_lanes
        if not (math.isfinite(s00) and math.isfinite(s01) and math.isfinite(s11) and s00 > 0.0):
            return FALLBACK
        l00 = math.sqrt(s00)
        l10 = s01 / l00
        q = s11 - l10 * l10
        if not q > 0.0:
            return FALLBACK
        l11 = math.sqrt(q)
        # K = P^xz S^-1 row by row (solve2's operations)
        y0 = Pxz[0, 0] / l00
        k01 = ((Pxz[0, 1] - l10 * y0) / l11) / l11
        k00 = (y0 - l10 * k01) / l00
        y0 = Pxz[1, 0] / l00
        k11 = ((Pxz[1, 1] - l10 * y0) / l11) / l11
        k10 = (y0 - l10 * k11) / l00
        y0 = Pxz[2, 0] / l00
        k21 = ((Pxz[2, 1] - l10 * y0) / l11) / l11
        k20 = (y0 - l10 * k21) / l00
        # f P_i - K S K^T (schur_update), then symmetrized
        t00 = k00 * s00 + k01 * s01
        t01 = k00 * s01 + k01 * s11
        t10 = k10 * s00 + k11 * s01
        t11 = k10 * s01 + k11 * s11
        t20 = k20 * s00 + k21 * s01
        t21 = k20 * s01 + k21 * s11
        n00 = Pi[0, 0] * f - (t00 * k00 + t01 * k01)
        n01 = Pi[0, 1] * f - (t00 * k10 + t01 * k11)
        n02 = Pi[0, 2] * f - (t00 * k20 + t01 * k21)
        n10 = Pi[1, 0] * f - (t10 * k00 + t11 * k01)
        n11 = Pi[1, 1] * f - (t10 * k10 + t11 * k11)
        n12 = Pi[1, 2] * f - (t10 * k20 + t11 * k21)
        n20 = Pi[2, 0] * f - (t20 * k00 + t21 * k01)
        n21 = Pi[2, 1] * f - (t20 * k10 + t21 * k11)
        n22 = Pi[2, 2] * f - (t20 * k20 + t21 * k21)
        p00 = 0.5 * (n00 + n00)
        p01 = 0.5 * (n01 + n10)
        p02 = 0.5 * (n02 + n20)
        p11 = 0.5 * (n11 + n11)
        p12 = 0.5 * (n12 + n21)
        p22 = 0.5 * (n22 + n22)
        m2 = p00 * p11 - p01 * p01
        det = (
            p00 * (p11 * p22 - p12 * p12)
            - p01 * (p01 * p22 - p12 * p02)
            + p02 * (p01 * p12 - p11 * p02)
        )
        pd = (p00 > 0.0) and (m2 > 0.0) and (det > 0.0) and math.isfinite(det)
        update[0, c] = nu0
        update[1, c] = nu1
        update[2, c] = l00
        update[3, c] = l10
        update[4, c] = l11
        update[5, c] = k00 * nu0 + k01 * nu1
        update[6, c] = k10 * nu0 + k11 * nu1
        update[7, c] = k20 * nu0 + k21 * nu1
        update[8, c] = p00
        update[9, c] = p01
        update[10, c] = p02
        update[11, c] = p11
        update[12, c] = p12
        update[13, c] = p22
        update[14, c] = 1.0 if pd else 0.0
        update[15, c] = 0.0
        update[16, c] = k00
        update[17, c] = k01
        update[18, c] = k10
        update[19, c] = k11
        update[20, c] = k20
        update[21, c] = k21
    return _OK


@jit_inline
def withhold_lanes(zone, lane_e, n, decision, inflation):
    """The withheld lanes discarded (after the decisions): detected, neither triggered nor
    delivered, no inflation. Twin: :func:`resloc.cl.detection.detect` (its withheld
    rows)."""
    verdict = zone[3]
    for c in range(n):
        if verdict[lane_e[c]] == WITHHELD:
            decision[1, c] = 1.0
            decision[2, c] = 0.0
            decision[3, c] = 0.0
            inflation[c] = 1.0
