"""Compiled twin of the reciprocal range check (:mod:`resloc.cl.detection_reciprocal`).

The check compares each link's range with its partner's reading of the same pair, once per
step, from the readings and the predicted estimates only: its verdict does not depend on the
order in which the links are fused. The compiled correction therefore runs it as a pre-pass,
:func:`reciprocal_verdicts`, one call over every link, as it runs the redundancy stage
(:mod:`resloc.cl.kernels_redundancy`): the verdicts reach the link loops ORed into
:attr:`KernelDetection.fixes <resloc.cl.kernels_detection.KernelDetection>` (which makes the
loops run their options' form, :func:`~resloc.cl.kernels_rounds.beyond_paper`). The
per-link state ``[s, V, hold]`` is the same store of the run's
:class:`~resloc.cl.memory.LinkMemory` the numpy stage reads and writes
(``stage_statistic("reciprocal", width=3)``), updated in place; a run can switch paths
between steps. :meth:`~resloc.cl.kernels_detection.PrepassVerdict.undo` puts it back
when the kernel gives up on a step.

==============================  =========================================================
kernel function                 numpy twin
==============================  =========================================================
:func:`inside_discs`            :func:`~resloc.cl.detection_zone.inside_zone_map` (one
                                position)
:func:`reciprocal_verdicts`     :func:`~resloc.cl.detection_reciprocal.reciprocal_evidence`
                                (``judged_pairs``, ``reciprocal_step``) and
                                ``ReciprocalCheck.discard``'s store
:func:`partner_rows`            :func:`~resloc.cl.detection_zone.reciprocal_rows`
                                (``materialize_with_reciprocal``'s partner readings)
:func:`partner_readings`        the head of ``resloc.cl.step._correct_reference`` (a
                                tamper hook's readings and the partners')
==============================  =========================================================

With zone trust on, the zone stage withholds or substitutes rows round by round and the
numpy stage stores no state for the rows it never judges: the link loops decide zone trust,
and :func:`resloc.cl.kernels_zone.keep_unjudged_state` puts back this pre-pass's state (and
the redundancy pre-pass's) for those rows, so the combination runs compiled too.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np

from resloc.cl import kernels_detection as _kernels_detection
from resloc.cl.detection_reciprocal import STATE_WIDTH, ReciprocalCheck
from resloc.cl.detection_zone import materialize_with_reciprocal
from resloc.cl.kernels_detection import (
    DetectorState,
    PrepassVerdict,
    gain_at,
    shared_slots,
    store_slots,
)
from resloc.cl.kernels_math import (
    gain_array,
    jit_inline,
    jit_lanes,
    lower_bound,
    per_params,
    stamp_with_pieces,
)
from resloc.cl.kernels_zone_verdicts import inside_map
from resloc.cl.links import LinkBatch
from resloc.cl.params import CLParams

__all__ = [
    "ReciprocalOptions",
    "inside_discs",
    "partner_readings",
    "partner_rows",
    "reciprocal_options",
    "reciprocal_verdict",
    "reciprocal_verdicts",
]

#: The state's columns (twin: ``detection_reciprocal._SUM, _VAR, _HOLD``).
_SUM, _VAR, _HOLD = 0, 1, 2


class ReciprocalOptions(NamedTuple):
    """The stage's options as :func:`reciprocal_verdicts` takes them; gains ``(1,)`` or
    ``(B,)``."""

    variance: float  # 2 sigma_r^2 (m^2)
    gate: np.ndarray  # reciprocal_gate
    sequence_gate: np.ndarray  # reciprocal_sequence_gate
    hold: np.ndarray  # reciprocal_hold
    forget: np.ndarray  # reciprocal_forget
    discs: np.ndarray  # (Z, 3) the zone map's discs (cx, cy, r); (0, 3) without a map


@per_params
def reciprocal_options(params: CLParams) -> ReciprocalOptions:
    """The stage's options of ``params`` (:class:`ReciprocalOptions`)."""
    discs = np.asarray(params.zone_trust_map, dtype=float).reshape(-1, 3)
    return ReciprocalOptions(
        float(2.0 * params.range_std**2),
        gain_array(params.reciprocal_gate),
        gain_array(params.reciprocal_sequence_gate),
        gain_array(params.reciprocal_hold),
        gain_array(params.reciprocal_forget),
        np.ascontiguousarray(discs),
    )


# ---------------------------------------------------------------------------------------
# Compiled pieces
# ---------------------------------------------------------------------------------------
@jit_inline
def inside_discs(px, py, discs):
    """Whether ``(px, py)`` lies inside any disc ``(cx, cy, r)`` of ``discs: (Z, 3)``
    (:func:`resloc.cl.kernels_zone_verdicts.inside_map`: no libm call where the squares decide).
    Twin: :func:`~resloc.cl.detection_zone.inside_zone_map` (``hypot(.) - r <= 0``)."""
    return inside_map(discs, px, py)


