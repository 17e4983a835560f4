"""Compiled twin of zone-aware trust (:mod:`resloc.cl.detection_zone`).

The stage decides per link, at the observer's *running* estimate (a robot's earlier links
of the step may have moved it across a zone's edge), whether the link is

* ``OUTSIDE``: the observer's estimate is outside the map; the other stages judge it;
* ``SUBSTITUTED``: the observer is inside, its partner's transmitted estimate is outside
  and the partner's reading of the pair is finite: the link's moments and innovation become
  the partner's position fix of the observer
  (:func:`~resloc.cl.kernels_zone_verdicts.position_fix_of_link`), which the
  other stages judge and the update fuses (the redundancy stages neither judge nor store
  it: :func:`resloc.cl.detection_redundancy.RedundancyCheck.discard`);
* ``WITHHELD``: inside, with no trusted partner reading: discarded, and no other stage sees
  it (no CUSUM, robot CUSUM or recovery statistic changes).

The decision is made inside the link loops, where the running estimate is, by the kernels
of :mod:`resloc.cl.kernels_zone_verdicts` (in row order and in the rounds). They write each
row's verdict into :attr:`KernelZone.verdict`, which the stages that run after it read
(``detect_link``, ``screen_lanes``) and which the dispatch reads after the loop: the
redundancy pre-pass (:mod:`resloc.cl.kernels_redundancy`) writes every link's
sequence-test state before the loop, and :func:`keep_unjudged_state` puts the withheld
and substituted links' state back, as the reference stores only the rows its stages
judged.

This module holds the stage's state and the glue around the loops:

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`restore_unjudged`       ``_restore`` (the pre-passes' state of the rows not judged)
:func:`zone_links`             the head of ``resloc.cl.step._correct_reference`` (the
                               partners' readings)
:func:`partner_readings`       the same without a tamper hook
                               (:func:`~resloc.cl.detection_zone.reciprocal_rows`)
:func:`zone_rows`              the same into new arrays, with the verdicts' array
=============================  ==========================================================
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np

from resloc.cl.detection_zone import materialize_with_reciprocal
from resloc.cl.kernels_math import jit, lower_bound, per_params
from resloc.cl.kernels_zone_verdicts import OUTSIDE
from resloc.cl.links import LinkBatch
from resloc.cl.params import CLParams

__all__ = [
    "KernelZone",
    "keep_unjudged_state",
    "no_zone",
    "partner_readings",
    "restore_unjudged",
    "zone_links",
    "zone_rows",
    "zone_state",
]


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
