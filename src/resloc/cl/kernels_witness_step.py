"""The witness stage's step in one compiled call.

Before it, :func:`~resloc.cl.kernels_witness.witness_verdict` made five calls a step, each
with its numpy glue: the receivers' delivery
(:func:`~resloc.cl.kernels_witness_frames.delivered_pass`), the verdict per link (the
delivered statistic looked up and compared with ``h``), the step's notes
(:func:`~resloc.cl.kernels_witness.notes_of` on gathered rows), which notes are sent (the
observer outside the zone-trust map, the note a number) and, after the loop, the record
of the notes in the pending store. :func:`witness_pass` does all of it in one compiled
call; the constants it reads (each robot's ``f``, ``k``, ``h``, the consistency gates, the
zone map) are kept per ``params`` object. The record is written into a copy of the pending
values (the link loop may still fail, and the memory must then be as it was), which
:meth:`~resloc.cl.kernels_witness.WitnessVerdict.record` puts in the memory after the loop.

=============================  ==========================================================
function                       numpy twin
=============================  ==========================================================
:func:`witness_pass`           ``deliver_witness``, ``WitnessCheck.discard``,
                               ``step_notes`` and ``reference_record``
                               (:mod:`resloc.cl.detection_witness`,
                               :mod:`resloc.cl.detection_witness_frames`)
=============================  ==========================================================

:func:`fused_verdict` falls back (None: the separate calls of ``witness_verdict``) with
the numpy backend, shapes it does not take or ids beyond the memory's; with an
adversary's ``notes`` hook it gives the notes to the hook and the record is the spec's
(``record_witness`` on the notes the hook returns).
"""

from __future__ import annotations

import math
import weakref

import numpy as np

from resloc.cl.backend import backend
from resloc.cl.detection_witness import STATE, consistency_gates, step_notes
from resloc.cl.detection_witness_frames import PENDING, PENDING_WIDTH
from resloc.cl.kernels_math import jit_lanes
from resloc.cl.kernels_witness import WITNESS_RUNS, WitnessVerdict, note_at
from resloc.cl.kernels_witness_frames import delivered_pass, per_robot
from resloc.cl.memory import LinkStatistic

__all__ = ["fused_verdict", "witness_pass"]

#: Status of :func:`witness_pass`: done, an id beyond the memory's or the estimates',
#: the consistency gates too short (``need`` holds minus the largest set).
DONE, BAD_IDS, SHORT_GATES = 0, 1, 2


