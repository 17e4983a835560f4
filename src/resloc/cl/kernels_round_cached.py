"""The ``cached`` neighbour estimates in the link rounds
(:func:`resloc.cl.kernels_rounds.correct_rounds`).

With ``cached`` estimates a link's first pass uses ``j``'s last received estimate (the
per-link rows ``x_ref``, ``P_ref`` :func:`resloc.cl.kernels_inputs.cached_rows` gathers), the
trigger fires at a link's first reception, an accepted untriggered link may be fused with
the cached estimate (``update_without_transmission``), and a delivered message is fused
with the estimate it carries: a second pass with the transmitted rows ``x_nb``, ``P_nb``,
which :func:`~resloc.cl.kernels_round_stages.inflated_moments` runs beside the recovery's.

The second pass runs ahead of the decisions, in the first pass's SIMD lanes
(:func:`fresh_lanes`, :func:`take_fresh`): with ``n`` robots' lanes in a round, lanes
``n .. 2n - 1`` are the same links with j's transmitted estimate, through the same
vectorized stages (factors, points, moments, Kalman update); a lane whose link turns out
delivered takes its twin's moments and update, the others' are dropped. Measured on a
captured step of the paper's scenario (17 robots, 260 links, ~80 delivered): the lanes'
loops run their SIMD bodies on blocks of :data:`LANE_BLOCK` lanes from :data:`LANE_MIN`
lanes on, the rest lane by lane, so 40 lanes (34 padded, :func:`padded_lanes`) cost less
than 17, where the second pass lane by lane cost ~0.45 us a delivered link. A twin that
needs a special case (a factor with jitter, a point or innovation the lanes cannot take),
a re-admission on an inflated covariance, the stealthy attacker's or zone trust's changes
of the lanes, and chunks of more than ``CHUNK / 2`` robots keep the second pass of
:func:`~resloc.cl.kernels_round_stages.inflated_moments`.

=========================  =============================================================
function                   piece of ``correct_links``
=========================  =============================================================
:func:`cached_lanes`       ``_cached_decision``, ``fresh``
:func:`padded_lanes`       (how many lanes; also the joints' rounds)
:func:`lanes_ahead`        (how many lanes)
:func:`fresh_lanes`        the second pass's inputs (``attempt == 1``, ``fresh``)
:func:`fresh_covariances`  the second pass's ``P_j``
:func:`take_fresh`         the second pass's moments and update
:func:`transmitted_lanes`  ``xj0``, ``xj1`` (the update stages' ``j``)
:func:`sent_lanes`         the ``delivered`` flag
=========================  =============================================================
"""

from __future__ import annotations

from resloc.cl import kernels_links as _kernels_links
from resloc.cl import kernels_math as _kernels_math
from resloc.cl.kernels_link_stages import load_lane
from resloc.cl.kernels_links import cached_decision
from resloc.cl.kernels_math import jit_lanes, stamp_with_pieces

_jit = jit_lanes

__all__ = [
    "LANE_BLOCK",
    "LANE_MIN",
    "cached_lanes",
    "fresh_covariances",
    "fresh_lanes",
    "lanes_ahead",
    "pad_gathered",
    "padded_lanes",
    "sent_lanes",
    "take_fresh",
    "transmitted_lanes",
]


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


#: The vectorized stages' loops (points, moments, Kalman update) run their SIMD bodies on
#: blocks of this many lanes, and only from :data:`LANE_MIN` lanes on; the other lanes run
#: one by one (~0.3 us a lane through the points and moments). Measured on the bench
#: machine (AVX-512), points and moments of n lanes: 12 lanes 3.7 us, 17 lanes 3.1 us,
#: 24 lanes 2.2 us, 34 lanes 3.4 us, 40 lanes 2.6 us.
LANE_BLOCK = 8
LANE_MIN = 24


