"""The pending store of witness notes, compiled: a row of it read (:func:`copy_note`, for
the outvoted pass, :mod:`resloc.cl.kernels_outvoted`) and the step's sent notes written
into it in place (:func:`record_in_place`, :func:`fast_record`). A row holds a note's
``u``, ``Q``, ``P_pos`` and its waiting flag
(:data:`~resloc.cl.detection_witness_frames.PENDING_WIDTH` values); the receivers read the
waiting notes the next step (:mod:`resloc.cl.kernels_witness_frames`).
"""

from __future__ import annotations

import numpy as np

from resloc.cl.backend import backend
from resloc.cl.kernels_math import jit_lanes
from resloc.cl.kernels_witness import WITNESS_RUNS

__all__ = ["copy_note", "fast_record", "record_in_place"]


@jit_lanes
def copy_note(pvals, e, u, Q, Pp, q):
    """Pending row ``e``'s note into row ``q`` of ``u``, ``Q``, ``P_pos``."""
    u[q, 0] = pvals[e, 0]
    u[q, 1] = pvals[e, 1]
    Q[q, 0, 0] = pvals[e, 2]
    Q[q, 0, 1] = pvals[e, 3]
    Q[q, 1, 0] = pvals[e, 4]
    Q[q, 1, 1] = pvals[e, 5]
    Pp[q, 0, 0] = pvals[e, 6]
    Pp[q, 0, 1] = pvals[e, 7]
    Pp[q, 1, 0] = pvals[e, 8]
    Pp[q, 1, 1] = pvals[e, 9]


@jit_lanes
def record_in_place(keys, n, i, j, sent, u, Q, P_pos, values):
    """The sent notes ``u (E, 2)``, ``Q (E, 2, 2)``, ``P_pos (E, 2, 2)`` of links ``(i, j)``
    written into the pending store ``keys (K,)`` (sorted), ``values (K, 11)``, every other
    note's flag cleared. False, nothing written, when a sent link is not stored yet (the
    numpy spec inserts it). Twin: :func:`~resloc.cl.detection_witness_frames.
    reference_record`."""
    E = i.shape[0]
    K = keys.shape[0]
    pos = np.empty(E, np.int64)
    for e in range(E):
        if sent[e]:
            key = i[e] * n + j[e]
            p = np.searchsorted(keys, key)
            if p >= K or keys[p] != key:
                return False
            pos[e] = p
    for p in range(K):
        values[p, 10] = 0.0
    for e in range(E):
        if sent[e]:
            p = pos[e]
            values[p, 0] = u[e, 0]
            values[p, 1] = u[e, 1]
            values[p, 2] = Q[e, 0, 0]
            values[p, 3] = Q[e, 0, 1]
            values[p, 4] = Q[e, 1, 0]
            values[p, 5] = Q[e, 1, 1]
            values[p, 6] = P_pos[e, 0, 0]
            values[p, 7] = P_pos[e, 0, 1]
            values[p, 8] = P_pos[e, 1, 0]
            values[p, 9] = P_pos[e, 1, 1]
            values[p, 10] = 1.0
    return True


def fast_record(notes, memory) -> bool:
    """:func:`record_in_place` on the memory's pending store; False with the numpy backend,
    arrays it does not take, or a link not stored yet (then the numpy spec records)."""
    if backend() != "numba":
        return False
    from resloc.cl.detection_witness_frames import PENDING, PENDING_WIDTH

    store = memory.stage_statistic(PENDING, width=PENDING_WIDTH)
    v = store.values
    if not len(store) or v.dtype != np.float64 or not v.flags.c_contiguous:
        return False
    E = len(notes)
    arrays = (
        np.ascontiguousarray(notes.i, np.int64),
        np.ascontiguousarray(notes.j, np.int64),
        np.ascontiguousarray(notes.sent, np.bool_),
        np.ascontiguousarray(notes.u, float),
        np.ascontiguousarray(notes.Q, float),
        np.ascontiguousarray(notes.P_pos, float),
    )
    shapes = ((E,), (E,), (E,), (E, 2), (E, 2, 2), (E, 2, 2))
    if any(a.shape != s for a, s in zip(arrays, shapes, strict=True)):
        return False
    if not record_in_place(store.keys, store.n_nodes, *arrays, v):
        return False
    WITNESS_RUNS["records"] += 1
    return True
