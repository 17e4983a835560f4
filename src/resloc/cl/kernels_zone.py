"""Compiled twin of zone-aware trust (:mod:`resloc.cl.detection_zone`).

The stage decides per link, at the observer's *running* estimate (a robot's earlier links
of the step may have moved it across a zone's edge), whether the link is

* ``OUTSIDE``: the observer's estimate is outside the map; the other stages judge it;
* ``SUBSTITUTED``: the observer is inside, its partner's transmitted estimate is outside
  and the partner's reading of the pair is finite: the link's moments and innovation become
  the partner's position fix of the observer (:func:`position_fix_of_link`), which the
  other stages judge and the update fuses (the redundancy stages neither judge nor store
  it: :func:`resloc.cl.detection_redundancy.RedundancyCheck.discard`);
* ``WITHHELD``: inside, with no trusted partner reading: discarded, and no other stage sees
  it (no CUSUM, robot CUSUM or recovery statistic changes).

The decision is made inside the link loops, where the running estimate is: in row order
(:func:`resloc.cl.kernels_links.correct_links`, :func:`zone_verdict` then
:func:`position_fix_of_link` on both passes of a link) and in the rounds
(:func:`resloc.cl.kernels_rounds.correct_rounds`, :func:`zone_lanes` after the vectorized
update and again after the recovery's inflated second pass, :func:`withhold_lanes` after
the decisions). Both write each row's verdict into :attr:`KernelZone.verdict`, which the
stages that run after it read (``detect_link``, ``screen_lanes``) and which the dispatch
reads after the loop: the redundancy pre-pass (:mod:`resloc.cl.kernels_redundancy`)
writes every link's sequence-test state before the loop, and :func:`keep_unjudged_state`
puts the withheld and substituted links' state back, as the reference stores only the
rows its stages judged.

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
:func:`restore_unjudged`       ``_restore`` (the pre-passes' state of the rows not judged)
:func:`zone_links`             the head of ``resloc.cl.step._correct_reference`` (the
                               partners' readings)
:func:`partner_readings`       the same without a tamper hook
                               (:func:`~resloc.cl.detection_zone.reciprocal_rows`)
:func:`zone_rows`              the same into new arrays, with the verdicts' array
=============================  ==========================================================

The fix is a linear measurement of the observer's position, so the kernels cover it for the
Kalman update of the naive fusion only (``ZoneTrust.kernel_refusal`` names the rest).

The lane stages are inlined into the rounds (``jit_inline``): called, each passed its ~15
arrays per round, they cost 0.5 us a call in reference counts (measured: the rounds' step
121 -> 115 us with the stage on and an empty map, 98 us with it off).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np

from resloc.cl.detection_zone import materialize_with_reciprocal
from resloc.cl.kernels_lanes import FALLBACK
from resloc.cl.kernels_math import jit, jit_inline, lower_bound, per_params
from resloc.cl.links import LinkBatch
from resloc.cl.params import CLParams

__all__ = [
    "OUTSIDE",
    "SUBSTITUTED",
    "WITHHELD",
    "KernelZone",
    "inside_disc",
    "inside_map",
    "keep_unjudged_state",
    "no_zone",
    "partner_readings",
    "position_fix_of_link",
    "restore_unjudged",
    "withhold_lanes",
    "zone_lanes",
    "zone_links",
    "zone_rows",
    "zone_state",
    "zone_verdict",
]

#: A row's verdict (:attr:`KernelZone.verdict`).
OUTSIDE = 0
WITHHELD = 1
SUBSTITUTED = 2
#: ``zone_lanes``'s status when every lane is done (the loops' ``OK``).
_OK = 0


class KernelZone(NamedTuple):
    """Zone-aware trust as the link loops take it (a stage that is off: ``on`` False and
    empty arrays, never read)."""

    on: bool
    discs: np.ndarray  # (Z, 3): centre x, y and radius of each distrusted disc (m)
    z_reciprocal: np.ndarray  # (E, 2) the partner's range and bearing of the pair (nan: none)
    verdict: np.ndarray  # (E,) int64, written by the loop: OUTSIDE, WITHHELD or SUBSTITUTED


_NO_ZONE: list = []


def no_zone() -> KernelZone:
    """The stage switched off (built once: the loops only read it)."""
    if not _NO_ZONE:
        _NO_ZONE.append(
            KernelZone(False, np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, np.int64))
        )
    return _NO_ZONE[0]


class ZoneState(NamedTuple):
    """:func:`zone_state`'s result: the loops' :class:`KernelZone`."""

    kernel: KernelZone


@per_params
def _discs(params: CLParams) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(params.zone_trust_map, float).reshape(-1, 3))


def zone_state(
    filt, x, P, links: LinkBatch, params: CLParams, strategy, memory
) -> tuple[LinkBatch, ZoneState] | None:
    """The stage for the links of one step: ``links`` as the kernel reads them (an
    adversary's hook applied, :func:`zone_links`) and the stage's state. Without a hook and
    without the partners' readings, these are gathered by one compiled pass
    (:func:`zone_rows`). None when the readings are not ``(E, 2)`` (the reference path
    then raises the explanatory error)."""
    E = len(links)
    if links.z_reciprocal is None and links.tamper is None:
        z = np.ascontiguousarray(links.z, dtype=float)
        if z.shape == (E, 2):
            li = np.ascontiguousarray(links.i, dtype=np.int64)
            lj = np.ascontiguousarray(links.j, dtype=np.int64)
            found, z_rec, verdict = zone_rows(li, lj, z)
            if found:  # (else rows not sorted by observer: the reference's way)
                return links, ZoneState(KernelZone(True, _discs(params), z_rec, verdict))
    links = zone_links(filt, x, P, links, params, strategy, memory)
    z_rec = links.z_reciprocal
    if z_rec is None or np.shape(z_rec) != (E, 2):
        return None
    kernel = KernelZone(
        True,
        _discs(params),
        np.ascontiguousarray(z_rec, dtype=float),
        np.zeros(E, np.int64),
    )
    return links, ZoneState(kernel)


def zone_links(filt, x, P, links: LinkBatch, params: CLParams, strategy, memory) -> LinkBatch:
    """``links`` with every partner's reading (``z_reciprocal``), as the reference's
    correction attaches them when the batch carries none: an adversary's tamper hook applied
    to every row at the predicted estimates (``x: (B, 3)``, ``P: (B, 3, 3)``; its moments by
    the fusion ``strategy``, only when there is a hook: they reach nothing else), then the
    hook's ``reported`` readings of the partners. A batch that carries them is returned as
    it is. Twin: the head of ``resloc.cl.step._correct_reference``."""
    if links.z_reciprocal is not None:
        return links
    tamper = links.tamper
    if tamper is None:
        E = len(links)
        return materialize_with_reciprocal(links, np.zeros((E, 2)), np.zeros((E, 2, 2)))
    pre = strategy.moments(
        filt, memory, x[links.i], P[links.i], links.x_nb, links.P_nb, links.i, links.j,
        params.R,
    )  # fmt: skip
    reported = getattr(tamper, "reported", None)
    links = materialize_with_reciprocal(links, pre.z_hat, pre.S)
    if reported is not None:
        links = dataclasses.replace(links, z_reciprocal=reported(links.z_reciprocal))
    return links


def keep_unjudged_state(state: ZoneState, fixes, li, lj) -> None:
    """After a compiled step: the state the pre-passes keep per link (the redundancy
    sequence test's, the reciprocal check's) of the withheld and substituted links back to
    what it was before the step (the reference stores the state of the rows its stages
    judged only: ``RedundancySequence.discard``, ``ReciprocalCheck.discard``). ``fixes``:
    the pre-passes' verdicts (:class:`~resloc.cl.kernels_detection.PrepassVerdict` of
    each; None: not run), whose saved
    store entries (:func:`~resloc.cl.kernels_detection.store_slots`) hold the state before
    them: a copy of the old values, or, when the step inserted links, the old keys and
    values."""
    verdict = state.kernel.verdict
    rows = None
    for fix in fixes:
        for saved in () if fix is None else fix.state.saved[:1]:
            store, _, _, slots, old = saved
            values = store.values
            if old is not None and values.ndim == 2:
                # the steady state: one compiled pass, no index arrays (restore_unjudged;
                # the stores' values are contiguous: kernels_detection.store_slots)
                restore_unjudged(verdict, slots, values, old)
                RESTORE_RUNS["compiled"] += 1
                continue
            if rows is None:
                rows = np.flatnonzero(verdict != OUTSIDE)
            if rows.size:
                _restore(saved, rows, li, lj)


#: How often :func:`keep_unjudged_state` restored a store by the compiled pass (the tests
#: read it).
RESTORE_RUNS = {"compiled": 0}


def _restore(saved: tuple, rows: np.ndarray, li: np.ndarray, lj: np.ndarray) -> None:
    """One store's entries at ``rows`` back to their values in ``saved``."""
    store, keys, values, slots, old = saved
    if old is not None:  # every link known, values kept in place
        at = slots[rows]
        store.values[at] = old[at]
        return
    # links inserted this step: their old values from the old arrays (0: never stored)
    wanted = li[rows] * store.n_nodes + lj[rows]
    before = np.zeros((rows.size, *store.values.shape[1:]))
    if len(keys):
        pos = np.minimum(np.searchsorted(keys, wanted), len(keys) - 1)
        hit = keys[pos] == wanted
        before[hit] = values[pos[hit]]
    store.values[slots[rows]] = before