@jit_lanes
def witness_pass(
    pkeys,
    pvals,
    n,
    li,
    lj,
    ok,
    skeys,
    svals,
    f_at,
    k_at,
    h_at,
    gates,
    z,
    x,
    P,
    x_nb,
    crows,
    claims,
    R,
    discs,
    zoned,
    record,
):
    """The witness stage's whole step.

    Parameters
    ----------
    pkeys, pvals, n, li, lj, ok, skeys, svals, f_at, k_at, h_at, gates
        As :func:`~resloc.cl.kernels_witness_frames.delivered_pass` (every robot judged).
    z : ndarray, shape (E, 2)
        The readings as reported.
    x, P : ndarray, shapes (B, 3), (B, 3, 3)
        The predicted estimates (``B >= n``).
    x_nb : ndarray, shape (E, 3)
        The neighbours' broadcasts.
    crows, claims : ndarray, shapes (E,) or (0,), (C, 3, 3)
        Their covariances as sent (before any cap): link ``e``'s ``claims[crows[e]]``
        (``crows`` empty: ``claims[e]``).
    R : ndarray, shape (2, 2)
    discs : ndarray, shape (Z, 3)
        The zone-trust map (centre, radius); read when ``zoned``.
    record : bool
        Compute the step's notes and record them (False: an adversary's hook changes
        them first; the caller computes and records them by the spec's functions).

    Returns
    -------
    status : int
        :data:`DONE`, :data:`BAD_IDS` (nothing computed) or :data:`SHORT_GATES`.
    keys, values, need
        The delivered store and the sets enumerated (``delivered_pass``).
    discard : ndarray of bool, shape (E,)
        ``S_{i,j} > h_j`` after the delivery (``WitnessCheck.discard``).
    pending : ndarray, shape (P, 11)
        The pending values with the step's sent notes (``step_notes``) recorded
        (``reference_record``), valid when ``recorded``.
    recorded : bool
        ``record`` and every sent link was in the pending store (else the caller records
        by the spec, which inserts).
    """
    E = li.shape[0]
    bad = n > x.shape[0] or n > P.shape[0]
    by_row = crows.shape[0] > 0
    bad = bad or (crows.shape[0] != E if by_row else claims.shape[0] != E)
    for e in range(E):
        bad = bad or li[e] < 0 or li[e] >= n or lj[e] < 0 or lj[e] >= n
        if by_row and not bad:
            bad = crows[e] < 0 or crows[e] >= claims.shape[0]
    discard = np.zeros(E, np.bool_)
    if bad:
        return BAD_IDS, np.empty(0, np.int64), np.empty(0), 0, discard, pvals, False
    on_ok = np.ones(n, np.bool_)
    keys, values, need, S = delivered_pass(
        pkeys, pvals, n, li, lj, ok, skeys, svals, on_ok, f_at, k_at, h_at, gates
    )
    if need < 0:
        return SHORT_GATES, keys, values, need, discard, pvals, False
    for e in range(E):
        discard[e] = S[li[e] * n + lj[e]] > h_at[lj[e]]
    if not record:
        return DONE, keys, values, need, discard, pvals, False
    # the step's notes, recorded into a copy of the pending values (the memory is put
    # right after the loop); per observer, not per link: the reading's lengthening
    # (note_at), inside the map
    lengthen = np.empty(n)
    inside = np.zeros(n, np.bool_)
    for r in range(n):
        lengthen[r] = math.exp(0.5 * (R[1, 1] + P[r, 2, 2]))
        for d in range(discs.shape[0] if zoned else 0):  # (inside_zone_map)
            gap = math.hypot(x[r, 0] - discs[d, 0], x[r, 1] - discs[d, 1]) - discs[d, 2]
            inside[r] = inside[r] or gap <= 0.0
    pending = pvals.copy()
    slot = np.full(n * n, -1, np.int64)  # each stored link's row (a search per link costs)
    for p in range(pkeys.shape[0]):
        pending[p, 10] = 0.0
        if 0 <= pkeys[p] < n * n:
            slot[pkeys[p]] = p
    u = np.empty((1, 2))
    Q = np.empty((1, 2, 2))
    for e in range(E):
        r = li[e]
        if inside[r] or not ok[e]:
            continue  # (not sent: inside the map, j's estimate not received)
        note_at(z, e, x, r, P, x_nb, R, u, Q, 0, lengthen[r])
        if not (math.isfinite(u[0, 0]) and math.isfinite(u[0, 1])):
            continue  # (not sent: no number)
        p = slot[r * n + lj[e]]
        if p < 0:  # a link not stored yet: the spec records (it inserts)
            return DONE, keys, values, need, discard, pvals, False
        pending[p, 0] = u[0, 0]
        pending[p, 1] = u[0, 1]
        pending[p, 2] = Q[0, 0, 0]
        pending[p, 3] = Q[0, 0, 1]
        pending[p, 4] = Q[0, 1, 0]
        pending[p, 5] = Q[0, 1, 1]
        c = crows[e] if by_row else e
        pending[p, 6] = claims[c, 0, 0]
        pending[p, 7] = claims[c, 0, 1]
        pending[p, 8] = claims[c, 1, 0]
        pending[p, 9] = claims[c, 1, 1]
        pending[p, 10] = 1.0
    return DONE, keys, values, need, discard, pending, True


_NO_ROWS = np.zeros(0, np.int64)

#: The constants of the last ``params`` object: (weak reference, n, constants).
_CONSTANTS: list = [None, -1, None]


