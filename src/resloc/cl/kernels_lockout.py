"""The lock-out floor compiled: one pass before the correction, one after.

Twins of :func:`~resloc.cl.detection_lockout.reference_floor` and
:func:`~resloc.cl.detection_lockout.reference_record` (the numpy specification:
``np.unique`` of the observers, the stage store's ``get`` and ``set``, ``np.bincount``,
the zone map test and :func:`~resloc.cl.detection_widening.scale_robots`). Their numpy
glue cost about 50 microseconds a step on the paper's 17 robots (floor ~15, record ~37),
the stage's whole cost. The passes read and write the stage's per-robot store (keyed
``r * n + r``: the discarded share and the factor applied) where it lies in the memory.

A pass writes the store only when every robot it would write is stored already (a run's
steady state, from its second step); otherwise it writes nothing and the spec runs (the
only code that inserts). An observer id outside the store's id space or the covariances'
rows is the spec's to decide (it raises, or indexes as numpy does).

The record also tells whether the store is idle (nobody's share above the threshold, no
factor above 1): the next floor then raises nobody and writes nothing, on either path, and
:func:`fast_floor` skips it while the store holds the same arrays (a clean run's usual
step: its floor was ~3 us a step in runs, pass and glue).
"""

from __future__ import annotations

import math
import weakref

import numpy as np

from resloc.cl.backend import backend
from resloc.cl.kernels_math import jit_lanes, per_params
from resloc.cl.kernels_startup import floor_factor, stored_slots, write_raised

__all__ = ["LOCKOUT_RUNS", "fast_floor", "fast_record", "floor_pass", "record_pass"]

#: How often each compiled pass ran or left the step to the spec, and the floors skipped
#: on an idle store (:class:`_Kept`; the tests read it).
LOCKOUT_RUNS = {"floors": 0, "records": 0, "fallbacks": 0, "idle": 0}

#: A pass's status besides the number of robots raised / recorded (>= 0): an observer is
#: not stored yet, or an id is out of range (nothing written: the spec runs); a robot is
#: raised and ``out`` is not the covariances' size (nothing written: the caller allocates
#: it and runs the pass again; a step that raises none, the usual one, allocates none).
REFUSED, NEED_OUT = -2, -3


@jit_lanes
def floor_pass(skeys, svals, n, li, P, out, share, std):
    """Every observer whose stored share is above ``share`` raised to the floor ``std``.

    Parameters
    ----------
    skeys, svals : ndarray, shapes (S,), (S, 2)
        The stage's store (keys ``r * n + r``, sorted; values the share and the last
        factor), written in place.
    n : int
        The store's id space.
    li : ndarray of int64, shape (E,)
        The step's observers (one per link, any order).
    P : ndarray, shape (B, 3, 3)
        The covariances before the stage.
    out : ndarray, shape (B, 3, 3) or (0, 3, 3)
        Receives ``P`` with every raised robot's block times its factor (written only when
        one is raised; too small then: :data:`NEED_OUT`).
    share, std : float
        ``lockout_share``, ``lockout_floor_std``.

    Returns
    -------
    int
        The number of robots raised (``out`` holds the covariances when > 0, ``P`` is
        unchanged otherwise), :data:`REFUSED` or :data:`NEED_OUT` (nothing written).
    """
    if P.shape[1] != 3 or P.shape[2] != 3 or svals.shape[1] != 2:
        return REFUSED  # (checked here, not by the glue a step)
    observer, slot, ok = stored_slots(skeys, n, li, np.ones(li.shape[0], np.bool_), P.shape[0])
    if not ok:
        return REFUSED
    factor = np.ones(n)
    raised = 0
    for r in range(n):
        if observer[r] and svals[slot[r], 0] > share:
            factor[r] = floor_factor(P, r, std)
            if factor[r] > 1.0:
                raised += 1
    if raised and out.shape[0] != P.shape[0]:
        return NEED_OUT
    for r in range(n):
        if observer[r]:
            svals[slot[r], 1] = factor[r]
    if raised:
        write_raised(out, P, observer, factor)
    return raised


