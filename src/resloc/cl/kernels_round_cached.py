"""The ``cached`` neighbour estimates in the link rounds
(:func:`resloc.cl.kernels_rounds.correct_rounds`).

With ``cached`` estimates a link's first pass uses ``j``'s last received estimate (the
per-link rows ``x_ref``, ``P_ref`` :func:`resloc.cl.kernels._cached_rows` gathers), the
trigger fires at a link's first reception, an accepted untriggered link may be fused with
the cached estimate (``update_without_transmission``), and a delivered message is fused
with the estimate it carries: a second pass with the transmitted rows ``x_nb``, ``P_nb``,
which :func:`~resloc.cl.kernels_round_stages.inflated_moments` runs beside the recovery's.

=========================  =============================================================
function                   piece of ``correct_links``
=========================  =============================================================
:func:`cached_lanes`       ``_cached_decision``, ``fresh``
:func:`fresh_moments`      ``attempt == 1`` with the transmitted estimate (``f = 1``)
:func:`transmitted_lanes`  ``xj0``, ``xj1`` (the update stages' ``j``)
:func:`sent_lanes`         the ``delivered`` flag
=========================  =============================================================

A delivered link needs its moments twice (decide on the cached estimate, fuse the fresh
one), and about a third of a step's links are delivered (the paper's scenario: 88 of 260):
:func:`fresh_moments` runs their second pass with the rounds' SIMD stages on the delivered
lanes gathered into lanes of their own (the robot's estimate and the factor of ``P_i`` are
the first pass's; the factor of ``P_j`` and the points are new), where
:func:`~resloc.cl.kernels_round_stages.inflated_moments` would run the row-order loop's
scalar pieces lane by lane (measured: that scalar pass was about a third of the option's
cost over the default). The lanes the recovery also inflates (``f > 1``, rare) are left to
``inflated_moments``.
"""

from __future__ import annotations

import numpy as np

from resloc.cl import kernels_lanes as _kernels_lanes
from resloc.cl import kernels_link_stages as _kernels_link_stages
from resloc.cl import kernels_links as _kernels_links
from resloc.cl import kernels_math as _kernels_math
from resloc.cl.kernels_lanes import FALLBACK
from resloc.cl.kernels_link_stages import (
    UPDATE_ROWS,
    chol_jitter_lanes,
    chol_lanes,
    gather_lanes,
    kalman_lanes,
    load_covariances,
    load_robot_covariances,
    moment_scratch,
    moments_lanes,
    points_lanes,
)
from resloc.cl.kernels_links import NOT_PD, OK, cached_decision
from resloc.cl.kernels_math import jit_lanes, stamp_with_pieces

_jit = jit_lanes

__all__ = [
    "FRESH_DONE",
    "cached_lanes",
    "fresh_moments",
    "fresh_scratch",
    "sent_lanes",
    "transmitted_lanes",
]

#: ``fresh[c]`` of a lane whose second pass :func:`fresh_moments` ran (1.0: still to run,
#: by ``inflated_moments``; 0.0: none).
FRESH_DONE = 2.0


@_jit
def cached_lanes(lane_e, n, known, channel_ok, options, decision, sent, fresh):
    """The decisions of ``cached`` neighbour estimates per lane: the trigger fires at a
    link's first reception, and with ``update_without_transmission`` an accepted,
    untriggered link with a cached estimate is fused with it. Rewrites ``decision``'s
    ``triggered`` and, in place of ``delivered``, ``fused`` (what the later stages fuse);
    ``sent``: delivered; ``fresh``: 1.0 where delivered with a cached estimate (the second
    pass then fuses the transmitted one, :func:`inflated_moments`). Twin: the
    ``_cached_decision`` call and ``fresh`` of ``correct_links``."""
    trigger, update_without_transmission = options[3], options[10]
    for c in range(n):
        e = lane_e[c]
        triggered, delivered, fused = cached_decision(
            decision[1, c] == 1.0, decision[2, c] == 1.0, decision[3, c] == 1.0, known[e],
            trigger, channel_ok[e], update_without_transmission,
        )  # fmt: skip
        decision[2, c] = 1.0 if triggered else 0.0
        decision[3, c] = 1.0 if fused else 0.0
        sent[c] = 1.0 if delivered else 0.0
        fresh[c] = 1.0 if delivered and known[e] else 0.0


@_jit
def fresh_scratch(C, m):
    """The working arrays of :func:`fresh_moments` for ``C`` lanes (``CHUNK``, what
    ``kalman_lanes`` takes) and ``m`` sigma points: the first pass's lane of each column,
    :func:`~resloc.cl.kernels_link_stages.moment_scratch`, ``P_i`` by lane, the update,
    and two 3 x 3 matrices for the Cholesky jitter."""
    return (
        np.empty(C, np.int64),
        moment_scratch(C, m),
        np.empty((9, C)),
        np.empty((UPDATE_ROWS, C)),
        np.empty((3, 3)),
        np.empty((3, 3)),
    )