@_jit
def padded_lanes(n, C):
    """How many lanes the vectorized stages run for ``n`` lanes of work: ``n`` padded to a
    multiple of :data:`LANE_BLOCK` and to at least :data:`LANE_MIN` (at most ``C``), or
    ``n`` itself below one block (padding would cost more than it saves). The padding
    lanes are computed and never read."""
    if n < LANE_BLOCK:
        return n
    return min(C, max(LANE_MIN, (n + LANE_BLOCK - 1) // LANE_BLOCK * LANE_BLOCK))


@_jit
def pad_gathered(n, n2, obs, src, xi, xr, zl, sin_cos, bad):
    """Lanes ``n .. n2 - 1`` (``n2 = padded_lanes(n, CHUNK)``) copies of lane 0's gathered
    inputs (:func:`~resloc.cl.kernels_link_stages.gather_lanes`): work for the vectorized
    stages' SIMD bodies whose results are never read (both forms of the rounds,
    :func:`resloc.cl.kernels_rounds.correct_rounds`, unless ``cached`` runs ahead)."""
    for d in range(n, n2):
        obs[d] = obs[0]
        src[d] = src[0]
        for a in range(3):
            xi[a, d] = xi[a, 0]
        xr[0, d] = xr[0, 0]
        xr[1, d] = xr[1, 0]
        zl[0, d] = zl[0, 0]
        zl[1, d] = zl[1, 0]
        sin_cos[0, d] = sin_cos[0, 0]
        sin_cos[1, d] = sin_cos[1, 0]
        bad[d] = bad[0]


@_jit
def lanes_ahead(n, C):
    """How many lanes the vectorized stages run with ``cached``'s second pass ahead of
    ``n`` robots' lanes: ``2n`` padded (:func:`padded_lanes`); ``n`` (no lanes ahead) when
    ``2n > C``."""
    if 2 * n > C:
        return n
    return padded_lanes(2 * n, C)


@_jit
def fresh_lanes(x_nb, n, n2, obs, src, xi, xr, zl, sin_cos, bad):
    """Lanes ``n .. n2 - 1`` (``n2 = lanes_ahead(n, CHUNK)``): lane ``n + c`` (``c < n``)
    is lane ``c``'s link with j's transmitted position (``x_nb`` at row ``src[c]``), robot
    i, its estimate, the measurement, the heading's sine and cosine and ``bad`` copied from
    lane ``c``; the lanes from ``2n`` on (padding, never read) copy lane ``n``."""
    for d in range(n, n2):
        c = d - n if d < 2 * n else 0
        s = src[c]
        obs[d] = obs[c]
        src[d] = s
        xi[0, d] = xi[0, c]
        xi[1, d] = xi[1, c]
        xi[2, d] = xi[2, c]
        xr[0, d] = x_nb[s, 0]
        xr[1, d] = x_nb[s, 1]
        zl[0, d] = zl[0, c]
        zl[1, d] = zl[1, c]
        sin_cos[0, d] = sin_cos[0, c]
        sin_cos[1, d] = sin_cos[1, c]
        bad[d] = bad[c]


@_jit
def fresh_covariances(P_nb, src, n, n2, cov):
    """j's transmitted covariance of lanes ``n .. n2 - 1`` (row ``src[d]`` of ``P_nb``, as
    :func:`fresh_lanes` set it) as :func:`load_covariances
    <resloc.cl.kernels_link_stages.load_covariances>` writes lanes: the lower triangle, and
    whether all nine entries are finite."""
    for d in range(n, n2):
        load_lane(P_nb, src[d], d, cov)


@_jit
def take_fresh(n, inflation, decision, fresh, ok_j, bad, moments, pxz, update):
    """Each fused lane ``c`` whose second pass is the transmitted estimate's (``fresh[c]``,
    no inflation) takes lane ``n + c``'s moments, ``P^xz`` and update (:func:`fresh_lanes`)
    and is done (``fresh[c] = 0``); a twin whose factor needed jitter (``ok_j``), or with
    a point or innovation the lanes cannot take (``bad``, ``update[15]``), is left to
    :func:`~resloc.cl.kernels_round_stages.inflated_moments` (``fresh[c]`` stays 1).
    Twin: the second pass of ``correct_links`` (``attempt == 1`` with ``fresh``)."""
    for c in range(n):
        d = n + c
        if not (decision[3, c] == 1.0 and fresh[c] == 1.0 and inflation[c] == 1.0):
            continue
        if ok_j[d] != 1.0 or bad[d] != 0.0 or update[15, d] != 0.0:
            continue
        for a in range(moments.shape[0]):
            moments[a, c] = moments[a, d]
        for a in range(pxz.shape[0]):
            pxz[a, c] = pxz[a, d]
        for a in range(update.shape[0]):
            update[a, c] = update[a, d]
        fresh[c] = 0.0


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
    cached_lanes, padded_lanes, pad_gathered, lanes_ahead, fresh_lanes, fresh_covariances,
    take_fresh, transmitted_lanes, sent_lanes,
):  # fmt: skip
    stamp_with_pieces(_dispatcher, _kernels_math, _kernels_links)
