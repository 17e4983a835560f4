"""The receivers' witness statistic, compiled in one pass per step.

Twin of :func:`~resloc.cl.detection_witness_frames.reference_delivered_store` (the numpy
specification: ``pending_notes``, ``received_groups``, ``whole_set_statistic``, the skip
rule of ``received_state``, ``received_statistic``, ``witness_cusum`` and the decay of the
silent pairs). :func:`delivered_pass` reads the pending notes and the statistic store as
they lie in the memory and returns the new store's keys and values; the numpy glue per
step (sorting, ``unique``, the stores' searches) was most of the stage's cost.

The groups are sets of observers, the ids being small ints: receiver r holds the notes on
robot j of the observers it heard this step (itself, and the senders of its links whose
channel is ok), i.e. the mask of j's observers ANDed with the mask of r's senders (one
64-bit word per 64 ids). Each distinct (j, mask) is one set of notes, its rows in
ascending order (the pending rows are sorted by (observer, on)), judged once: most
receivers hold the same notes on a robot, and the sums over a set's rows, the step's
float work, are done once per set instead of once per receiver (the spec identifies the
sets by a random 64-bit word per row; the masks identify them exactly). A receiver that
holds a frame twice (a duplicate link) gets sets of its own, with the rows repeated as
the spec repeats them. Each set's whole set is judged; a group left at 0 by a consistent
whole set skips the enumeration (the spec's rule), the others' sets are enumerated by
:func:`~resloc.cl.kernels_witness_statistic.terms_statistic` (``group_statistics``' enumeration, on
the information terms the sums used: computed once per note), each once, stopping at the
first consistent subset whose statistic clips every group holding the set at 0 (``S + T -
k <= 0``: the smallest would give the same 0; the spec enumerates them all). The store is
made dense (``n * n``) for the pass: the new one comes out in key order. The notes are
written into the pending store by :mod:`resloc.cl.kernels_witness_pending`.
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl.backend import backend
from resloc.cl.kernels_math import jit_lanes
from resloc.cl.kernels_witness import WITNESS_RUNS
from resloc.cl.kernels_witness_statistic import SET_CHUNK, set_moments, terms_statistic
from resloc.cl.memory import LinkStatistic
from resloc.cl.params import CLParams, at_robots

__all__ = ["delivered_pass", "fast_delivered", "per_robot"]


@jit_lanes
def _bit(o):
    """Observer ``o``'s bit in its word ``o // 64`` of a set's mask."""
    return np.uint64(1) << np.uint64(o & 63)


@jit_lanes
def delivered_pass(pkeys, pvals, n, li, lj, ok, skeys, svals, on_ok, f_at, k_at, h_at, gates):
    """The statistic store after the pending notes arrive with this step's frames.

    Parameters
    ----------
    pkeys, pvals : ndarray, shapes (P,), (P, 11)
        The pending store (keys ``observer * n + on``, sorted; values ``u``, ``Q``,
        ``P_pos``, waiting flag: :data:`~resloc.cl.detection_witness_frames.PENDING`).
    n : int
        The id space (every id in ``li``, ``lj`` and the keys below ``n``).
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
    S : ndarray, shape (n * n,)
        The new store dense (``S[r * n + j]``, 0 for a pair it does not hold).
    """
    W = (n + 63) // 64
    NN = n * n
    # the waiting rows on each robot j, by observer (ascending: the pending keys are
    # sorted by (observer, on)): jrows[jfirst[j] : jfirst[j + 1]], with each row's
    # information terms, claimed trace, whether Q is positive definite and observer in
    # jterm, jobs (read in that order);
    # notes_on[j]: the observers' mask
    Pn = pkeys.shape[0]
    jfirst = np.zeros(n + 1, np.int64)
    notes_on = np.zeros((n, W), np.uint64)
    # (the scratch in a few blocks: an allocation costs about what a set's sums do)
    p_rows = np.empty((2, Pn), np.int64)
    p_obs = p_rows[0]  # each row's observer and robot (no division a row: the keys ascend)
    p_on = p_rows[1]
    o = 0
    for p in range(Pn):
        key = pkeys[p]
        while key >= (o + 1) * n:
            o += 1
        on = key - o * n
        p_obs[p] = o
        p_on[p] = on
        if pvals[p, 10] > 0.0 and on_ok[on]:
            jfirst[on + 1] += 1
            notes_on[on, o >> 6] |= _bit(o)
    for j in range(n):
        jfirst[j + 1] += jfirst[j]
    j_rows = np.empty((2, jfirst[n]), np.int64)
    jrows = j_rows[0]
    jobs = j_rows[1]
    jterm = np.empty((jfirst[n], 8))
    fill = jfirst[:n].copy()
    for p in range(Pn):
        on = p_on[p]
        if not (pvals[p, 10] > 0.0 and on_ok[on]):
            continue
        t = fill[on]
        fill[on] += 1
        jrows[t] = p
        Q00, Q01, Q10, Q11 = pvals[p, 2], pvals[p, 3], pvals[p, 4], pvals[p, 5]
        u0, u1 = pvals[p, 0], pvals[p, 1]
        det = Q00 * Q11 - Q01 * Q10
        Ya = Q11 / det
        Yb = -0.5 * (Q01 + Q10) / det
        Yc = Q00 / det
        ya = Ya * u0 + Yb * u1
        yb = Yb * u0 + Yc * u1
        jterm[t, 0] = Ya
        jterm[t, 1] = Yb
        jterm[t, 2] = Yc
        jterm[t, 3] = ya
        jterm[t, 4] = yb
        jterm[t, 5] = u0 * ya + u1 * yb
        jterm[t, 6] = pvals[p, 6] + pvals[p, 9]
        jterm[t, 7] = 1.0 if (Q00 > 0.0 and det > 0.0) else 0.0  # (Q positive definite)
        jobs[t] = p_obs[p]
    # each receiver's frames: itself and the senders of its links whose channel is ok
    # (times[r * n + o]: how often; a receiver holding a frame twice has its own sets)
    per_pair = np.empty((5, NN), np.int64)
    times = per_pair[0]
    times[:] = 0
    heard = np.zeros((n, W), np.uint64)
    twice = np.zeros(n, np.bool_)
    for r in range(n):
        times[r * n + r] = 1
        heard[r, r >> 6] |= _bit(r)
    for e in range(li.shape[0]):
        if ok[e]:
            r, o = li[e], lj[e]
            times[r * n + o] += 1
            twice[r] = twice[r] or times[r * n + o] > 1
            heard[r, o >> 6] |= _bit(o)
    # each group (r, j): the notes on j that r received, as a set of observers; each
    # distinct set listed (its rows ascending, as the spec's groups) and judged once: its
    # whole set's statistic and consistency, whether it is judged (more than f notes)
    set_of = per_pair[1]
    set_of[:] = -1
    s_on = per_pair[2]
    s_recv = per_pair[3]  # a receiver holding it (its rows: the frames' counts)
    s_count = per_pair[4]
    smask = np.empty((NN, W), np.uint64)
    flags = np.zeros((5, NN), np.bool_)
    s_shared, consistent, judged, held, enumerate_ = (
        flags[0],
        flags[1],
        flags[2],
        flags[3],
        flags[4],
    )
    floats = np.zeros((3, NN))
    T, S_old, S_new = floats[0], floats[1], floats[2]
    unclaimed = False
    largest = 0
    D = 0
    widest = 0
    for j in range(n):
        widest = max(widest, jfirst[j + 1] - jfirst[j])
    pre = np.zeros((widest + 1, 6))
    pre_best = np.full(widest + 1, -np.inf)
    pre_big = np.full(widest + 1, -1, np.int64)
    pre_nan = np.zeros(widest + 1, np.bool_)
    for j in range(n):
        if not on_ok[j] or jfirst[j + 1] == jfirst[j]:
            continue
        first = D
        # the running sums over j's rows in order (the sets that hold every row up to a
        # position start from them: the same sums, in the same order)
        m0, mj = jfirst[j], jfirst[j + 1] - jfirst[j]
        for t in range(mj):
            for col in range(6):
                pre[t + 1, col] = pre[t, col] + jterm[m0 + t, col]
            trace = jterm[m0 + t, 6]
            pre_nan[t + 1] = pre_nan[t] or math.isnan(trace)
            pre_best[t + 1] = pre_best[t]
            pre_big[t + 1] = pre_big[t]
            if not math.isnan(trace) and (pre_big[t] < 0 or trace > pre_best[t]):
                pre_best[t + 1] = trace  # (the first of equal traces)
                pre_big[t + 1] = jrows[m0 + t]
        for r in range(n):
            if r == j:
                continue
            empty = True
            for w in range(W):
                if notes_on[j, w] & heard[r, w]:
                    empty = False
            if empty:
                continue
            found = -1
            if not twice[r]:
                for a in range(first, D):
                    if s_shared[a]:
                        same = True
                        for w in range(W):
                            if smask[a, w] != notes_on[j, w] & heard[r, w]:
                                same = False
                        if same:
                            found = a
                            break
            set_of[r * n + j] = D if found < 0 else found
            if found >= 0:
                continue
            for w in range(W):
                smask[D, w] = notes_on[j, w] & heard[r, w]
            s_shared[D] = not twice[r]
            s_on[D] = j
            s_recv[D] = r
            rn = r * n
            x1 = 0  # the rows before the first one r did not receive (all, twice: none)
            while not twice[r] and x1 < mj and times[rn + jobs[m0 + x1]] > 0:
                x1 += 1
            c = x1
            Sa, Sb, Sc, sa, sb, sq = (
                pre[x1, 0],
                pre[x1, 1],
                pre[x1, 2],
                pre[x1, 3],
                pre[x1, 4],
                pre[x1, 5],
            )
            best_trace = pre_best[x1]
            big = pre_big[x1]
            unclaimed = unclaimed or pre_nan[x1]
            for t in range(m0 + x1, m0 + mj):
                copies = times[rn + jobs[t]]
                while copies > 0:  # (once, but for a frame received twice)
                    copies -= 1
                    c += 1
                    Sa += jterm[t, 0]
                    Sb += jterm[t, 1]
                    Sc += jterm[t, 2]
                    sa += jterm[t, 3]
                    sb += jterm[t, 4]
                    sq += jterm[t, 5]
                    trace = jterm[t, 6]
                    if math.isnan(trace):
                        unclaimed = True
                    elif big < 0 or trace > best_trace:  # (the first of equal traces)
                        best_trace = trace
                        big = jrows[t]
            s_count[D] = c
            largest = max(largest, c)
            big = big if big >= 0 else jrows[jfirst[j]]  # (every claim nan: unclaimed)
            Ia, Ib, Ic, ma, mb, spread = set_moments(Sa, Sb, Sc, sa, sb, sq)
            Ca = pvals[big, 6] + Ia
            Cb = 0.5 * (pvals[big, 7] + pvals[big, 8]) + Ib
            Cc = pvals[big, 9] + Ic
            T[D] = (Cc * ma * ma - 2.0 * Cb * ma * mb + Ca * mb * mb) / (Ca * Cc - Cb * Cb)
            gate = gates[c] if c < gates.shape[0] else np.inf
            consistent[D] = (c < 2 or spread <= gate) and math.isfinite(T[D])
            judged[D] = c > f_at[j]
            D += 1
    if largest >= gates.shape[0]:
        return np.empty(0, np.int64), np.empty(0), -largest, np.empty(0)
    if unclaimed:  # a claim that is not a number: every set enumerated
        T[:D] = np.nan
        consistent[:D] = False
    # the old store dense; the groups whose set must be enumerated (the skip rule: a
    # consistent whole set that leaves S at 0 needs no smaller statistic), each set once,
    # stopping at a statistic that clips every group holding the set at 0
    for p in range(skeys.shape[0]):
        S_old[skeys[p]] = svals[p]
        held[skeys[p]] = True
    per_set = np.zeros((2, D))
    stop, Tn = per_set[0], per_set[1]
    stop[:] = np.inf
    wanted = np.zeros(D, np.bool_)
    for key in range(NN):
        a = set_of[key]
        if a < 0 or not judged[a]:
            continue  # (a group not judged counts no statistic)
        k = k_at[s_on[a]]
        if consistent[a] and S_old[key] + T[a] - k <= 0.0:
            continue
        enumerate_[key] = True
        wanted[a] = True
        v = k - S_old[key]
        stop[a] = -np.inf if math.isnan(v) else min(stop[a], v)
    # each wanted set's statistic from its rows' terms as summed above (the same values
    # group_statistics would compute from the notes: computed once per note)
    need = 0
    widest_set = 1
    for a in range(D):
        if wanted[a]:
            need += 1
            widest_set = max(widest_set, s_count[a])
    if need:
        terms = np.empty((widest_set, 6))
        idx = np.zeros(max(f_at.max(), 1) + 1, np.int64)
        kept = np.zeros(6)
        drop = np.empty((7, SET_CHUNK))
        tot = np.zeros(6)
        for a in range(D):
            if not wanted[a]:
                continue
            j = s_on[a]
            rn = s_recv[a] * n
            m = 0
            tot[:] = 0.0
            tame = True
            big = jrows[jfirst[j]]
            best_trace = -np.inf
            for t in range(jfirst[j], jfirst[j + 1]):
                for _ in range(times[rn + jobs[t]]):  # (its rows, as summed)
                    tame = tame and jterm[t, 7] > 0.0
                    for col in range(6):
                        terms[m, col] = jterm[t, col]
                        tot[col] += jterm[t, col]
                        tame = tame and abs(jterm[t, col]) < 1e100
                    trace = jterm[t, 6]
                    if m == 0:
                        big = jrows[t]
                    if math.isnan(best_trace):
                        pass  # (argmax: the first nan wins, as group_statistics)
                    elif math.isnan(trace) or trace > best_trace:
                        best_trace = trace
                        big = jrows[t]
                    m += 1
            P01 = 0.5 * (pvals[big, 7] + pvals[big, 8])
            Tn[a] = terms_statistic(
                terms, tot, m, tame, pvals[big, 6], P01, pvals[big, 9], f_at[j],
                0.5 * h_at[j], gates, stop[a], idx, kept, drop,
            )  # fmt: skip
    # the new store: each group's CUSUM, the silent pairs' decay (keys ascending)
    keys = np.empty(NN, np.int64)
    values = np.empty(NN)
    K = 0
    for key in range(NN):
        if set_of[key] < 0 and not held[key]:
            continue
        j0 = key % n
        a = set_of[key]
        if a >= 0:
            h = h_at[j0]
            step = 0.0
            if judged[a]:
                Tg = Tn[a] if enumerate_[key] else T[a]
                step = Tg if (math.isnan(Tg) or Tg < 0.5 * h) else 0.5 * h
            v = S_old[key] + step - k_at[j0]
            if not math.isnan(v):
                v = min(max(v, 0.0), 2.0 * h)
        elif on_ok[j0]:
            v = S_old[key] - k_at[j0]
            v = v if (v > 0.0 or math.isnan(v)) else 0.0
        else:
            continue
        keys[K] = key
        values[K] = v
        S_new[key] = v
        K += 1
    return keys[:K], values[:K], need, S_new


def per_robot(value, n: int, dtype=float) -> np.ndarray:
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
    from resloc.cl.detection_witness_frames import PENDING, PENDING_WIDTH

    stat = memory.stage_statistic(STATE)
    pending = memory.stage_statistic(PENDING, width=PENDING_WIDTH)
    n = stat.n_nodes
    i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
    if len(i) and (min(i.min(), j.min()) < 0 or max(i.max(), j.max()) >= n):
        return None  # (ids beyond the memory's: the numpy spec)
    on_ok = np.ones(n, np.bool_)
    if robots is not None:
        on_ok[:] = False
        on_ok[np.asarray(robots, np.int64)] = True
    f_at = per_robot(np.rint(params.witness_liars), n, np.int64)
    k_at, h_at = per_robot(params.witness_k, n), per_robot(params.witness_h, n)
    p_fa = float(np.max(params.witness_false_alarm))
    largest = 16
    args = (
        np.ascontiguousarray(pending.keys, np.int64),
        np.ascontiguousarray(pending.values, float).reshape(len(pending), PENDING_WIDTH),
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
        keys, values, need, _ = delivered_pass(*args, consistency_gates(p_fa, largest))
        if need >= 0:
            break
        largest = max(-need, 2 * largest)
    out = LinkStatistic(n)
    out.keys, out.values = keys, values
    WITNESS_RUNS["delivered"] += 1
    WITNESS_RUNS["enumerated"] += need
    return out