@_jit
def fresh_moments(
    x, li, nb, x_nb, P_nb, z, lane_e, n, decision, inflation, fresh, zl, Li, moments, pxz, update,
    axis, value, Wm, Wc, circular, R, jitter, P, scratch,
):  # fmt: skip
    """The second pass of the lanes delivered with a cached estimate (``fresh[c] == 1``,
    fused: ``decision[3]``, not inflated by the recovery: ``inflation[c] == 1``): the
    moments with j's transmitted estimate (``x_nb``, ``P_nb`` by link, as ``cached`` passes
    them), by the SIMD stages on those lanes gathered into ``scratch``'s
    (:func:`fresh_scratch`), then the innovation and Kalman update
    (``kalman_lanes``), written over the lanes' ``moments``, ``pxz`` and ``update``;
    ``fresh[c]`` becomes :data:`FRESH_DONE`. Robot i's estimate ``x`` is the first pass's
    (nothing is applied in between), so is the factor ``Li`` of ``P_i``, and the
    measurement ``zl`` (the attacker's, where it tampered). Returns ``OK``, ``NOT_PD``
    (``P_j`` has no factor) or ``FALLBACK`` (a special case of the row-order loop). Twin:
    ``attempt == 1`` of ``correct_links`` with ``fresh`` (the scalar pieces of
    ``inflated_moments``)."""
    lane, work, Pi, upd, scratch_in, scratch_out = scratch
    (lane_k, obs, src, xi, xr, zk, sin_cos, Lik, Ljk, cov, _ok_i, ok_j, bad, Z0, Z1, sums,
     mom, pxz_k, mean) = work  # fmt: skip
    k = np.int64(0)  # not the literal 0 (see kernels_rounds._rounds)
    for c in range(n):
        if decision[3, c] == 1.0 and fresh[c] == 1.0 and inflation[c] == 1.0:
            lane[k] = c
            lane_k[k] = lane_e[c]
            k += 1
    if k == 0:
        return OK
    # (cached: x_nb, P_nb are per link, nb the identity)
    gather_lanes(x, li, nb, x_nb, z, lane_k, k, obs, src, xi, xr, zk, sin_cos, bad)
    for t in range(k):
        c = lane[t]
        zk[0, t] = zl[0, c]
        zk[1, t] = zl[1, c]
        for a in range(3):
            for b in range(a + 1):
                Lik[a, b, t] = Li[a, b, c]
    load_covariances(P_nb, src, k, cov)
    chol_lanes(cov, k, Ljk, ok_j)
    if not chol_jitter_lanes(P_nb, src, k, Ljk, ok_j, jitter, scratch_in, scratch_out):
        return NOT_PD
    points_lanes(axis, value, Wm, k, xi, xr, sin_cos, Lik, Ljk, Z0, Z1, sums, bad)
    moments_lanes(axis, value, Wm, Wc, circular, k, Lik, Z0, Z1, sums, mom, pxz_k, mean, bad)
    load_robot_covariances(P, obs, k, Pi)
    kalman_lanes(k, zk, R, mom, pxz_k, Pi, upd)
    for t in range(k):
        if bad[t] != 0.0 or upd[15, t] != 0.0:
            return FALLBACK
    for t in range(k):
        c = lane[t]
        for a in range(5):
            moments[a, c] = mom[a, t]
        for a in range(6):
            pxz[a, c] = pxz_k[a, t]
        for a in range(UPDATE_ROWS):
            update[a, c] = upd[a, t]
        fresh[c] = FRESH_DONE
    return OK


@_jit
def transmitted_lanes(x_nb, src, n, xr):
    """``j``'s transmitted position per lane in ``xr`` (the update stages' Jacobians and
    records use it, whichever estimate the moments used)."""
    for c in range(n):
        s = src[c]
        xr[0, c] = x_nb[s, 0]
        xr[1, c] = x_nb[s, 1]


@_jit
def sent_lanes(lane_e, n, sent, out):
    """The ``delivered`` flags of ``cached`` lanes (:func:`cached_lanes`: ``apply_lanes``
    wrote the fused flag there too)."""
    delivered = out[2][2]
    for c in range(n):
        delivered[lane_e[c]] = sent[c] == 1.0


for _dispatcher in (
    cached_lanes,
    fresh_scratch,
    fresh_moments,
    transmitted_lanes,
    sent_lanes,
):
    stamp_with_pieces(
        _dispatcher, _kernels_math, _kernels_lanes, _kernels_link_stages, _kernels_links
    )
