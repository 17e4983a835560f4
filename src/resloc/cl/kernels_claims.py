"""Compiled twin of the claimed covariances a defence changes before the link loop.

Two options change what a neighbour claims before anything judges or fuses it: the
redundancy stage's cap (``detector.redundancy_cap_fusion``: each claim raised to the
observer's median claim, :func:`~resloc.cl.detection_redundancy.capped_claims`) and the
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
from resloc.cl.kernels_math import jit, per_params
from resloc.cl.kernels_reciprocal import inside_discs
from resloc.cl.kernels_redundancy import claim_scales, trace_scales
from resloc.cl.links import LinkBatch
from resloc.cl.params import CLParams

__all__ = [
    "CLAIMS_RUNS",
    "CLAIMS_UNCHANGED",
    "CLAIMS_UNSORTED",
    "claimed_covariances",
    "claimed_links",
    "claimed_rows",
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
    :func:`~resloc.cl.kernels_redundancy.claim_scales`' factor; then, when the neighbour's
    broadcast position ``x_src[rows[e], :2]`` lies inside a disc of ``discs: (Z, 3)``,
    scaled by that factor of the (capped) claims and multiplied by ``inflation``.
    ``scale``, ``scratch``: (E,) scratch. Returns the number of rows inside the map,
    ``CLAIMS_UNCHANGED`` (``out`` not written) when neither step changed anything (no cap,
    no row inside) and ``CLAIMS_UNSORTED`` when the rows are not sorted by observer. Twin:
    :func:`~resloc.cl.detection_redundancy.capped_claims` then
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
    for e in range(E):  # the median of the (capped) claims: their traces, then factors
        scale[e] = out[e, 0, 0] + out[e, 1, 1]
    trace_scales(li, scale, scratch)
    for e in range(E):
        if place[rows[e]] == 2:
            for a in range(3):
                for b in range(3):
                    out[e, a, b] = inflation * (out[e, a, b] * scale[e])
    return inside


@jit
def claimed_rows(li, x_src, P_src, rows, cap, discs, inflation):
    """:func:`claimed_covariances` into new arrays, with the claimed rows' estimates
    gathered beside them: ``(inside, P_out: (E, 3, 3), x_out: (E, D))``, ``x_out[e] =
    x_src[rows[e]]`` (``x_src: (S, D)``; both empty when ``inside`` is
    ``CLAIMS_UNCHANGED`` or ``CLAIMS_UNSORTED``). The batch that carries per-row claims
    carries per-row estimates (:meth:`~resloc.cl.links.LinkBatch.neighbour_rows`): numpy's
    gather of them was half of the claims' cost."""
    E = li.shape[0]
    D = x_src.shape[1]
    # the claims, the estimates, the factors and the medians' scratch: one allocation
    # (C-contiguous slices; four allocations and their release were ~0.4 us)
    block = np.empty(E * (11 + D))
    out = block[: 9 * E].reshape((E, 3, 3))
    x_out = block[9 * E : (9 + D) * E].reshape((E, D))
    scratch = block[(9 + D) * E :].reshape((2, E))
    inside = claimed_covariances(
        li, x_src, P_src, rows, cap, discs, inflation, out, scratch[0], scratch[1]
    )
    if inside < 0:
        return inside, np.empty((0, 3, 3)), np.empty((0, 3))
    for e in range(E):
        n = rows[e]
        for a in range(D):
            x_out[e, a] = x_src[n, a]
    return inside, out, x_out


@per_params
def _claim_options(params: CLParams) -> tuple[bool, np.ndarray, float]:
    """``(cap, discs, inflation)`` as :func:`claimed_covariances` takes them (no discs
    without the landmarks)."""
    cap = bool(params.redundancy and params.redundancy_cap_fusion)
    discs = np.zeros((0, 3))
    if params.zone_landmarks and params.zone_landmarks_map:
        discs = np.asarray(params.zone_landmarks_map, dtype=float).reshape(-1, 3)
    return cap, np.ascontiguousarray(discs), float(params.zone_landmarks_inflation)


def claimed_links(params: CLParams, links: LinkBatch) -> LinkBatch | None:
    """``links`` with the claims the correction fuses (:func:`claimed_covariances`): a
    shallow copy whose ``P_nb`` is the new ``(E, 3, 3)`` array and ``x_nb`` the claimed
    rows' estimates ``(E, 3)``, gathered by the same pass (:func:`claimed_rows`), or
    ``links`` itself when no claim changes. Rows not
    sorted by observer: None with the cap on (the reference path then judges them), else
    the numpy stage's batch (:func:`~resloc.cl.detection_landmark.landmark_links`). Twin:
    the head of ``resloc.cl.step._correct_reference``."""
    cap, discs, inflation = _claim_options(params)
    if not cap and not discs.shape[0]:
        return links
    nb, x_src, P_src = links.neighbour_rows()
    li = np.ascontiguousarray(links.i, dtype=np.int64)
    E = len(li)
    rows = np.arange(E, dtype=np.int64) if nb is None else np.ascontiguousarray(nb, np.int64)
    x_src = np.ascontiguousarray(x_src, dtype=float)
    P_src = np.ascontiguousarray(P_src, dtype=float)
    if x_src.ndim != 2 or x_src.shape[1] < 2 or P_src.shape[1:] != (3, 3) or rows.shape != (E,):
        return None if cap else landmark_links(params, links)
    inside, out, x_out = claimed_rows(li, x_src, P_src, rows, cap, discs, inflation)
    CLAIMS_RUNS["compiled"] += 1
    if inside == CLAIMS_UNSORTED:
        return None if cap else landmark_links(params, links)
    if inside == CLAIMS_UNCHANGED:
        return links
    # the other fields shared, as dataclasses.replace does; the per-row estimates are what
    # reading ``x_nb`` would gather (LinkBatch.neighbour_rows)
    return _shallow_copy(links, out, x_out)


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
