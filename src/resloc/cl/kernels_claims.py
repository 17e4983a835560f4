"""Compiled twin of the claimed covariances a defence changes before the link loop.

Two options change what a neighbour claims before anything judges or fuses it: the
redundancy stage's cap (``detector.redundancy_cap_fusion``: each claim raised to the
observer's median claim, :func:`~resloc.cl.detection_redundancy_fixes.capped_claims`) and the
zone landmarks (``detector.zone_landmarks``: the claims of the neighbours whose broadcast
position lies inside the map raised to the median of the capped claims, then inflated,
:func:`~resloc.cl.detection_landmark.landmark_claims`). In numpy each is a few passes over
every row (the per-observer medians by a ``lexsort``, the map by a ``(E, Z)`` distance
table, the copies) and a new :class:`~resloc.cl.links.LinkBatch` by
``dataclasses.replace`` (which gathers both per-link estimate arrays); here both are one
compiled pass, :func:`claimed_covariances`, into one new array, and the batch is a shallow
copy with that array as its claims (the estimates stay where they are, read by index).

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`claimed_covariances`    ``capped_claims`` (the cap) then ``landmark_claims``
                               (``inside_zone_map``, ``capped_claims``, the inflation)
:func:`claimed_rows`           the same into new arrays, the estimates gathered
:func:`claimed_links`          the head of ``resloc.cl.step._correct_reference`` (the cap
                               and :func:`~resloc.cl.detection_landmark.landmark_links`)
=============================  ==========================================================

The kernel is compiled (or loaded from numba's cache) on the first step that switches one
of the two options on: a run without them does not pay for it.
"""

from __future__ import annotations

import copy

import numpy as np

from resloc.cl.detection_landmark import landmark_links
from resloc.cl.kernels_math import jit, jit_inline, per_params
from resloc.cl.kernels_reciprocal import inside_discs
from resloc.cl.kernels_redundancy_fixes import claim_scales, scales_to_median, trace_scales
from resloc.cl.links import LinkBatch
from resloc.cl.params import CLParams

__all__ = [
    "CLAIMS_RUNS",
    "CLAIMS_UNCHANGED",
    "CLAIMS_UNSORTED",
    "claim_options",
    "claimed_covariances",
    "claimed_links",
    "claimed_rows",
    "raised_trace_scales",
]

#: :func:`claimed_covariances`'s results besides the number of rows inside the map.
CLAIMS_UNSORTED = -2  # rows not sorted by observer: nothing decided
CLAIMS_UNCHANGED = -1  # neither option changed a claim: ``out`` not written

#: How often :func:`claimed_links` ran the compiled pass (the tests read it).
CLAIMS_RUNS = {"compiled": 0}


@jit
def claimed_covariances(li, x_src, P_src, rows, cap, discs, inflation, out, scale, scratch):
    """Row ``e``'s claim ``P_src[rows[e]]`` (``(S, 3, 3)``, observer ``li[e]``) as the
    correction fuses it, into ``out: (E, 3, 3)``: with ``cap``, scaled by
    :func:`~resloc.cl.kernels_redundancy_fixes.claim_scales`' factor; then, when the neighbour's
    broadcast position ``x_src[rows[e], :2]`` lies inside a disc of ``discs: (Z, 3)``,
    scaled by that factor of the (capped) claims and multiplied by ``inflation``.
    ``scale``, ``scratch``: (E,) scratch. Returns the number of rows inside the map,
    ``CLAIMS_UNCHANGED`` (``out`` not written) when neither step changed anything (no cap,
    no row inside) and ``CLAIMS_UNSORTED`` when the rows are not sorted by observer. Twin:
    :func:`~resloc.cl.detection_redundancy_fixes.capped_claims` then
    :func:`~resloc.cl.detection_landmark.landmark_claims` (same products, same order)."""
    E = li.shape[0]
    Z = discs.shape[0]
    # each source row's place, tested once (a step's 260 links read 17 robots' estimates):
    # 0 not tested, 1 outside, 2 inside
    place = np.zeros(x_src.shape[0] if Z > 0 else 0, np.int8)
    inside = 0
    for e in range(E):
        if e > 0 and li[e] < li[e - 1]:
            return CLAIMS_UNSORTED
        if Z > 0:
            n = rows[e]
            if place[n] == 0:
                place[n] = 2 if inside_discs(x_src[n, 0], x_src[n, 1], discs) else 1
            if place[n] == 2:
                inside += 1
    if not cap and inside == 0:
        return CLAIMS_UNCHANGED
    if cap:
        claim_scales(li, P_src, rows, scale, scratch)
    for e in range(E):
        f = scale[e] if cap else 1.0
        n = rows[e]
        for a in range(3):
            for b in range(3):
                out[e, a, b] = P_src[n, a, b] * f if cap else P_src[n, a, b]
    if inside == 0:
        return inside
    raised = np.empty(E if cap else 0, np.bool_)
    for e in range(E):  # the median of the (capped) claims: their traces, then factors
        if cap:
            raised[e] = scale[e] != 1.0
        scale[e] = out[e, 0, 0] + out[e, 1, 1]
    if not (cap and raised_trace_scales(li, scale, raised, scratch, np.empty(E))):
        trace_scales(li, scale, scratch)
    for e in range(E):
        if place[rows[e]] == 2:
            for a in range(3):
                for b in range(3):
                    out[e, a, b] = inflation * (out[e, a, b] * scale[e])
    return inside