@jit_lanes
def partner_rows(li, lj, row):
    """Per row ``e``: the row of the reverse link ``(lj[e], li[e])``, -1 where the batch holds
    none, into ``row: (E,)`` (a binary search in the neighbour's rows when every observer's
    neighbours ascend, else a scan). Rows must be sorted by observer (False otherwise).
    Twin: :func:`~resloc.cl.detection_zone.reciprocal_rows` (links distinct)."""
    E = li.shape[0]
    B = 0
    T = 0
    low = 0
    ascending = True  # each observer's neighbours in ascending order (the usual batch)
    for e in range(E):
        if e > 0 and li[e] < li[e - 1]:
            return False
        if e > 0 and li[e] == li[e - 1] and lj[e] <= lj[e - 1]:
            ascending = False
        if li[e] + 1 > B:
            B = li[e] + 1
        T = max(T, lj[e] + 1)
        low = min(low, lj[e])
    T = max(T, B)
    if low >= 0 and T <= 4 * E + 64 and T * T <= 16 * E + 1024:
        # ids of a team: a table of every pair's row, one write and one read a row (the
        # searches below: 1.2 us for a step's 260 rows, 0.5; kernels_zone.partner_readings)
        pair = np.full(T * T, -1, np.int64)
        for e in range(E - 1, -1, -1):  # (the first row of a pair, as the scan's)
            pair[li[e] * T + lj[e]] = e
        for e in range(E):
            row[e] = pair[lj[e] * T + li[e]]
        return True
    first = np.zeros(B, np.int64)
    stop = np.zeros(B, np.int64)
    for e in range(E - 1, -1, -1):  # each observer's rows (contiguous: sorted)
        first[li[e]] = e
    for e in range(E):
        stop[li[e]] = e + 1
    for e in range(E):
        j = lj[e]
        want = li[e]
        row[e] = -1
        if j < 0 or j >= B:
            continue
        lo = first[j]
        hi = stop[j]
        if ascending:
            lo = lower_bound(lj, want, lo, hi)
            if lo < stop[j] and lj[lo] == want:
                row[e] = lo
        else:
            for r in range(lo, hi):
                if lj[r] == want:
                    row[e] = r
                    break
    return True


# IEEE division (jit_lanes' error model): ``d^2 / (2 sigma_r^2)`` as numpy divides, even
# with a zero range noise.
@jit_lanes
def reciprocal_verdicts(
    li, lj, z, z_rec, x, x_nb, nb, variance, gate, sequence_gate, hold, forget, discs, state,
    slot, discard,
):  # fmt: skip
    """The reciprocal range check on every link of one step: link ``e`` compares its range
    ``z[e, 0]`` with its partner's, ``z_rec[e, 0]`` (``nan``: none; ``z_rec`` of shape
    ``(0, 2)``: the reverse link's reading in ``z``, found here) and, with a map
    (``discs: (Z, 3)``), is left to it when exactly one of the observer's predicted position
    ``x[li[e]]`` and the neighbour's transmitted one ``x_nb[nb[e]]`` is inside.
    ``state[slot[e]]``: the link's ``[s, V, hold]``, updated in place; the verdict (held
    out, flagged by the sum, or over the one-step gate) is ORed into ``discard: (E,)``
    (zeros, or another pre-pass's discards: no second array and ``|`` a step). Rows sorted
    by observer (False otherwise). Twin:
    :func:`~resloc.cl.detection_reciprocal.reciprocal_evidence` with
    ``ReciprocalCheck.discard``."""
    E = li.shape[0]
    found = z_rec.shape[0] == 0
    row = np.empty(E, np.int64)
    if found:
        if not partner_rows(li, lj, row):
            return False
    else:
        for e in range(E):
            if e > 0 and li[e] < li[e - 1]:
                return False
    mapped = discs.shape[0] > 0
    # each observer's and each source row's place, tested once (a step's 260 links: 17
    # observers, 17 robots' estimates): 0 not tested, 1 outside, 2 inside
    observer_in = 0
    place = np.zeros(x_nb.shape[0] if mapped else 0, np.int8)
    for e in range(E):
        i = li[e]
        k = slot[e]
        partner = z_rec[e, 0]
        if found:
            partner = z[row[e], 0] if row[e] >= 0 else math.nan
        if e == 0 or i != li[e - 1]:
            observer_in = 0
        judged = math.isfinite(partner)
        if judged and mapped:
            n = nb[e]
            if observer_in == 0:
                observer_in = 2 if inside_discs(x[i, 0], x[i, 1], discs) else 1
            if place[n] == 0:
                place[n] = 2 if inside_discs(x_nb[n, 0], x_nb[n, 1], discs) else 1
            judged = observer_in == place[n]
        if state[k, _HOLD] > 0.0:  # held out: counted down, the sums untouched
            state[k, _HOLD] = state[k, _HOLD] - 1.0
            discard[e] = True
            continue
        if not judged:  # nothing to compare: the sums stay as they are
            continue
        lam = gain_at(forget, i)
        d = z[e, 0] - partner
        s = lam * state[k, _SUM] + d
        V = lam * lam * state[k, _VAR] + variance
        one_step = d * d / variance > gain_at(gate, i)
        alarm = V > 0.0 and s * s / V > gain_at(sequence_gate, i)
        if alarm:  # the hold starts with the sums reset (re-admitted afresh)
            state[k, _SUM] = 0.0
            state[k, _VAR] = 0.0
            state[k, _HOLD] = gain_at(hold, i)
        else:
            state[k, _SUM] = s
            state[k, _VAR] = V
        if alarm or one_step:
            discard[e] = True
    return True