def _constants(params, n: int, largest: int = 0) -> tuple:
    """``(f_at, k_at, h_at, gates, R, discs, zoned)`` for ``params`` and ids ``0 .. n -
    1``, the gates covering sets of at least ``largest`` notes (kept for the last
    ``params``)."""
    ref, held_n, held = _CONSTANTS
    if ref is not None and ref() is params and held_n == n and len(held[3]) > largest:
        return held
    p_fa = float(np.max(params.witness_false_alarm))
    zoned = bool(params.zone_trust and params.zone_trust_map)
    discs = np.asarray(params.zone_trust_map if zoned else (), float).reshape(-1, 3)
    held = (
        per_robot(np.rint(params.witness_liars), n, np.int64),
        per_robot(params.witness_k, n),
        per_robot(params.witness_h, n),
        consistency_gates(p_fa, max(largest, n)),
        np.ascontiguousarray(params.R, float),
        np.ascontiguousarray(discs),
        zoned,
    )
    try:
        _CONSTANTS[:] = [weakref.ref(params), n, held]
    except TypeError:  # not weakly referenceable: not kept
        _CONSTANTS[:] = [None, -1, None]
    return held


def fused_verdict(params, memory, x, P, links, inputs) -> WitnessVerdict | None:
    """:func:`~resloc.cl.kernels_witness.witness_verdict` by :func:`witness_pass`; None
    with the numpy backend, shapes it does not take or ids beyond the memory's (the
    separate calls then run; so in one robot's process given its delivery over the wire,
    ``memory.delivered_witness``, which :func:`delivered_store` takes)."""
    if backend() != "numba" or memory.delivered_witness is not None:
        return None
    stat = memory.stage_statistic(STATE)
    pending = memory.stage_statistic(PENDING, width=PENDING_WIDTH)
    n = stat.n_nodes
    li = np.ascontiguousarray(links.i, np.int64)
    E = len(li)
    arrays = (
        np.ascontiguousarray(links.j, np.int64),
        np.ascontiguousarray(links.channel_ok, np.bool_),
        np.ascontiguousarray(links.z, float),
        np.ascontiguousarray(x, float),
        np.ascontiguousarray(P, float),
        np.ascontiguousarray(links.x_nb, float),
        _NO_ROWS if inputs.rows is None else np.ascontiguousarray(inputs.rows, np.int64),
        np.ascontiguousarray(inputs.claims, float),
    )
    lj, ok, z, xc, Pc, x_nb, crows, claims = arrays
    if lj.shape != (E,) or ok.shape != (E,) or z.shape != (E, 2):
        return None
    if xc.ndim != 2 or xc.shape[1:] != (3,) or Pc.ndim != 3 or Pc.shape[1:] != (3, 3):
        return None
    if x_nb.shape != (E, 3) or claims.ndim != 3 or claims.shape[1:] != (3, 3):
        return None
    if crows.ndim != 1:
        return None
    # (the stores' arrays as LinkStatistic and the pass make them: int64 keys, float64
    # values, contiguous; checked, not converted)
    pkeys, pvals, skeys, svals = pending.keys, pending.values, stat.keys, stat.values
    if pvals.shape != (len(pkeys), PENDING_WIDTH) or svals.shape != skeys.shape:
        return None
    if pkeys.dtype != np.int64 or skeys.dtype != np.int64:
        return None
    if pvals.dtype != np.float64 or svals.dtype != np.float64:
        return None
    largest = 0
    record = inputs.lie_notes is None
    while True:
        f_at, k_at, h_at, gates, R, discs, zoned = _constants(params, n, largest)
        status, keys, values, need, discard, after, recorded = witness_pass(
            pkeys,
            pvals,
            n,
            li,
            lj,
            ok,
            skeys,
            svals,
            f_at,
            k_at,
            h_at,
            gates,
            z,
            xc,
            Pc,
            x_nb,
            crows,
            claims,
            R,
            discs,
            zoned,
            record,
        )
        if status != SHORT_GATES:
            break
        largest = -need
    if status != DONE:
        return None
    store = LinkStatistic(n)
    store.keys, store.values = keys, values
    runs = WITNESS_RUNS
    runs["verdicts"] += 1
    runs["delivered"] += 1
    runs["enumerated"] += need
    runs["steps"] += 1
    if recorded:  # (the notes are in ``after``)
        return WitnessVerdict(discard, store, None, after)
    notes = step_notes(z, xc[li], Pc[li], x_nb, inputs.claimed, li, lj, params, ok)
    if inputs.lie_notes is not None:  # the adversary's notes: the spec records them
        notes = inputs.lie_notes(notes)
    return WitnessVerdict(discard, store, notes)
