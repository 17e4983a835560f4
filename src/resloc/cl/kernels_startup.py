"""The start-up floor compiled in one pass per step.

Twin of :func:`~resloc.cl.detection_startup.reference_floor` (the numpy specification:
``np.unique`` of the observers, the stage store's ``get`` and ``set``, the schedule, the
factors and :func:`~resloc.cl.detection_widening.scale_robots`). :func:`startup_pass` reads
and writes the stage's per-robot store (keyed ``r * n + r``: the count of corrections and
the factor applied) where it lies in the memory; the numpy glue of those calls, about
40 microseconds a step on the paper's 17 robots, was the stage's whole cost.

The pass writes the store only when every observer of the step is stored already (a run's
steady state, from its second step); otherwise it writes nothing and the spec runs (the only
code that inserts). An observer id outside the store's id space or the covariances' rows is
the spec's to decide (it raises, or indexes as numpy does).

It also tells whether the stage is over for the store (:func:`stage_over`, the spec's
:func:`~resloc.cl.detection_startup.floor_over`): then :func:`fast_floor` is not called again
(:func:`~resloc.cl.detection_startup.startup_floor` keeps that answer).
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl.backend import backend
from resloc.cl.kernels_math import jit_lanes

__all__ = [
    "STARTUP_RUNS",
    "fast_floor",
    "floor_factor",
    "stage_over",
    "startup_pass",
    "stored_slots",
    "write_raised",
]

#: How often the compiled pass ran, left the step to the spec (an observer not stored yet,
#: an id out of range, arrays it does not take) and found the stage over (the tests read it).
STARTUP_RUNS = {"passes": 0, "fallbacks": 0, "over": 0}

#: :func:`startup_pass`'s status besides the number of robots raised (>= 0): the stage is
#: over for the store (nothing written); an observer is not stored yet, or an id is out of
#: range (nothing written: the spec runs).
OVER, REFUSED = -1, -2


@jit_lanes
def _floor(seen, steps, std, decay, end):
    """The floor (m) of a robot with ``seen`` corrections before this one (twin of
    :func:`~resloc.cl.detection_startup.startup_floor_schedule`: ``np.power``, the C
    ``pow``, as numba's ``**`` of two floats)."""
    past = seen - steps + 1.0
    if not (past >= 0.0):  # np.maximum(past, 0): nan stays nan
        past = past if math.isnan(past) else 0.0
    floor = std * decay**past
    return floor if floor >= end else 0.0


@jit_lanes
def floor_factor(P, r, floor):
    """``max(floor^2 / max(P_r,xx, P_r,yy), 1)``: the factor that raises robot ``r``'s
    covariance in ``P (B, 3, 3)`` to the floor, as numpy computes it (``np.maximum``: a
    nan wins; shared with :mod:`resloc.cl.kernels_lockout`)."""
    a, d = P[r, 0, 0], P[r, 1, 1]
    largest = a if (math.isnan(a) or a >= d) else d
    if math.isnan(d):
        largest = d
    f = floor * floor / largest
    if not (f >= 1.0) and not math.isnan(f):
        f = 1.0
    return f


@jit_lanes
def write_raised(out, P, observer, factor):
    """``out (B, 3, 3)`` <- ``P`` with every observer's block times its factor above 1
    (``observer (n,)`` bool, ``factor (n,)``): the spec's
    :func:`~resloc.cl.detection_widening.scale_robots`."""
    out[:] = P
    for r in range(observer.shape[0]):
        if observer[r] and factor[r] > 1.0:
            f = factor[r]
            for a in range(3):
                for b in range(3):
                    out[r, a, b] *= f


@jit_lanes
def stored_slots(skeys, n, li, mask, B):
    """Each marked observer's row in a per-robot store (shared with
    :mod:`resloc.cl.kernels_lockout`) (keys ``r * n + r`` ascending);
    ``observer[r]`` whether ``r`` observes on a link with ``mask`` set. ``ok`` False when
    an id is out of range or a marked observer is not stored yet."""
    E = li.shape[0]
    observer = np.zeros(n, np.bool_)
    slot = np.empty(n, np.int64)
    for e in range(E):
        if li[e] < 0 or li[e] >= n or li[e] >= B:
            return observer, slot, False
        if mask[e]:
            observer[li[e]] = True
    S = skeys.shape[0]
    q = 0
    for r in range(n):
        if observer[r]:
            key = r * n + r
            while q < S and skeys[q] < key:
                q += 1
            if q >= S or skeys[q] != key:
                return observer, slot, False
            slot[r] = q
    return observer, slot, True


@jit_lanes
def stage_over(skeys, svals, n, steps, std, decay, end):
    """Whether the store ``skeys, svals (S,), (S, 2)`` holds every robot id ``0 .. n - 1``
    (keys ``r * n + r``) with its floor ended and factor 1, for a schedule that never rises
    again (``decay <= 1``): the spec's :func:`~resloc.cl.detection_startup.floor_over`."""
    if skeys.shape[0] != n or not (decay <= 1.0):
        return False
    for q in range(n):
        if skeys[q] != q * (n + 1) or svals[q, 1] != 1.0:
            return False
        if _floor(svals[q, 0], steps, std, decay, end) > 0.0:
            return False
    return True


@jit_lanes
def startup_pass(skeys, svals, n, li, P, out, steps, std, decay, end):
    """Every observer's floor factor, its store row, and the floored covariances.

    Parameters
    ----------
    skeys, svals : ndarray, shapes (S,), (S, 2)
        The stage's store (keys ``r * n + r``, sorted; values the count of corrections and
        the last factor), written in place.
    n : int
        The store's id space.
    li : ndarray of int64, shape (E,)
        The step's observers (one per link, any order).
    P : ndarray, shape (B, 3, 3)
        The covariances before the stage.
    out : ndarray, shape (B, 3, 3)
        Receives ``P`` with every raised robot's block times its factor (written only when
        one is raised).
    steps, std, decay, end : float
        ``startup_steps``, ``startup_floor_std``, ``startup_decay``, ``STARTUP_FLOOR_END``.

    Returns
    -------
    int
        The number of robots raised (``out`` holds the covariances when > 0, ``P`` is
        unchanged otherwise), :data:`OVER` or :data:`REFUSED` (nothing written).
    """
    # every observer's row (ids out of range and observers not stored yet: the spec's)
    observer, slot, ok = stored_slots(skeys, n, li, np.ones(li.shape[0], np.bool_), P.shape[0])
    if not ok:
        return REFUSED
    if stage_over(skeys, svals, n, steps, std, decay, end):
        return OVER
    factor = np.empty(n)
    raised = 0
    for r in range(n):
        if not observer[r]:
            continue
        seen = svals[slot[r], 0]
        floor = _floor(seen, steps, std, decay, end)
        f = floor_factor(P, r, floor) if floor > 0.0 else 1.0
        factor[r] = f
        if f > 1.0:
            raised += 1
    for r in range(n):
        if observer[r]:
            svals[slot[r], 0] += 1.0
            svals[slot[r], 1] = factor[r]
    if raised:
        write_raised(out, P, observer, factor)
    return raised


def fast_floor(params, state, links, P: np.ndarray, end: float) -> tuple[str, np.ndarray | None]:
    """:func:`~resloc.cl.detection_startup.startup_floor` by :func:`startup_pass` on the
    stage's store ``state`` (the stage on): ``("done", covariances)``; ``("over", P)``
    (the stage is over for the store, nothing written); ``("spec", None)`` with the numpy
    backend, arrays it does not take, or a step the pass refuses (then the spec runs)."""
    if backend() != "numba":
        return "spec", None
    n = state.n_nodes
    li = np.ascontiguousarray(links.i, np.int64)
    Pa = np.ascontiguousarray(P, float)
    if state.values.ndim != 2 or Pa.ndim != 3 or Pa.shape[1:] != (3, 3) or li.ndim != 1:
        STARTUP_RUNS["fallbacks"] += 1
        return "spec", None
    # (the store's own arrays, written in place: numba takes them as they are)
    out = np.empty_like(Pa)
    status = startup_pass(
        state.keys, state.values, n, li, Pa, out, float(params.startup_steps),
        float(params.startup_floor_std), float(params.startup_decay), end,
    )  # fmt: skip
    if status == REFUSED:
        STARTUP_RUNS["fallbacks"] += 1
        return "spec", None
    if status == OVER:
        STARTUP_RUNS["over"] += 1
        return "over", P
    STARTUP_RUNS["passes"] += 1
    return "done", (out if status > 0 else P)
