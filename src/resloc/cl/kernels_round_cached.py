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
:func:`transmitted_lanes`  ``xj0``, ``xj1`` (the update stages' ``j``)
:func:`sent_lanes`         the ``delivered`` flag
=========================  =============================================================
"""

from __future__ import annotations

from resloc.cl import kernels_links as _kernels_links
from resloc.cl import kernels_math as _kernels_math
from resloc.cl.kernels_links import cached_decision
from resloc.cl.kernels_math import jit_lanes, stamp_with_pieces

_jit = jit_lanes

__all__ = ["cached_lanes", "sent_lanes", "transmitted_lanes"]


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


for _dispatcher in (cached_lanes, transmitted_lanes, sent_lanes):
    stamp_with_pieces(_dispatcher, _kernels_math, _kernels_links)