@jit_lanes
def record_pass(skeys, svals, n, li, detected, channel_ok, x, discs, weight, share):
    """Each observer's share updated with the step's: ``s <- (1 - w) s + w d / m`` over
    its judged links (``detected``, ``channel_ok``: bool, shape (E,); judged: the channel
    through and the observer's estimate ``x (B, 3)`` outside every disc ``(cx, cy, r)`` of
    ``discs (Z, 3)``, the spec's :func:`~resloc.cl.detection_zone.inside_zone_map`); an
    observer with none judged is left. Returns the number of observers recorded (or
    :data:`REFUSED`) and whether the store is busy: a row with its share above ``share``
    or its factor above 1 (else the next floor raises nobody and writes nothing:
    :func:`fast_floor` skips it)."""
    recorded = _record(skeys, svals, n, li, detected, channel_ok, x, discs, weight)
    busy = False
    for q in range(svals.shape[0] if recorded != REFUSED else 0):
        if svals[q, 0] > share or svals[q, 1] > 1.0:
            busy = True
            break
    return recorded, busy


@jit_lanes
def _record(skeys, svals, n, li, detected, channel_ok, x, discs, weight):
    """:func:`record_pass`'s update: the number of observers recorded, or :data:`REFUSED`."""
    E = li.shape[0]
    if x.shape[1] < 2 or svals.shape[1] != 2 or detected.shape[0] != E or channel_ok.shape[0] != E:
        return REFUSED  # (checked here, not by the glue a step)
    judged = np.zeros(E, np.bool_)
    inside = np.zeros(n, np.int8)  # per observer: 0 not tested yet, 1 inside, -1 outside
    for e in range(E):
        r = li[e]
        if r < 0 or r >= n or r >= x.shape[0]:
            return REFUSED
        if not channel_ok[e]:
            continue
        if inside[r] == 0:  # (the zone map test once per observer, not per link)
            inside[r] = -1
            for z in range(discs.shape[0]):
                gap = math.hypot(x[r, 0] - discs[z, 0], x[r, 1] - discs[z, 1])
                if gap - discs[z, 2] <= 0.0:
                    inside[r] = 1
                    break
        judged[e] = inside[r] < 0
    observer, slot, ok = stored_slots(skeys, n, li, judged, x.shape[0])
    if not ok:
        return REFUSED
    m = np.zeros(n)
    d = np.zeros(n)
    for e in range(E):
        if judged[e]:
            m[li[e]] += 1.0
            if detected[e]:
                d[li[e]] += 1.0
    recorded = 0
    for r in range(n):
        if observer[r]:
            known = svals[slot[r], 0]
            svals[slot[r], 0] = (1.0 - weight) * known + weight * (d[r] / max(m[r], 1.0))
            if not (svals[slot[r], 1] > 1.0):
                svals[slot[r], 1] = 1.0
            recorded += 1
    return recorded


_NO_OUT = np.zeros((0, 3, 3))


class _Kept:
    """A memory's stage store and the passes' constants, kept from step to step (a run
    passes the same ``params`` every step), and the store's arrays when the last record
    found it idle (nobody's share above ``lockout_share``, no factor above 1: the next
    floor would raise nobody and write nothing, the spec's too; skipped while the store
    holds those same arrays)."""

    __slots__ = ("constants", "idle", "params", "state")

    def __init__(self, params, memory) -> None:
        from resloc.cl.detection_lockout import LOCKOUT_STATE

        self.params = params
        self.state = memory.stage_statistic(LOCKOUT_STATE, width=2)
        self.constants = _constants(params)
        self.idle: tuple | None = None