# ---------------------------------------------------------------------------------------
# Compiled pieces
# ---------------------------------------------------------------------------------------
@jit
def partner_readings(li, lj, z, out):
    """Per row ``e`` of link ``(i, j)``: the reading ``z`` of the row of link ``(j, i)`` into
    ``out[e]`` (``nan`` where the batch holds none; the first such row where several).
    Rows sorted by observer (False otherwise, ``out`` then partial). Twin:
    :func:`~resloc.cl.detection_zone.reciprocal_rows` and the partner's reading of
    :func:`~resloc.cl.detection_zone.materialize_with_reciprocal` (no tamper hook)."""
    E = li.shape[0]
    for e in range(1, E):
        if li[e] < li[e - 1]:
            return False
    top = -1
    low = 0
    for e in range(E):
        top = max(top, max(li[e], lj[e]))
        low = min(low, min(li[e], lj[e]))
    T = top + 1
    if low >= 0 and T <= 4 * E + 64 and T * T <= 16 * E + 1024:
        # ids of a team (small non-negative integers): a table of every pair's row, one
        # write and one read a row (the walks below: 2.5 us for a step's 260 rows, 1.0)
        pair = np.full(T * T, -1, np.int64)
        for e in range(E - 1, -1, -1):  # (the first row of a pair wins, as below)
            pair[li[e] * T + lj[e]] = e
        for e in range(E):
            r = pair[lj[e] * T + li[e]]
            out[e, 0] = z[r, 0] if r >= 0 else math.nan
            out[e, 1] = z[r, 1] if r >= 0 else math.nan
        return True
    # the first row of each observer id, one walk over the rows (in place of a binary
    # search per row: half of the pass), where the ids are small non-negative integers
    table = low >= 0 and top < 4 * E + 64
    first = np.empty(top + 2 if table else 0, np.int64)
    if table:
        p = 0
        for r in range(top + 2):
            while p < E and li[p] < r:
                p += 1
            first[r] = p
    for e in range(E):
        j = lj[e]
        if table:
            lo = first[j]
        else:  # binary search of the sorted observers
            lo = lower_bound(li, j, 0, E)
        out[e, 0] = math.nan
        out[e, 1] = math.nan
        while lo < E and li[lo] == j:
            if lj[lo] == li[e]:
                out[e, 0] = z[lo, 0]
                out[e, 1] = z[lo, 1]
                break
            lo += 1
    return True


@jit
def zone_rows(li, lj, z):
    """:func:`partner_readings` into a new ``(E, 2)`` array, with the stage's verdicts
    ``(E,)`` int64 (``OUTSIDE``) beside it: ``(sorted, z_rec, verdict)``. The glue's
    numpy calls (the two arrays' allocations, ~0.2 us each) in the compiled call."""
    E = li.shape[0]
    z_rec = np.empty((E, 2))
    verdict = np.zeros(E, np.int64)
    return partner_readings(li, lj, z, z_rec), z_rec, verdict


@jit
def restore_unjudged(verdict, slots, values, old):
    """``values[slots[e]] = old[slots[e]]`` on every row ``e`` whose ``verdict`` is not
    ``OUTSIDE`` (``values``, ``old``: ``(K, w)``). Twin: ``_restore`` (the steady state's
    fancy indexing)."""
    for e in range(verdict.shape[0]):
        if verdict[e] != OUTSIDE:
            k = slots[e]
            for c in range(values.shape[1]):
                values[k, c] = old[k, c]


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