@jit_inline
def raised_trace_scales(li, scale, raised, ranked, work):
    """:func:`~resloc.cl.kernels_redundancy_fixes.trace_scales` of the capped claims' traces
    ``scale: (E,)`` (replaced by their factors), from the order of the traces before the
    cap: ``ranked: (E,)`` holds each observer's traces before the cap sorted (the scratch
    :func:`~resloc.cl.kernels_redundancy_fixes.claim_scales` leaves), ``raised: (E,)`` whether
    the cap's factor of a row was not 1. False, nothing written, when a trace is NaN (the
    caller then sorts). ``work: (E,)`` scratch. Rows sorted by observer (the caller tested
    them).

    Why the same median: a row the cap left (factor 1) keeps its trace to the bit
    (``P * 1.0``), and the raised rows are those of trace ``t > 0`` with ``m / t > 1``
    (``m`` the median before the cap): as the division is monotone, in the sorted traces
    they follow the ``t <= 0`` ones, one contiguous run. So the capped traces, sorted, are
    the traces before the cap without that run merged with the raised rows' new traces,
    sorted; only these (about half a group) are sorted here, and the median is read from
    the merge. The values at the median's two places are those of a full sort (ties
    between equal values do not change them)."""
    E = li.shape[0]
    for e in range(E):
        if scale[e] != scale[e]:
            return False
    start = 0
    while start < E:
        stop = start + 1
        while stop < E and li[stop] == li[start]:
            stop += 1
        count = stop - start
        c = 0  # the raised rows' traces, sorted (insertion) into work[start:start + c]
        for e in range(start, stop):
            if raised[e]:
                t = scale[e]
                k = start + c
                while k > start and work[k - 1] > t:
                    work[k] = work[k - 1]
                    k -= 1
                work[k] = t
                c += 1
        p = start  # the run of raised rows in ``ranked``: after the traces <= 0
        while p < stop and ranked[p] <= 0.0:
            p += 1
        lo = (count - 1) // 2
        hi = count // 2
        a = start  # the merge up to the place hi; a skips the run [p, p + c)
        b = start
        low = 0.0
        v = 0.0
        for r in range(hi + 1):
            if a == p:
                a = p + c
            if b < start + c and (a >= stop or work[b] < ranked[a]):
                v = work[b]
                b += 1
            else:
                v = ranked[a]
                a += 1
            if r == lo:
                low = v
        median = 0.5 * (low + v)
        scales_to_median(scale, start, stop, median)
        start = stop
    return True


@jit
def claimed_rows(li, x_src, P_src, rows, cap, discs, inflation):
    """:func:`claimed_covariances` into new arrays, with the claimed rows' estimates
    gathered beside them: ``(inside, P_out: (E, 3, 3), x_out: (E, D))``, ``x_out[e] =
    x_src[rows[e]]`` (``x_src: (S, D)``; both empty when ``inside`` is
    ``CLAIMS_UNCHANGED`` or ``CLAIMS_UNSORTED``, the latter also for estimates of fewer
    than 2 components, claims not ``(S, 3, 3)`` or ``rows`` not ``(E,)``). The batch that
    carries per-row claims carries per-row estimates
    (:meth:`~resloc.cl.links.LinkBatch.neighbour_rows`): numpy's gather of them was half of
    the claims' cost."""
    E = li.shape[0]
    D = x_src.shape[1]
    if D < 2 or P_src.shape[1] != 3 or P_src.shape[2] != 3 or rows.shape[0] != E:
        return CLAIMS_UNSORTED, np.empty((0, 3, 3)), np.empty((0, 3))  # (refused alike)
    out = np.empty((E, 3, 3))
    scratch = np.empty((2, E))  # the factors and the medians' scratch (one allocation)
    inside = claimed_covariances(
        li, x_src, P_src, rows, cap, discs, inflation, out, scratch[0], scratch[1]
    )
    if inside < 0:
        return inside, np.empty((0, 3, 3)), np.empty((0, 3))
    x_out = np.empty((E, D))
    for e in range(E):
        n = rows[e]
        for a in range(D):
            x_out[e, a] = x_src[n, a]
    return inside, out, x_out


