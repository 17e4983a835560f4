"""The outvoted stage compiled in one pass per step.

Twin of :func:`~resloc.cl.detection_outvoted.reference_widen` (the numpy specification:
``pending_notes``, :func:`~resloc.cl.detection_outvoted.outvoted_statistic` with
:func:`~resloc.cl.detection_outvoted.group_medians`, the sequence test and the widening).
:func:`outvoted_pass` reads the pending notes and the stage's per-robot store as they lie in
the memory; the numpy glue per step (``isin``, ``lexsort``, the stores' searches, the
medians' sorts) was most of the stage's cost.

The grouping is a counting sort, the ids being small ints: the pending rows (keys sorted by
(observer, on)) are bucketed by the robot they are on, in ascending row order, so each
robot's rows come sorted by observer (the spec's ``lexsort``); robot r keeps the rows of the
observers whose frame reached it (the links (r, o) with their channel through). Each
robot's statistic is the witness stage's enumeration
(:func:`~resloc.cl.kernels_witness_statistic.group_statistics`), stopped at the first consistent set
whose statistic clips the robot's sequence test at 0 (``S + T - k <= 0``: the smallest
gives the same 0; the spec enumerates them all, and its ``T`` is read nowhere else). The
widening's 2 x 2 solve is written out (the spec calls LAPACK: equal to rounding); a
position block that is not symmetric positive definite goes to the spec (which raises on a
singular one).
"""

from __future__ import annotations

import math
import weakref
from typing import NamedTuple

import numpy as np

from resloc.cl.backend import backend
from resloc.cl.detection_outvoted import OUTVOTED_STATE
from resloc.cl.detection_witness import consistency_gates
from resloc.cl.detection_witness_frames import PENDING, PENDING_WIDTH
from resloc.cl.kernels_math import jit_lanes, per_params
from resloc.cl.kernels_witness_pending import copy_note
from resloc.cl.kernels_witness_statistic import group_statistics
from resloc.cl.params import CLParams, at_robots

__all__ = ["OUTVOTED_RUNS", "fast_widen", "outvoted_pass", "widened_covariances"]

#: How often the compiled pass ran, fell back to the spec, and how many judged robots' sets
#: of notes it enumerated in full, without the early stop (the tests read it).
OUTVOTED_RUNS = {"passes": 0, "fallbacks": 0, "enumerated": 0}

#: :func:`outvoted_pass`'s status: done; refused (a position block the 2 x 2 solve does
#: not take, an id out of range, pending keys out of range or unsorted: the spec decides);
#: ``-c`` (c > 0): ``gates`` stops short of a group of ``c`` notes.
DONE, REFUSED = 0, 1