#: Per memory: its :class:`_Kept` (weak: it goes with its memory; the store does not refer
#: to its memory).
_KEPT: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def fast_floor(params, memory, links, P: np.ndarray) -> np.ndarray | None:
    """:func:`~resloc.cl.detection_lockout.lockout_floor` by :func:`floor_pass` on
    ``memory``'s stage store (the stage on): the covariances, or None with the numpy
    backend, arrays it does not take, or a step the pass refuses (then the spec runs).
    ``P`` itself, no pass, when the last record found the store idle (:class:`_Kept`)."""
    if backend() != "numba":
        return None
    kept = _KEPT.get(memory)  # (not a helper's call: a call costs ~0.2 us a step in runs)
    if kept is None or kept.params is not params:
        kept = _KEPT[memory] = _Kept(params, memory)
    state = kept.state
    skeys, svals = state.keys, state.values
    idle = kept.idle
    if idle is not None and idle[0] is skeys and idle[1] is svals:
        LOCKOUT_RUNS["idle"] += 1
        return P
    li = np.ascontiguousarray(links.i, np.int64)
    Pa = np.ascontiguousarray(P, float)
    if svals.ndim != 2 or Pa.ndim != 3 or li.ndim != 1:  # (the shapes: the pass checks)
        LOCKOUT_RUNS["fallbacks"] += 1
        return None
    share, std, _, _ = kept.constants
    out = _NO_OUT
    status = floor_pass(skeys, svals, state.n_nodes, li, Pa, out, share, std)
    if status == NEED_OUT:
        out = np.empty_like(Pa)
        status = floor_pass(skeys, svals, state.n_nodes, li, Pa, out, share, std)
    if status == REFUSED:
        LOCKOUT_RUNS["fallbacks"] += 1
        return None
    LOCKOUT_RUNS["floors"] += 1
    return out if status > 0 else P


def fast_record(params, memory, links, detected: np.ndarray, x: np.ndarray) -> bool:
    """:func:`~resloc.cl.detection_lockout.record_lockout`'s update by :func:`record_pass`
    on ``memory``'s stage store (the stage on; ``x (B, 3)`` the estimates the correction
    started from): whether it ran (False: the spec runs)."""
    kept = _KEPT.get(memory)  # (not a helper's call: a call costs ~0.2 us a step in runs)
    if kept is None or kept.params is not params:
        kept = _KEPT[memory] = _Kept(params, memory)
    kept.idle = None  # (whichever path records: the spec writes the store in place)
    state = kept.state
    skeys, svals = state.keys, state.values
    if backend() != "numba" or svals.ndim != 2:
        return False
    xa = np.ascontiguousarray(x, float)
    if xa.ndim != 2:  # (its width: the pass checks)
        LOCKOUT_RUNS["fallbacks"] += 1
        return False
    share, _, discs, weight = kept.constants
    status, busy = record_pass(
        skeys, svals, state.n_nodes, np.ascontiguousarray(links.i, np.int64),
        np.ascontiguousarray(detected, np.bool_),
        np.ascontiguousarray(links.channel_ok, np.bool_), xa, discs, weight, share,
    )  # fmt: skip
    if status == REFUSED:
        LOCKOUT_RUNS["fallbacks"] += 1
        return False
    LOCKOUT_RUNS["records"] += 1
    if not busy:
        kept.idle = (skeys, svals)
    return True


@per_params
def _constants(params) -> tuple[float, float, np.ndarray, float]:
    """``(lockout_share, lockout_floor_std, discs, weight)`` as the passes take them (kept
    per ``params``): the zone map ``(Z, 3)`` (empty without zone trust) and ``1 /
    lockout_window``."""
    discs = np.zeros((0, 3))
    if params.zone_trust and params.zone_trust_map:
        discs = np.asarray(params.zone_trust_map, float).reshape(-1, 3)
    return (
        float(params.lockout_share),
        float(params.lockout_floor_std),
        np.ascontiguousarray(discs),
        1.0 / float(params.lockout_window),
    )
