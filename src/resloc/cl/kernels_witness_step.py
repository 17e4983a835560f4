"""The witness stage's step in one compiled call.

Before it, :func:`~resloc.cl.kernels_witness.witness_verdict` made five calls a step, each
with its numpy glue: the receivers' delivery
(:func:`~resloc.cl.kernels_witness_frames.delivered_pass`), the verdict per link (the
delivered statistic looked up and compared with ``h``), the step's notes
(:func:`~resloc.cl.kernels_witness_notes.notes_of` on gathered rows), which notes are sent (the
observer outside the zone-trust map, the note a number) and, after the loop, the record
of the notes in the pending store. :func:`witness_pass` does all of it in one compiled
call; the constants it reads (each robot's ``f``, ``k``, ``h``, the consistency gates, the
zone map) are kept per ``params`` object. The record is written into a copy of the pending
values (the link loop may still fail, and the memory must then be as it was), which
:meth:`~resloc.cl.kernels_witness.WitnessVerdict.record` puts in the memory after the loop.
The notes are computed in SIMD lanes (:func:`~resloc.cl.kernels_witness_notes.sent_notes`:
sines and cosines by polynomials, the distance by a square root; ``note_at``'s values to a
few ulps, not to the bit), the broadcasts read by index.

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

from resloc.cl import kernels_lanes as _kernels_lanes
from resloc.cl.backend import backend
from resloc.cl.detection_witness import STATE, consistency_gates, step_notes
from resloc.cl.detection_witness_frames import PENDING, PENDING_WIDTH
from resloc.cl.kernels_math import jit_lanes, stamp_with_pieces
from resloc.cl.kernels_witness import WITNESS_RUNS, WitnessVerdict
from resloc.cl.kernels_witness_frames import delivered_pass, per_robot
from resloc.cl.kernels_witness_notes import NOTE_ROWS, sent_notes
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
    x_src,
    xrows,
    crows,
    claims,
    R,
    discs,
    record,
    keys,
    values,
    discard,
    pending,
):
    """The witness stage's whole step (its arrays written into the last four: a returned
    array costs numba's boxing, ~0.5 us each a call).

    Parameters
    ----------
    pkeys, pvals, n, li, lj, ok, skeys, svals, f_at, k_at, h_at, gates
        As :func:`~resloc.cl.kernels_witness_frames.delivered_pass` (every robot judged).
    z : ndarray, shape (E, 2)
        The readings as reported.
    x, P : ndarray, shapes (B, 3), (B, 3, 3)
        The predicted estimates (``B >= n``).
    x_src, xrows : ndarray, shapes (S, 3), (E,) or (0,)
        The neighbours' broadcasts: link ``e``'s ``x_src[xrows[e]]`` (``xrows`` empty:
        ``x_src[e]``; read by index, not gathered: ``links.x_nb`` would keep them).
    crows, claims : ndarray, shapes (E,) or (0,), (C, 3, 3)
        Their covariances as sent (before any cap): link ``e``'s ``claims[crows[e]]``
        (``crows`` empty: ``claims[e]``).
    R : ndarray, shape (2, 2)
    discs : ndarray, shape (Z, 3)
        The zone-trust map (centre, radius); empty without zone trust.
    record : bool
        Compute the step's notes and record them (False: an adversary's hook changes
        them first; the caller computes and records them by the spec's functions).
    keys, values : ndarray, shapes (n * n,), (n * n,)
        Receive the delivered store (``delivered_pass``) in their first ``K`` entries.
    discard : ndarray of bool, shape (E,)
        Receives ``S_{i,j} > h_j`` after the delivery (``WitnessCheck.discard``).
    pending : ndarray, shape (P, 11)
        Receives the pending values with the step's sent notes (``step_notes``) recorded
        (``reference_record``), valid when ``recorded`` (``record`` False: not written,
        may be empty).

    Returns
    -------
    status : int
        :data:`DONE`, :data:`BAD_IDS` (shapes that do not fit or ids beyond the memory's or
        the estimates': nothing computed) or :data:`SHORT_GATES`.
    K : int
        The delivered store's size (:data:`DONE`).
    need : int
        The sets enumerated (``delivered_pass``).
    recorded : bool
        ``record`` and every sent link was in the pending store (else the caller records
        by the spec, which inserts).
    """
    E = li.shape[0]
    # (the shapes, checked here: a comparison in Python costs ~60 ns)
    bad = lj.shape[0] != E or ok.shape[0] != E or z.shape[0] != E or z.shape[1] != 2
    bad = bad or x_src.shape[1] != 3 or x.shape[1] != 3
    bad = bad or P.shape[1] != 3 or P.shape[2] != 3 or claims.shape[1] != 3
    bad = bad or claims.shape[2] != 3 or pvals.shape[0] != pkeys.shape[0]
    bad = bad or pvals.shape[1] != PENDING_WIDTH or svals.shape[0] != skeys.shape[0]
    bad = bad or (record and pending.shape[0] != pvals.shape[0])
    bad = bad or keys.shape[0] < n * n or values.shape[0] < n * n or discard.shape[0] != E
    if bad:
        return BAD_IDS, 0, 0, False
    bad = n > x.shape[0] or n > P.shape[0]
    by_row = crows.shape[0] > 0
    bad = bad or (crows.shape[0] != E if by_row else claims.shape[0] != E)
    x_by_row = xrows.shape[0] > 0
    bad = bad or (xrows.shape[0] != E if x_by_row else x_src.shape[0] != E)
    for e in range(E):
        bad = bad or li[e] < 0 or li[e] >= n or lj[e] < 0 or lj[e] >= n
        if by_row and not bad:
            bad = crows[e] < 0 or crows[e] >= claims.shape[0]
        if x_by_row and not bad:
            bad = xrows[e] < 0 or xrows[e] >= x_src.shape[0]
    if bad:
        return BAD_IDS, 0, 0, False
    on_ok = np.ones(n, np.bool_)
    new_keys, new_values, need, S = delivered_pass(
        pkeys, pvals, n, li, lj, ok, skeys, svals, on_ok, f_at, k_at, h_at, gates
    )
    if need < 0:
        return SHORT_GATES, 0, need, False
    K = new_keys.shape[0]
    keys[:K] = new_keys
    values[:K] = new_values
    for e in range(E):
        discard[e] = S[li[e] * n + lj[e]] > h_at[lj[e]]
    if not record:
        return DONE, K, need, False
    # the step's notes, recorded into a copy of the pending values (the memory is put
    # right after the loop); per observer, not per link: the reading's lengthening
    # (sent_notes'), inside the map
    lengthen = np.empty(n)
    inside = np.zeros(n, np.bool_)
    for r in range(n):
        lengthen[r] = math.exp(0.5 * (R[1, 1] + P[r, 2, 2]))
        for d in range(discs.shape[0]):  # (inside_zone_map)
            gap = math.hypot(x[r, 0] - discs[d, 0], x[r, 1] - discs[d, 1]) - discs[d, 2]
            inside[r] = inside[r] or gap <= 0.0
    pending[:] = pvals
    slot = np.full(n * n, -1, np.int64)  # each stored link's row (a search per link costs)
    for p in range(pkeys.shape[0]):
        pending[p, 10] = 0.0
        if 0 <= pkeys[p] < n * n:
            slot[pkeys[p]] = p
    notes = np.empty((NOTE_ROWS, E))
    sent_notes(z, x, P, x_src, xrows, li, R, lengthen, notes)
    for e in range(E):
        r = li[e]
        if inside[r] or not ok[e]:
            continue  # (not sent: inside the map, j's estimate not received)
        if not (math.isfinite(notes[0, e]) and math.isfinite(notes[1, e])):
            continue  # (not sent: no number)
        p = slot[r * n + lj[e]]
        if p < 0:  # a link not stored yet: the spec records (it inserts)
            return DONE, K, need, False
        pending[p, 0] = notes[0, e]
        pending[p, 1] = notes[1, e]
        pending[p, 2] = notes[2, e]
        pending[p, 3] = notes[3, e]
        pending[p, 4] = notes[3, e]
        pending[p, 5] = notes[4, e]
        c = crows[e] if by_row else e
        pending[p, 6] = claims[c, 0, 0]
        pending[p, 7] = claims[c, 0, 1]
        pending[p, 8] = claims[c, 1, 0]
        pending[p, 9] = claims[c, 1, 1]
        pending[p, 10] = 1.0
    return DONE, K, need, True


stamp_with_pieces(witness_pass, _kernels_lanes)  # (sent_notes' sincos_lanes)

_NO_ROWS = np.zeros(0, np.int64)
_NO_PENDING = np.zeros((0, PENDING_WIDTH))
#: The arrays' dimensions the pass takes (``li .. crows``), and the stores' dtypes.
_DIMS = (1, 1, 1, 2, 2, 3, 2, 1, 1)
_INT, _FLOAT = np.dtype(np.int64), np.dtype(np.float64)

#: The constants of the last ``params`` object: (weak reference, n, constants).
_CONSTANTS: list = [None, -1, None]


def _constants(params, n: int, largest: int = 0) -> tuple:
    """``(f_at, k_at, h_at, gates, R, discs)`` for ``params`` and ids ``0 .. n - 1``, the
    gates covering sets of at least ``largest`` notes, the zone map empty without zone trust
    (kept for the last ``params``)."""
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
    lj = np.ascontiguousarray(links.j, np.int64)
    ok = np.ascontiguousarray(links.channel_ok, np.bool_)
    z = np.ascontiguousarray(links.z, float)
    xc = np.ascontiguousarray(x, float)
    Pc = np.ascontiguousarray(P, float)
    nb_rows, x_sent, _ = links.neighbour_rows()  # (links.x_nb would gather them for good:
    # the loop then reads every neighbour per link instead of by index; the pass gathers)
    x_src = np.ascontiguousarray(x_sent, float)
    xrows = _NO_ROWS if nb_rows is None else np.ascontiguousarray(nb_rows, np.int64)
    crows = _NO_ROWS if inputs.rows is None else np.ascontiguousarray(inputs.rows, np.int64)
    claims = np.ascontiguousarray(inputs.claims, float)
    # (the stores' arrays as LinkStatistic and the pass make them: int64 keys, float64
    # values; checked, not converted; the shapes are checked by the pass)
    pkeys, pvals, skeys, svals = pending.keys, pending.values, stat.keys, stat.values
    dims = (li.ndim, lj.ndim, ok.ndim, z.ndim, xc.ndim, Pc.ndim, x_src.ndim, xrows.ndim, crows.ndim)
    if dims != _DIMS or claims.ndim != 3 or pvals.ndim != 2 or svals.ndim != 1:
        return None
    if pkeys.dtype != _INT or skeys.dtype != _INT:
        return None
    if pvals.dtype != _FLOAT or svals.dtype != _FLOAT:
        return None
    E = len(li)
    largest = 0
    record = inputs.lie_notes is None
    # the pass's arrays (allocated here: numba boxes a returned array at ~0.5 us)
    keys = np.empty(n * n, np.int64)
    values = np.empty(n * n)
    discard = np.empty(E, np.bool_)
    after = np.empty(pvals.shape) if record else _NO_PENDING
    while True:
        f_at, k_at, h_at, gates, R, discs = _constants(params, n, largest)
        status, K, need, recorded = witness_pass(
            pkeys, pvals, n, li, lj, ok, skeys, svals, f_at, k_at, h_at, gates, z, xc, Pc,
            x_src, xrows, crows, claims, R, discs, record, keys, values, discard, after,
        )  # fmt: skip
        if status != SHORT_GATES:
            break
        largest = -need
    if status != DONE:
        return None
    store = LinkStatistic.holding(n, keys[:K], values[:K])
    runs = WITNESS_RUNS
    runs["verdicts"] += 1
    runs["delivered"] += 1
    runs["enumerated"] += need
    runs["steps"] += 1
    if recorded:  # (the notes are in ``after``)
        return WitnessVerdict(discard, store, None, after)
    x_nb = x_src if nb_rows is None else x_src[xrows]
    notes = step_notes(z, xc[li], Pc[li], x_nb, inputs.claimed, li, lj, params, ok)
    if inputs.lie_notes is not None:  # the adversary's notes: the spec records them
        notes = inputs.lie_notes(notes)
    return WitnessVerdict(discard, store, notes)