@jit_lanes
def _sorted_median(buf, c):
    """The median of ``buf[:c]`` (sorted in place; c > 0): the middle element or the mean of
    the two middle ones, nan when one is nan (``np.median``)."""
    for t in range(c):
        if math.isnan(buf[t]):
            return np.nan
    for t in range(1, c):
        v = buf[t]
        s = t - 1
        while s >= 0 and buf[s] > v:
            buf[s + 1] = buf[s]
            s -= 1
        buf[s + 1] = v
    return (buf[(c - 1) // 2] + buf[c // 2]) / 2.0


@jit_lanes
def outvoted_pass(
    pkeys,
    pvals,
    n,
    li,
    lj,
    ok,
    skeys,
    svals,
    P,
    f_at,
    half_h_at,
    consts,
    gates,
    robots,
    values,
):
    """Every receiver's sequence test and widening factor after the pending notes on it;
    the store written in place and the widened covariances made when it can (``written``,
    ``widened``: the steady state's whole step in one call, no numpy glue after it). Its
    arrays are written into the last two (a returned array costs numba's boxing); the
    widened covariances are :func:`widened_covariances`' (a step that widens none, the
    usual one, allocates none).

    Parameters
    ----------
    pkeys, pvals : ndarray, shapes (Np,), (Np, 11)
        The witness stage's pending store (keys ``observer * n + on``, sorted; values ``u``,
        ``Q``, ``P_pos``, waiting flag: :data:`~resloc.cl.detection_witness_frames.PENDING`).
    n : int
        The id space.
    li, lj, ok : ndarray, shape (E,)
        The step's links: receiver, sender, channel ok.
    skeys, svals : ndarray, shapes (S,), (S, 2)
        The stage's store keyed ``r * n + r`` (sorted): ``S_r`` and the last factor.
    P : ndarray, shape (B, 3, 3)
        The covariances before the stage (B >= every receiver's id + 1).
    f_at, half_h_at : ndarray, shape (n,)
        ``witness_liars`` (int64) and ``witness_h / 2`` of each robot.
    consts : ndarray, shape (4,)
        ``witness_k``, ``witness_h``, ``outvoted_cap``, ``outvoted_max_std`` (one array:
        each argument costs numba's dispatch ~65 ns).
    gates : ndarray, shape (M,)
        ``gates[c]``: the consistency gate of ``c`` notes.
    robots : ndarray of int, shape (n,)
        Receives the receivers (ascending) in its first ``G`` entries.
    values : ndarray, shape (n, 2)
        Receives their new ``S`` and factor (1: none), the store's rows, in its first
        ``G`` rows.

    Returns
    -------
    G : int
        The number of receivers.
    status : int
        :data:`DONE`, :data:`REFUSED` or ``-c`` (module docstring).
    enumerated : int
        Judged receivers whose enumeration did not stop early (every set of notes).
    written : bool
        :data:`DONE` and every receiver stored before (a run's steady state): ``values``
        written into ``svals`` at their rows (else the caller sets them: the store inserts).
    widened : int
        Receivers whose factor is above 1 (:data:`DONE`).
    """
    k, h, cap, max_std = consts[0], consts[1], consts[2], consts[3]
    E = li.shape[0]
    if lj.shape[0] != E or ok.shape[0] != E or P.shape[1] != 3 or P.shape[2] != 3:
        return 0, REFUSED, 0, False, 0  # (arrays the glue no longer checks a step)
    if pvals.shape[0] != pkeys.shape[0] or pvals.shape[1] != PENDING_WIDTH:
        return 0, REFUSED, 0, False, 0
    if svals.shape[0] != skeys.shape[0] or svals.shape[1] != 2 or f_at.shape[0] < n:
        return 0, REFUSED, 0, False, 0
    for e in range(E):  # ids the spec would index with (or fail on): the spec decides
        if li[e] < 0 or lj[e] < 0 or li[e] >= n or lj[e] >= n or li[e] >= P.shape[0]:
            return 0, REFUSED, 0, False, 0
    # the receivers (ascending) and each one's senders whose frame got through
    is_recv = np.zeros(n, np.bool_)
    rfirst = np.zeros(n + 1, np.int64)
    for e in range(E):
        is_recv[li[e]] = True
        if ok[e]:
            rfirst[li[e] + 1] += 1
    for r in range(n):
        rfirst[r + 1] += rfirst[r]
    senders = np.empty(rfirst[n], np.int64)
    fill = rfirst[:n].copy()
    for e in range(E):
        if ok[e]:
            senders[fill[li[e]]] = lj[e]
            fill[li[e]] += 1
    G = 0
    for r in range(n):
        if is_recv[r]:
            G += 1
    G = 0
    for r in range(n):
        if is_recv[r]:
            robots[G] = r
            G += 1
    # the waiting rows bucketed by the robot they are on (ascending rows: by observer);
    # each row's observer by a scan, not a division a row (the keys ascend)
    Np = pkeys.shape[0]
    onfirst = np.zeros(n + 1, np.int64)
    p_obs = np.empty(Np, np.int64)
    o = 0
    for p in range(Np):
        key = pkeys[p]
        if key < 0 or key >= n * n or key < o * n:  # (keys out of range or unsorted)
            return 0, REFUSED, 0, False, 0
        while key >= (o + 1) * n:
            o += 1
        p_obs[p] = o
        if pvals[p, 10] > 0.0:
            onfirst[key - o * n + 1] += 1
    for r in range(n):
        onfirst[r + 1] += onfirst[r]
    by_on = np.empty(onfirst[n], np.int64)
    fill = onfirst[:n].copy()
    for p in range(Np):
        if pvals[p, 10] > 0.0:
            on = pkeys[p] - p_obs[p] * n
            by_on[fill[on]] = p
            fill[on] += 1
    # each receiver's group: the notes on it from the observers it heard
    heard = np.full(n, -1, np.int64)
    grows = np.empty(onfirst[n], np.int64)
    gstart = np.empty(G, np.int64)
    gcount = np.empty(G, np.int64)
    M = 0
    largest = 0
    for g in range(G):
        r = robots[g]
        for s in range(rfirst[r], rfirst[r + 1]):
            heard[senders[s]] = r
        gstart[g] = M
        for t in range(onfirst[r], onfirst[r + 1]):
            p = by_on[t]
            if heard[p_obs[p]] == r:
                grows[M] = p
                M += 1
        gcount[g] = M - gstart[g]
        largest = max(largest, gcount[g])
    slot = np.full(G, -1, np.int64)
    if largest >= gates.shape[0]:
        return G, -largest, 0, False, 0
    # the stored S and factor (0 for a robot never stored), and where to stop enumerating
    ns = skeys.shape[0]
    S0 = np.zeros(G)
    f0 = np.zeros(G)
    stop = np.empty(G)
    f = np.empty(G, np.int64)
    half = np.empty(G)
    for g in range(G):
        r = robots[g]
        q = np.searchsorted(skeys, r * n + r)
        if q < ns and skeys[q] == r * n + r:
            slot[g] = q
            S0[g] = svals[q, 0]
            f0[g] = svals[q, 1]
        v = k - S0[g]
        stop[g] = -np.inf if math.isnan(v) else v
        f[g] = f_at[r]
        half[g] = half_h_at[r]
    u = np.empty((M, 2))
    Q = np.empty((M, 2, 2))
    Pp = np.empty((M, 2, 2))
    for q in range(M):
        copy_note(pvals, grows[q], u, Q, Pp, q)
    T = np.zeros(G)
    judged = np.zeros(G, np.bool_)
    group_statistics(u, Q, Pp, gstart, gcount, f, half, gates, stop, T, judged)
    enumerated = 0
    buf = np.empty(max(largest, 1))
    for g in range(G):
        r = robots[g]
        step = 0.0  # no judgement: decays by k
        if judged[g]:
            step = T[g] if (math.isnan(T[g]) or T[g] < 0.5 * h) else 0.5 * h
            if not (T[g] <= stop[g]):
                enumerated += 1
        v = S0[g] + step - k
        if not math.isnan(v):
            v = min(max(v, 0.0), 2.0 * h)
        values[g, 0] = v
        values[g, 1] = 1.0
        if not (v > h and f0[g] <= 1.0) or not judged[g]:
            continue
        c = gcount[g]
        for t in range(c):
            buf[t] = u[gstart[g] + t, 0]
        m0 = _sorted_median(buf, c)
        for t in range(c):
            buf[t] = u[gstart[g] + t, 1]
        m1 = _sorted_median(buf, c)
        if not (math.isfinite(m0) and math.isfinite(m1)):
            continue
        a, b, d = P[r, 0, 0], 0.5 * (P[r, 0, 1] + P[r, 1, 0]), P[r, 1, 1]
        det = a * d - b * b
        if not (a > 0.0 and det > 0.0 and P[r, 0, 1] == P[r, 1, 0]):
            return G, REFUSED, enumerated, False, 0
        # covariance matching, 2 dof: lambda = m^T P^-1 m / 2
        lam = (d * m0 * m0 - 2.0 * b * m0 * m1 + a * m1 * m1) / det / 2.0
        if not math.isnan(lam):
            lam = min(max(lam, 1.0), cap)
        bound = max_std * max_std / max(a, d)
        if math.isnan(bound):
            lam = np.nan
        elif not math.isnan(lam):
            lam = min(lam, max(bound, 1.0))
        values[g, 1] = lam
    written = True
    widened = 0
    for g in range(G):
        written = written and slot[g] >= 0
        if values[g, 1] > 1.0:
            widened += 1
    for g in range(G if written else 0):
        svals[slot[g], 0] = values[g, 0]
        svals[slot[g], 1] = values[g, 1]
    return G, DONE, enumerated, written, widened


@jit_lanes
def widened_covariances(P, robots, values, G):
    """``P (B, 3, 3)`` with every receiver ``robots[g]`` (``g < G``) whose factor
    ``values[g, 1]`` is above 1 times it (the spec's
    :func:`~resloc.cl.detection_widening.scale_robots`): a new array."""
    out = P.copy()
    for g in range(G):
        lam = values[g, 1]
        if lam > 1.0:
            for a in range(3):
                for b in range(3):
                    out[robots[g], a, b] *= lam
    return out


class _Options(NamedTuple):
    """The stage's options as :func:`outvoted_pass` takes them (kept per ``params``)."""

    consts: np.ndarray  # witness_k, witness_h, outvoted_cap, outvoted_max_std
    p_fa: float
    gates: np.ndarray  # consistency_gates(p_fa, 16), the first the pass is given
    at: dict  # n -> (f_at, half_h_at), shapes (n,)

    def per_robot(self, params: CLParams, n: int) -> tuple[np.ndarray, np.ndarray]:
        """``witness_liars`` (int64) and ``witness_h / 2`` at every robot id ``0 .. n - 1``."""
        if n not in self.at:
            ids = np.arange(n)
            f = np.broadcast_to(np.rint(at_robots(params.witness_liars, ids)), (n,))
            half_h = np.broadcast_to(0.5 * np.asarray(at_robots(params.witness_h, ids)), (n,))
            self.at[n] = (
                np.ascontiguousarray(f, np.int64),
                np.ascontiguousarray(half_h, float),
            )
        return self.at[n]


def _rows_of(values, rows: int, width: int) -> bool:
    """Whether a store's ``values`` are the C-contiguous float64 ``(rows, width)`` array the
    pass takes as it is (a run's; else a reshaped copy is passed)."""
    return values.dtype == _FLOAT and values.flags.c_contiguous and values.shape == (rows, width)


_FLOAT = np.dtype(float)
_INT = np.dtype(np.int64)


@per_params
def _options(params: CLParams) -> _Options:
    p_fa = float(np.max(params.witness_false_alarm))
    consts = (params.witness_k, params.witness_h, params.outvoted_cap, params.outvoted_max_std)
    # (scalars, as the spec reads them)
    return _Options(np.array([float(v) for v in consts]), p_fa, consistency_gates(p_fa, 16), {})


class _Kept:
    """A memory's inputs of :func:`outvoted_pass` kept from step to step (a run passes the
    same ``params`` and stores every step): the stores, the options, the per-robot arrays,
    the pass's output arrays, and the store's arrays once checked (the pass writes them in
    place: the same objects the next step, not checked again). The glue's checks, options
    and allocations were ~3 of its ~6 us a step in runs."""

    __slots__ = (
        "at", "gates", "in_place", "n", "opt", "params", "pending", "pkeys", "robots",
        "skeys", "state", "svals", "values",
    )  # fmt: skip

    def __init__(self, params: CLParams, memory) -> None:
        self.params = params
        self.state = memory.stage_statistic(OUTVOTED_STATE, width=2)
        self.pending = memory.stage_statistic(PENDING, width=PENDING_WIDTH)
        self.n = n = self.state.n_nodes
        self.opt = _options(params)
        self.at = self.opt.per_robot(params, n)
        # the pass's arrays (numba boxes a returned array at ~0.3 us; nothing keeps them
        # past the step: the store's set copies them)
        self.robots = np.empty(n, np.int64)
        self.values = np.empty((n, 2))
        self.skeys = self.svals = self.pkeys = None
        self.in_place = False

    def store_arrays(self) -> tuple[np.ndarray, np.ndarray, bool]:
        """The stage store's keys and values as the pass takes them, and whether the values
        are the store's own (written in place; else a copy, and the caller sets them)."""
        state = self.state
        skeys, svals = state.keys, state.values
        if skeys is self.skeys and svals is self.svals:  # checked at an earlier step
            return skeys, svals, True
        in_place = skeys.dtype == _INT and skeys.flags.c_contiguous
        in_place = in_place and _rows_of(svals, len(skeys), 2)
        if in_place:
            self.skeys, self.svals = skeys, svals
            return skeys, svals, True
        # (a store the pass cannot write: it writes a copy, set by the caller)
        skeys = np.ascontiguousarray(skeys, np.int64)
        return skeys, np.ascontiguousarray(svals, float).reshape(len(state), 2), False

    def pending_keys(self) -> np.ndarray:
        """The pending store's keys as the pass takes them (checked once per array)."""
        pkeys = self.pending.keys
        if pkeys is not self.pkeys:
            if pkeys.dtype != _INT or not pkeys.flags.c_contiguous:
                return np.ascontiguousarray(pkeys, np.int64)
            self.pkeys = pkeys
        return pkeys


#: Per memory: its :class:`_Kept` (weak: a finished run's arrays go with its memory; the
#: stores do not refer to their memory).
_KEPT: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def fast_widen(params: CLParams, memory, links, P: np.ndarray) -> np.ndarray | None:
    """:func:`~resloc.cl.detection_outvoted.widen_outvoted` by :func:`outvoted_pass` (the
    stage on, a memory given); None with the numpy backend, arrays it does not take, or
    what the compiled pass refuses (then the spec runs). In a run's steady state the pass
    writes the store itself, and a step that widens a robot calls
    :func:`widened_covariances`: the glue only checks and calls."""
    if backend() != "numba":
        return None
    kept = _KEPT.get(memory)
    if kept is None or kept.params is not params:
        kept = _KEPT[memory] = _Kept(params, memory)
        if kept.pending.n_nodes != kept.n:
            del _KEPT[memory]
            return None
    Pa = np.ascontiguousarray(P, float)
    if Pa.ndim != 3:
        return None
    skeys, svals, in_place = kept.store_arrays()
    pending = kept.pending
    pkeys, pvals = pending.keys, pending.values  # (new each step: the witness pass's)
    if pkeys is not kept.pkeys:
        pkeys = kept.pending_keys()
    # (_rows_of inline, a call costs ~0.2 us a step in runs; the width: the pass checks)
    if pvals.ndim != 2 or pvals.dtype is not _FLOAT or not pvals.flags.c_contiguous:
        pvals = np.ascontiguousarray(pvals, float).reshape(len(pending), PENDING_WIDTH)
    opt, robots, values = kept.opt, kept.robots, kept.values
    args = (
        pkeys,
        pvals,
        kept.n,
        np.ascontiguousarray(links.i, np.int64),
        np.ascontiguousarray(links.j, np.int64),
        np.ascontiguousarray(links.channel_ok, np.bool_),
        skeys,
        svals,
        Pa,
        *kept.at,
        opt.consts,
    )
    largest, gates = 16, opt.gates
    while True:
        G, status, enumerated, written, widened = outvoted_pass(*args, gates, robots, values)
        if status >= 0:
            break
        largest = max(-status, 2 * largest)
        gates = consistency_gates(opt.p_fa, largest)
    if status == REFUSED:
        OUTVOTED_RUNS["fallbacks"] += 1
        return None
    if not (written and in_place):  # (a receiver not stored yet: the store inserts)
        kept.state.set(robots[:G], robots[:G], values[:G])
    OUTVOTED_RUNS["passes"] += 1
    OUTVOTED_RUNS["enumerated"] += enumerated
    return widened_covariances(Pa, robots, values, G) if widened else P