stamp_with_pieces(reciprocal_verdicts, _kernels_detection)


# ---------------------------------------------------------------------------------------
# The dispatch's side (called by resloc.cl.kernels.fast_correct)
# ---------------------------------------------------------------------------------------
def partner_readings(filt, x, P, links: LinkBatch, strategy, memory, R) -> LinkBatch:
    """``links`` as the reference's correction judges them with an adversary's tamper hook:
    the hook applied to every row at the predicted estimates (it is Python), the partner
    readings taken from the result (and the hook's ``reported`` ones). ``links`` unchanged
    without a hook (:func:`reciprocal_verdicts` finds the partner readings in the batch when
    it carries none). Twin: the head of ``resloc.cl.step._correct_reference``."""
    if links.tamper is None:
        return links
    pre = strategy.moments(
        filt, memory, x[links.i], P[links.i], links.x_nb, links.P_nb, links.i, links.j, R
    )
    reported = getattr(links.tamper, "reported", None)
    links = materialize_with_reciprocal(links, pre.z_hat, pre.S)
    if reported is not None:
        links = dataclasses.replace(links, z_reciprocal=reported(links.z_reciprocal))
    return links


_IN_BATCH = np.zeros((0, 2))


def reciprocal_verdict(
    params, memory, li, lj, z, z_rec, x, x_nb, nb, detection, other=None
) -> PrepassVerdict | None:
    """The pre-pass of one step (:func:`reciprocal_verdicts`): ``li``, ``lj`` int64
    ``(E,)``, ``z``, ``z_rec: (E, 2)`` the readings as reported and the partners', ``x``
    the predicted estimates, ``x_nb`` the transmitted estimates at rows ``nb``
    (contiguous); ``detection``: the step's
    :class:`~resloc.cl.kernels_detection.KernelDetection` (the NIS CUSUM's store holds the
    same links as this stage's in a run's steady state: its slots are reused); ``other``:
    another pre-pass's discards ``(E,)`` bool (the redundancy stage's), into which this
    one's are ORed in place (the verdict's ``discard`` is then ``other``: the loops read
    the union). None without a memory to keep the state in (the reference path then raises
    the explanatory error) or when the rows are not sorted by observer."""
    if memory is None:
        return None
    E = len(li)
    if z_rec is None:
        z_rec = _IN_BATCH  # the reverse links' readings, found in the batch
    else:
        z_rec = np.ascontiguousarray(z_rec, dtype=float)
        if z_rec.shape != (E, 2):
            return None
    saved: list = []
    store = memory.stage_statistic(ReciprocalCheck.name, width=STATE_WIDTH)
    slots = None
    if detection.cusum:  # both stores hold every link of every step
        slots = shared_slots(store, memory.cusum, detection.cusum_slot, saved)
    if slots is None:
        slots = store_slots(store, li, lj, saved)
    discard = np.zeros(E, dtype=np.bool_) if other is None else other
    verdict = PrepassVerdict(discard, DetectorState(None, tuple(saved)))
    if not reciprocal_verdicts(
        li, lj, np.ascontiguousarray(z, dtype=float), z_rec, np.ascontiguousarray(x, dtype=float),
        x_nb, nb, *reciprocal_options(params), store.values, slots, discard,
    ):  # fmt: skip
        verdict.undo()
        return None  # rows not sorted by observer: the reference judges them
    return verdict