@per_params
def claim_options(params: CLParams) -> tuple[bool, bool, np.ndarray, float]:
    """``(on, cap, discs, inflation)``: whether either option changes a claim, then the
    options as :func:`claimed_covariances` takes them (no discs without the landmarks)."""
    cap = bool(params.redundancy and params.redundancy_cap_fusion)
    discs = np.zeros((0, 3))
    if params.zone_landmarks and params.zone_landmarks_map:
        discs = np.asarray(params.zone_landmarks_map, dtype=float).reshape(-1, 3)
    on = cap or discs.shape[0] > 0
    return on, cap, np.ascontiguousarray(discs), float(params.zone_landmarks_inflation)


def claimed_links(params: CLParams, links: LinkBatch) -> LinkBatch | None:
    """``links`` with the claims the correction fuses (:func:`claimed_covariances`): a
    shallow copy whose ``P_nb`` is the new ``(E, 3, 3)`` array and ``x_nb`` the claimed
    rows' estimates ``(E, 3)``, gathered by the same pass (:func:`claimed_rows`), or
    ``links`` itself when no claim changes. Rows not
    sorted by observer: None with the cap on (the reference path then judges them), else
    the numpy stage's batch (:func:`~resloc.cl.detection_landmark.landmark_links`). Twin:
    the head of ``resloc.cl.step._correct_reference``."""
    on, cap, discs, inflation = claim_options(params)
    if not on:
        return links
    nb, x_src, P_src = links.neighbour_rows()
    li = np.ascontiguousarray(links.i, dtype=np.int64)
    rows = np.arange(len(li), dtype=np.int64) if nb is None else np.ascontiguousarray(nb, np.int64)
    x_src = np.ascontiguousarray(x_src, dtype=float)
    P_src = np.ascontiguousarray(P_src, dtype=float)
    inside = CLAIMS_UNSORTED  # (the other shapes are tested by the pass)
    if x_src.ndim == 2 and P_src.ndim == 3 and rows.ndim == 1:
        inside, out, x_out = claimed_rows(li, x_src, P_src, rows, cap, discs, inflation)
        CLAIMS_RUNS["compiled"] += 1
    if inside >= 0:
        # the other fields shared, as dataclasses.replace does; the per-row estimates are
        # what reading ``x_nb`` would gather (LinkBatch.neighbour_rows)
        return _shallow_copy(links, out, x_out)
    if inside == CLAIMS_UNCHANGED:
        return links
    return None if cap else landmark_links(params, links)  # refused: the reference's way


#: Where a batch keeps the claims and estimates it was given or gathered (the ``__dict__``
#: entries of :class:`~resloc.cl.links.LinkBatch`'s ``P_nb`` and ``x_nb``).
_P_SLOT = LinkBatch.__dict__["P_nb"].slot
_X_SLOT = LinkBatch.__dict__["x_nb"].slot


def _shallow_copy(links: LinkBatch, P_nb: np.ndarray, x_nb: np.ndarray) -> LinkBatch:
    """``copy.copy(links)`` with ``P_nb`` and ``x_nb`` set: a new batch sharing every other
    field's value (its ``__dict__`` copied with the two; ``copy.copy`` then two
    assignments through the fields' descriptors: 2.2 us, here 0.5)."""
    fields = getattr(links, "__dict__", None)
    if fields is None or type(links) is not LinkBatch:
        claimed = copy.copy(links)
        claimed.P_nb, claimed.x_nb = P_nb, x_nb
        return claimed
    claimed = object.__new__(LinkBatch)
    claimed.__dict__ = {**fields, _P_SLOT: P_nb, _X_SLOT: x_nb}
    return claimed
