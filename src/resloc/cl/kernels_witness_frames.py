"""The receivers' witness statistic, compiled in one pass per step.

Twin of :func:`~resloc.cl.detection_witness_frames.reference_delivered_store` (the numpy
specification: ``pending_notes``, ``received_groups``, ``whole_set_statistic``, the skip
rule of ``received_state``, ``received_statistic``, ``witness_cusum`` and the decay of the
silent pairs). :func:`delivered_pass` reads the pending notes and the statistic store as
they lie in the memory and returns the new store's keys and values; the numpy glue per
step (sorting, ``unique``, the stores' searches) was most of the stage's cost.

The grouping is a counting sort, the ids being small ints: the step's links are bucketed
by receiver; each receiver's senders (itself first among them, in ascending id order) are
walked in ascending order, so the rows on one robot arrive in ascending row order (the
pending rows are sorted by (observer, on)); a per-robot counter, reset only where touched,
places them by the robot they are on. Each group's whole set is judged; a group left at 0
by a consistent whole set skips the enumeration (the spec's rule), the others are
enumerated by :func:`~resloc.cl.kernels_witness.group_statistics`, each distinct set of
notes once (identified, as the spec does, by the sum of a random 64-bit word per row),
stopping at the first consistent set whose statistic clips every group holding the set at
0 (``S + T - k <= 0``: the smallest would give the same 0; the spec enumerates them all).
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl.backend import backend
from resloc.cl.kernels_math import jit_lanes
from resloc.cl.kernels_witness import WITNESS_RUNS, group_statistics
from resloc.cl.memory import LinkStatistic
from resloc.cl.params import CLParams, at_robots

__all__ = ["delivered_pass", "fast_delivered", "fast_record", "record_in_place"]


@jit_lanes
def _insertion_sort(a, lo, hi):
    """``a[lo:hi]`` sorted in place (short segments)."""
    for t in range(lo + 1, hi):
        v = a[t]
        s = t - 1
        while s >= lo and a[s] > v:
            a[s + 1] = a[s]
            s -= 1
        a[s + 1] = v


@jit_lanes
def delivered_pass(
    pkeys, pvals, words, n, li, lj, ok, skeys, svals, on_ok, f_at, k_at, h_at, gates
):
    """The statistic store after the pending notes arrive with this step's frames.

    Parameters
    ----------
    pkeys, pvals : ndarray, shapes (P,), (P, 11)
        The pending store (keys ``observer * n + on``, sorted; values ``u``, ``Q``,
        ``P_pos``, waiting flag: :data:`~resloc.cl.detection_witness_frames.PENDING`).
    words : ndarray of uint64, shape (P,)
        A random odd word per pending row: a set of rows is identified by their sum.
    n : int
        The id space.
    li, lj, ok : ndarray, shape (E,)
        The step's links: receiver, sender, channel ok.
    skeys, svals : ndarray, shapes (S,), (S,)
        The statistic store keyed ``r * n + j`` (sorted).
    on_ok : ndarray of bool, shape (n,)
        The robots judged (the others' notes and statistics dropped).
    f_at, k_at, h_at : ndarray, shape (n,)
        ``witness_liars`` (int64), ``witness_k``, ``witness_h`` of each robot.
    gates : ndarray, shape (M,)
        ``gates[c]``: the consistency gate of ``c`` notes.

    Returns
    -------
    keys, values : ndarray, shapes (K,), (K,)
        The new store (sorted keys).
    need : int
        Distinct sets of notes enumerated; ``-c`` (c > 0) when ``gates`` stops short of a
        group of ``c`` notes.
    """
    P = pkeys.shape[0]
    rows = np.empty(P, np.int64)
    m = 0
    for p in range(P):
        if pvals[p, 10] > 0.0 and on_ok[pkeys[p] % n]:
            rows[m] = p
            m += 1
    # each observer's rows: rows[ofirst[o]:ofirst[o + 1]] (keys sorted: by observer, on)
    ofirst = np.zeros(n + 1, np.int64)
    row_on = np.empty(m, np.int64)  # the robot each row is on (one division a row)
    pterm = np.empty((P, 6))  # each row's information terms (once a row, not a receiver)
    for t in range(m):
        e = rows[t]
        ofirst[pkeys[e] // n + 1] += 1
        row_on[t] = pkeys[e] % n
        Q00, Q01, Q10, Q11 = pvals[e, 2], pvals[e, 3], pvals[e, 4], pvals[e, 5]
        u0, u1 = pvals[e, 0], pvals[e, 1]
        det = Q00 * Q11 - Q01 * Q10
        Ya = Q11 / det
        Yb = -0.5 * (Q01 + Q10) / det
        Yc = Q00 / det
        ya = Ya * u0 + Yb * u1
        yb = Yb * u0 + Yc * u1
        pterm[e, 0] = Ya
        pterm[e, 1] = Yb
        pterm[e, 2] = Yc
        pterm[e, 3] = ya
        pterm[e, 4] = yb
        pterm[e, 5] = u0 * ya + u1 * yb
    for o in range(n):
        ofirst[o + 1] += ofirst[o]
    # each receiver's senders: itself and the links' senders whose channel is ok (ascending)
    rfirst = np.zeros(n + 1, np.int64)
    E = li.shape[0]
    for e in range(E):
        if ok[e]:
            rfirst[li[e] + 1] += 1
    for r in range(n):
        rfirst[r + 1] += rfirst[r] + 1
    senders = np.empty(rfirst[n], np.int64)
    fill = rfirst[:n].copy()
    for r in range(n):
        senders[fill[r]] = r
        fill[r] += 1
    for e in range(E):
        if ok[e]:
            senders[fill[li[e]]] = lj[e]
            fill[li[e]] += 1
    total = 0
    for r in range(n):
        _insertion_sort(senders, rfirst[r], rfirst[r + 1])
        for s in range(rfirst[r], rfirst[r + 1]):
            o = senders[s]
            total += ofirst[o + 1] - ofirst[o]
    # the groups: (receiver, on) ascending, rows ascending within a group
    grows = np.empty(total, np.int64)
    gkey = np.empty(total, np.int64)
    gstart = np.empty(total, np.int64)
    gcount = np.empty(total, np.int64)
    per_on = np.zeros(n, np.int64)
    touched = np.empty(n, np.int64)
    G = 0
    M = 0
    largest = 0
    for r in range(n):
        nt = 0
        for s in range(rfirst[r], rfirst[r + 1]):
            o = senders[s]
            for t in range(ofirst[o], ofirst[o + 1]):
                on = row_on[t]
                if on == r:
                    continue
                if per_on[on] == 0:
                    touched[nt] = on
                    nt += 1
                per_on[on] += 1
        _insertion_sort(touched, 0, nt)
        pos = M
        for a in range(nt):
            on = touched[a]
            c = per_on[on]
            gkey[G] = r * n + on
            gstart[G] = pos
            gcount[G] = c
            largest = max(largest, c)
            per_on[on] = pos  # now the next free slot of the group
            pos += c
            G += 1
        for s in range(rfirst[r], rfirst[r + 1]):
            o = senders[s]
            for t in range(ofirst[o], ofirst[o + 1]):
                on = row_on[t]
                if on == r:
                    continue
                grows[per_on[on]] = rows[t]
                per_on[on] += 1
        for a in range(nt):
            per_on[touched[a]] = 0
        M = pos
    if largest >= gates.shape[0]:
        return np.empty(0, np.int64), np.empty(0), -largest
    # each group's S (0 for a pair never judged), whole set and skip rule
    S = np.zeros(G)
    T = np.zeros(G)
    judged = np.zeros(G, np.bool_)
    consistent = np.zeros(G, np.bool_)
    unclaimed = False
    ns = skeys.shape[0]
    for g in range(G):
        key = gkey[g]
        p = np.searchsorted(skeys, key)
        if p < ns and skeys[p] == key:
            S[g] = svals[p]
        Sa = Sb = Sc = sa = sb = sq = 0.0
        best_trace = -np.inf
        nan_trace = False
        big = grows[gstart[g]]
        for q in range(gstart[g], gstart[g] + gcount[g]):
            e = grows[q]
            Sa += pterm[e, 0]
            Sb += pterm[e, 1]
            Sc += pterm[e, 2]
            sa += pterm[e, 3]
            sb += pterm[e, 4]
            sq += pterm[e, 5]
            trace = pvals[e, 6] + pvals[e, 9]
            if math.isnan(trace):
                nan_trace = True
            elif trace > best_trace:  # (the first of equal traces)
                best_trace = trace
                big = e
        if nan_trace:
            unclaimed = True
        dS = Sa * Sc - Sb * Sb
        Ia = Sc / dS
        Ib = -Sb / dS
        Ic = Sa / dS
        ma = Ia * sa + Ib * sb
        mb = Ib * sa + Ic * sb
        spread = sq - (ma * sa + mb * sb)
        c = gcount[g]
        Ca = pvals[big, 6] + Ia
        Cb = 0.5 * (pvals[big, 7] + pvals[big, 8]) + Ib
        Cc = pvals[big, 9] + Ic
        T[g] = (Cc * ma * ma - 2.0 * Cb * ma * mb + Ca * mb * mb) / (Ca * Cc - Cb * Cb)
        consistent[g] = (c < 2 or spread <= gates[c]) and math.isfinite(T[g])
        judged[g] = c > f_at[key % n]
    # the groups to enumerate, each distinct set of notes once (most receivers hold the
    # same notes on a robot): a set's word is its rows' sum mixed with the robot and the
    # size (a collision of two different sets has probability ~G^2 / 2^64)
    rep = np.full(G, -1, np.int64)
    dkey = np.empty(G, np.uint64)
    dgroup = np.empty(G, np.int64)
    n_need = 0
    m_need = 0
    for g in range(G):
        if unclaimed:  # a claim that is not a number: every set enumerated
            T[g] = np.nan
            consistent[g] = False
        k = k_at[gkey[g] % n]
        if judged[g] and consistent[g] and S[g] + T[g] - k <= 0.0:
            continue
        w = np.uint64(gkey[g] % n) * np.uint64(0x9E3779B97F4A7C15)
        w += np.uint64(gcount[g]) * np.uint64(0xC2B2AE3D27D4EB4F)
        for q in range(gstart[g], gstart[g] + gcount[g]):
            w += words[grows[q]]
        for a in range(n_need):
            if dkey[a] == w:
                rep[g] = a
                break
        if rep[g] < 0:
            dkey[n_need] = w
            dgroup[n_need] = g
            rep[g] = n_need
            n_need += 1
            m_need += gcount[g]
    if n_need:
        u = np.empty((m_need, 2))
        Q = np.empty((m_need, 2, 2))
        Pp = np.empty((m_need, 2, 2))
        nstart = np.empty(n_need, np.int64)
        ncount = np.empty(n_need, np.int64)
        nf = np.empty(n_need, np.int64)
        nhalf = np.empty(n_need)
        # a set may stop at a statistic that clips every group holding it at 0
        stop = np.full(n_need, np.inf)
        for g in range(G):
            a = rep[g]
            if a >= 0:
                v = k_at[gkey[g] % n] - S[g]
                stop[a] = -np.inf if math.isnan(v) else min(stop[a], v)
        q2 = 0
        for a in range(n_need):
            g = dgroup[a]
            nstart[a] = q2
            ncount[a] = gcount[g]
            nf[a] = f_at[gkey[g] % n]
            nhalf[a] = 0.5 * h_at[gkey[g] % n]
            for q in range(gstart[g], gstart[g] + gcount[g]):
                e = grows[q]
                u[q2, 0] = pvals[e, 0]
                u[q2, 1] = pvals[e, 1]
                Q[q2, 0, 0] = pvals[e, 2]
                Q[q2, 0, 1] = pvals[e, 3]
                Q[q2, 1, 0] = pvals[e, 4]
                Q[q2, 1, 1] = pvals[e, 5]
                Pp[q2, 0, 0] = pvals[e, 6]
                Pp[q2, 0, 1] = pvals[e, 7]
                Pp[q2, 1, 0] = pvals[e, 8]
                Pp[q2, 1, 1] = pvals[e, 9]
                q2 += 1
        Tn = np.zeros(n_need)
        jn = np.zeros(n_need, np.bool_)
        group_statistics(u, Q, Pp, nstart, ncount, nf, nhalf, gates, stop, Tn, jn)
        for g in range(G):
            if rep[g] >= 0:
                T[g] = Tn[rep[g]]
    # the new store: the groups' CUSUM merged with the silent pairs' decay (keys sorted)
    keys = np.empty(G + ns, np.int64)
    values = np.empty(G + ns)
    K = 0
    p = 0
    for g in range(G + 1):
        key = gkey[g] if g < G else 9223372036854775807
        while p < ns and skeys[p] < key:
            j0 = skeys[p] % n
            if on_ok[j0]:
                v = svals[p] - k_at[j0]
                keys[K] = skeys[p]
                values[K] = v if (v > 0.0 or math.isnan(v)) else 0.0
                K += 1
            p += 1
        if p < ns and g < G and skeys[p] == key:
            p += 1
        if g == G:
            break
        j0 = key % n
        h = h_at[j0]
        Tg = T[g]
        step = 0.0
        if judged[g]:
            step = Tg if (math.isnan(Tg) or Tg < 0.5 * h) else 0.5 * h
        v = S[g] + step - k_at[j0]
        if not math.isnan(v):
            v = min(max(v, 0.0), 2.0 * h)
        keys[K] = key
        values[K] = v
        K += 1
    return keys[:K], values[:K], n_need


def _per_robot(value, n: int, dtype=float) -> np.ndarray:
    """A parameter at every robot id ``0 .. n - 1``, shape (n,)."""
    a = np.asarray(value, float)
    if a.ndim == 0:
        return np.full(n, a, dtype)
    return np.ascontiguousarray(at_robots(a, np.arange(n)), dtype=dtype)


def fast_delivered(params: CLParams, memory, i, j, channel_ok, robots=None) -> LinkStatistic | None:
    """:func:`~resloc.cl.detection_witness_frames.delivered_store` by :func:`delivered_pass`;
    None with the numpy backend."""
    if backend() != "numba":
        return None
    from resloc.cl.detection_witness import STATE, consistency_gates
    from resloc.cl.detection_witness_frames import PENDING, PENDING_WIDTH, row_words

    stat = memory.stage_statistic(STATE)
    pending = memory.stage_statistic(PENDING, width=PENDING_WIDTH)
    n = stat.n_nodes
    on_ok = np.ones(n, np.bool_)
    if robots is not None:
        on_ok[:] = False
        on_ok[np.asarray(robots, np.int64)] = True
    f_at = _per_robot(np.rint(params.witness_liars), n, np.int64)
    k_at, h_at = _per_robot(params.witness_k, n), _per_robot(params.witness_h, n)
    p_fa = float(np.max(params.witness_false_alarm))
    largest = 16
    args = (
        np.ascontiguousarray(pending.keys, np.int64),
        np.ascontiguousarray(pending.values, float).reshape(len(pending), PENDING_WIDTH),
        row_words(len(pending)),
        n,
        np.ascontiguousarray(i, np.int64),
        np.ascontiguousarray(j, np.int64),
        np.ascontiguousarray(channel_ok, np.bool_),
        np.ascontiguousarray(stat.keys, np.int64),
        np.ascontiguousarray(stat.values, float),
        on_ok,
        f_at,
        k_at,
        h_at,
    )
    while True:
        keys, values, need = delivered_pass(*args, consistency_gates(p_fa, largest))
        if need >= 0:
            break
        largest = max(-need, 2 * largest)
    out = LinkStatistic(n)
    out.keys, out.values = keys, values
    WITNESS_RUNS["delivered"] += 1
    WITNESS_RUNS["enumerated"] += need
    return out


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
