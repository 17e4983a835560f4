"""The witness stage's statistic, compiled (twins of ``witness_statistic`` and
``witness_cusum`` of :mod:`resloc.cl.detection_witness`).

The statistic works on groups of notes: rows sorted by a group key, each group given by its
first row and its size, so that a group can be "the notes on j" (the team's statistic) or
"the notes on j that receiver r received" (the receivers' delivery,
:mod:`resloc.cl.kernels_witness_frames`, and the outvoted pass,
:mod:`resloc.cl.kernels_outvoted`, call these kernels).

=============================  ==========================================================
function                       numpy twin
=============================  ==========================================================
:func:`group_statistics`       :func:`~resloc.cl.detection_witness.reference_statistic`
                               (any grouping of the notes: rows sorted by a group key,
                               each group its first row and size)
:func:`terms_statistic`        the same, for one group given its notes' information
                               terms (``delivered_pass`` gives those it summed)
:func:`cusum_of`               :func:`~resloc.cl.detection_witness.witness_cusum`
=============================  ==========================================================

``witness_statistic`` and ``group_statistic`` run :func:`fast_statistic` and
:func:`fast_groups` when the backend is numba (every receiver's statistic, and the
compromised robot's oracle, which evaluates them a dozen times a step), else the numpy
spec.
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl.backend import backend
from resloc.cl.detection_witness import WitnessNotes, consistency_gates, liars_at, note_groups
from resloc.cl.kernels_math import jit_inline, jit_lanes
from resloc.cl.kernels_witness import WITNESS_RUNS
from resloc.cl.params import CLParams, at_robots

__all__ = [
    "SET_CHUNK",
    "cusum_of",
    "fast_groups",
    "fast_statistic",
    "group_statistics",
    "set_moments",
    "statistic_of_groups",
    "terms_statistic",
]


@jit_lanes
def set_moments(Sa, Sb, Sc, sa, sb, sq):
    """A set's summed information terms (:func:`~resloc.cl.detection_witness.set_statistic`)
    to ``(Ia, Ib, Ic, ma, mb, spread)``: ``Y_K^-1``'s entries, the set's mean and its spread
    ``c_K``, the compiled passes' one copy of that step."""
    dS = Sa * Sc - Sb * Sb
    Ia = Sc / dS
    Ib = -Sb / dS
    Ic = Sa / dS
    ma = Ia * sa + Ib * sb
    mb = Ib * sa + Ic * sb
    return Ia, Ib, Ic, ma, mb, sq - (ma * sa + mb * sb)


@jit_lanes
def _merge_set(best, tot, d0, d1, d2, d3, d4, d5, size, gates, P00, P01, P11):
    """``best`` and the statistic of the set ``tot (6,)`` minus the dropped notes' sums
    ``d0 .. d5``, of ``size`` notes, when it is consistent (a nan propagates, as
    ``np.minimum``)."""
    Ia, Ib, Ic, ma, mb, spread = set_moments(
        tot[0] - d0, tot[1] - d1, tot[2] - d2, tot[3] - d3, tot[4] - d4, tot[5] - d5
    )
    if size > 1 and not spread <= gates[size]:
        return best
    Ca = P00 + Ia
    Cb = P01 + Ib
    Cc = P11 + Ic
    stat = (Cc * ma * ma - 2.0 * Cb * ma * mb + Ca * mb * mb) / (Ca * Cc - Cb * Cb)
    if math.isnan(stat) or math.isnan(best):
        return np.nan
    return min(stat, best)


#: The sets are judged in chunks of this many, of one size (each chunk's statistics in one
#: loop LLVM vectorizes; the stop tested after each chunk): the columns of the scratch
#: ``drop (7, SET_CHUNK)`` :func:`terms_statistic` takes.
SET_CHUNK = 16


@jit_inline
def _chunk_statistics(tot, drop, lo, hi, size, gate, P00, P01, P11, stat):
    """``stat[k]`` for ``lo <= k < hi``: the statistic of the set ``tot`` minus the dropped
    sums ``drop[:, k]`` (``size`` notes), ``inf`` when it is not consistent (the
    ``_merge_set`` arithmetic, operation for operation: the same values; branch-free, so
    LLVM vectorizes the loop: the divisions were most of an enumeration's time)."""
    single = size <= 1
    for k in range(lo, hi):
        Sa = tot[0] - drop[0, k]
        Sb = tot[1] - drop[1, k]
        Sc = tot[2] - drop[2, k]
        sa = tot[3] - drop[3, k]
        sb = tot[4] - drop[4, k]
        sq = tot[5] - drop[5, k]
        dS = Sa * Sc - Sb * Sb
        Ia = Sc / dS
        Ib = -Sb / dS
        Ic = Sa / dS
        ma = Ia * sa + Ib * sb
        mb = Ib * sa + Ic * sb
        spread = sq - (ma * sa + mb * sb)
        Ca = P00 + Ia
        Cb = P01 + Ib
        Cc = P11 + Ic
        value = (Cc * ma * ma - 2.0 * Cb * ma * mb + Ca * mb * mb) / (Ca * Cc - Cb * Cb)
        stat[k] = value if (single or spread <= gate) else np.inf


@jit_inline
def _chunk(best, tot, drop, K, size, gates, P00, P01, P11, enough):
    """``best`` merged with the ``K`` sets of ``size`` notes whose dropped sums are
    ``drop[:6, :K]`` (row 6 scratch), in order; ``(best, stopped)``: stopped in the chunk
    (with no nan in it: its smallest, at most ``enough`` too, which is all the callers read
    of a stopped enumeration), as ``_merge_set`` one by one (a nan propagates)."""
    stat = drop[6]
    gate = gates[size] if size > 1 else np.inf
    _chunk_statistics(tot, drop, 0, K, size, gate, P00, P01, P11, stat)
    smallest = np.inf
    nan = math.isnan(best)
    for k in range(K):  # (branch-free: the chunk's smallest, whether a nan)
        v = stat[k]
        smallest = v if v < smallest else smallest
        nan = nan or v != v
    if not nan:  # the chunk's smallest: at most enough iff a set in it stops
        best = smallest if smallest < best else best
        return best, best <= enough
    for k in range(K):
        v = stat[k]
        if math.isnan(v) or math.isnan(best):
            best = np.nan
        elif v < best:
            best = v
        if best <= enough:
            return best, True
    return best, False


@jit_lanes
def _smallest(terms, tot, idx, kept, m, dmax, gates, P00, P01, P11, enough, drop):
    """The smallest statistic over the consistent sets of the ``m`` notes ``terms (m, 6)``
    (their sums ``tot (6,)``) left after dropping at most ``dmax``; the enumeration stops
    at the first set at most ``enough`` (-inf: every set). ``drop (7, SET_CHUNK)``: scratch."""
    best = np.inf
    best = _merge_set(best, tot, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, m, gates, P00, P01, P11)
    if best <= enough:
        return best
    # by the number dropped (a single far note, the usual reason a set needs enumerating,
    # is found first when the enumeration may stop early); each subset's dropped sums in
    # ascending index order, as the generic enumeration below, written out SET_CHUNK sets at
    # a time and their statistics computed together (a loop LLVM vectorizes)
    for deep in range(1, min(dmax, 3) + 1):
        K = 0
        for a in range(m):
            for b in range(a + 1 if deep >= 2 else m, m + 1 if deep == 1 else m):
                # (deep 1: b takes the one value m, no second note)
                if deep == 1:
                    d0, d1, d2 = terms[a, 0], terms[a, 1], terms[a, 2]
                    d3, d4, d5 = terms[a, 3], terms[a, 4], terms[a, 5]
                else:
                    d0, d1, d2 = (
                        terms[a, 0] + terms[b, 0],
                        terms[a, 1] + terms[b, 1],
                        terms[a, 2] + terms[b, 2],
                    )
                    d3, d4, d5 = (
                        terms[a, 3] + terms[b, 3],
                        terms[a, 4] + terms[b, 4],
                        terms[a, 5] + terms[b, 5],
                    )
                for c in range(b + 1 if deep == 3 else m, m + 1 if deep < 3 else m):
                    # (deep 1, 2: c takes the one value m, no third note)
                    if deep < 3:
                        drop[0, K], drop[1, K], drop[2, K] = d0, d1, d2
                        drop[3, K], drop[4, K], drop[5, K] = d3, d4, d5
                    else:
                        drop[0, K] = d0 + terms[c, 0]
                        drop[1, K] = d1 + terms[c, 1]
                        drop[2, K] = d2 + terms[c, 2]
                        drop[3, K] = d3 + terms[c, 3]
                        drop[4, K] = d4 + terms[c, 4]
                        drop[5, K] = d5 + terms[c, 5]
                    K += 1
                    if K == SET_CHUNK:
                        best, stopped = _chunk(
                            best, tot, drop, K, m - deep, gates, P00, P01, P11, enough
                        )
                        if stopped:
                            return best
                        K = 0
        if K:
            best, stopped = _chunk(best, tot, drop, K, m - deep, gates, P00, P01, P11, enough)
            if stopped:
                return best
    for d in range(4, dmax + 1):
        for t in range(d):
            idx[t] = t
        while True:
            for c in range(6):
                dropped = 0.0
                for t in range(d):
                    dropped += terms[idx[t], c]
                kept[c] = dropped
            best = _merge_set(
                best,
                tot,
                kept[0],
                kept[1],
                kept[2],
                kept[3],
                kept[4],
                kept[5],
                m - d,
                gates,
                P00,
                P01,
                P11,
            )
            if best <= enough:
                return best
            # the next combination of d of m positions (lexicographic)
            t = d - 1
            while t >= 0 and idx[t] == m - d + t:
                t -= 1
            if t < 0:
                break
            idx[t] += 1
            for t2 in range(t + 1, d):
                idx[t2] = idx[t2 - 1] + 1
    return best


@jit_lanes
def group_statistics(u, Q, P_pos, start, count, f, half_h, gates, enough, T, judged):
    """The step's statistic of every group of notes: group ``g`` is rows ``start[g] ..
    start[g] + count[g] - 1`` of ``u (E, 2)``, ``Q (E, 2, 2)``, ``P_pos (E, 2, 2)``;
    ``f (G,)`` the notes it may drop, ``half_h (G,)`` what a group with no consistent set
    counts, ``gates (M,)`` the consistency gate of a set of each size (``gates[n]``, n >= 2),
    ``enough (G,)``: the enumeration of group g may stop at a set whose statistic is at
    most ``enough[g]`` (its CUSUM then clips at 0 whatever the smallest: the receivers'
    pass), when the group's notes cannot make a nan short of an overflow (terms finite and
    under 1e100, ``Q`` positive definite, the claim positive semi-definite: every set's
    information and ``C`` positive definite); ``-inf``: the smallest (the spec's ``T``).
    Writes ``T (G,)`` (the smallest ``T_K`` over the consistent sets left after dropping at
    most ``f[g]`` notes; 0 where not judged) and ``judged (G,)`` (more than ``f[g]``
    notes). The sets are enumerated (every combination of dropped notes). Twin:
    :func:`~resloc.cl.detection_witness.witness_statistic` (the same sums in the same
    order)."""
    terms = np.zeros((max(count.max() if count.shape[0] else 0, 1), 6))
    idx = np.zeros(max(f.max() if f.shape[0] else 0, 1) + 1, np.int64)
    kept = np.zeros(6)
    drop = np.empty((7, SET_CHUNK))
    tot = np.zeros(6)
    for g in range(start.shape[0]):
        m = count[g]
        s0 = start[g]
        T[g] = 0.0
        judged[g] = m > f[g]
        if not judged[g]:
            continue
        t0 = t1 = t2 = t3 = t4 = t5 = 0.0  # (the sums in scalars, in the rows' order)
        big = s0
        best_trace = -np.inf
        wild = False  # (not tame: branch-free, every note's test ORed in)
        for k in range(m):
            e = s0 + k
            det = Q[e, 0, 0] * Q[e, 1, 1] - Q[e, 0, 1] * Q[e, 1, 0]
            wild = wild | (not Q[e, 0, 0] > 0.0) | (not det > 0.0)
            Ya = Q[e, 1, 1] / det
            Yb = -0.5 * (Q[e, 0, 1] + Q[e, 1, 0]) / det
            Yc = Q[e, 0, 0] / det
            ya = Ya * u[e, 0] + Yb * u[e, 1]
            yb = Yb * u[e, 0] + Yc * u[e, 1]
            q = u[e, 0] * ya + u[e, 1] * yb
            terms[k, 0] = Ya
            terms[k, 1] = Yb
            terms[k, 2] = Yc
            terms[k, 3] = ya
            terms[k, 4] = yb
            terms[k, 5] = q
            t0 += Ya
            t1 += Yb
            t2 += Yc
            t3 += ya
            t4 += yb
            t5 += q
            wild = wild | (not abs(Ya) < 1e100) | (not abs(Yb) < 1e100)
            wild = wild | (not abs(Yc) < 1e100) | (not abs(ya) < 1e100)
            wild = wild | (not abs(yb) < 1e100) | (not abs(q) < 1e100)
            trace = P_pos[e, 0, 0] + P_pos[e, 1, 1]
            if math.isnan(best_trace):
                pass  # (argmax: the first nan wins)
            elif math.isnan(trace) or trace > best_trace:  # (the first of equal traces)
                best_trace = trace
                big = e
        tot[0], tot[1], tot[2], tot[3], tot[4], tot[5] = t0, t1, t2, t3, t4, t5
        tame = not wild
        P00 = P_pos[big, 0, 0]
        P01 = 0.5 * (P_pos[big, 0, 1] + P_pos[big, 1, 0])
        P11 = P_pos[big, 1, 1]
        T[g] = terms_statistic(
            terms, tot, m, tame, P00, P01, P11, f[g], half_h[g], gates, enough[g], idx, kept, drop
        )


@jit_lanes
def terms_statistic(terms, tot, m, tame, P00, P01, P11, f, half_h, gates, enough, idx, kept, drop):
    """The statistic of one judged group (:func:`group_statistics`) from its ``m`` notes'
    information terms ``terms[:m]`` (rows ``Y``'s three entries, ``Y u``, ``u^T Y u``, in
    the group's order) and their sums ``tot (6,)`` (in that order); ``tame``: every note's
    ``Q`` positive definite and every term under 1e100 in size; ``P00``, ``P01``, ``P11``:
    the position block of the note with the largest claim; ``idx``, ``kept``, ``drop (7,
    SET_CHUNK)``: scratch. The receivers' pass gives the terms it summed its sets with
    (:mod:`resloc.cl.kernels_witness_frames`: the same values, computed once per note)."""
    dmax = min(f, m - 1)
    # no set can make a nan (a nan anywhere counts h / 2): the stop is exact
    safe = tame and P00 >= 0.0 and P11 >= 0.0 and P00 * P11 - P01 * P01 >= 0.0
    safe = safe and abs(P00) < 1e100 and abs(P01) < 1e100 and abs(P11) < 1e100
    stop = enough if safe else -np.inf
    # the whole set first, here: most groups stop at it, and a call of the enumeration
    # costs ~60 ns (it starts with the same merge)
    best = _merge_set(np.inf, tot, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, m, gates, P00, P01, P11)
    if not best <= stop:
        best = _smallest(terms, tot, idx, kept, m, dmax, gates, P00, P01, P11, stop, drop)
    return best if math.isfinite(best) else half_h


@jit_lanes
def cusum_of(S, T, judged, k, h, out):
    """``clip(S + min(T, h / 2) - k, 0, 2 h)`` (``T`` counted only where ``judged``), all
    ``(G,)``, into ``out``. Twin: :func:`~resloc.cl.detection_witness.witness_cusum`."""
    for g in range(S.shape[0]):
        step = min(T[g], 0.5 * h[g]) if judged[g] else 0.0
        v = S[g] + step - k[g]
        out[g] = min(max(v, 0.0), 2.0 * h[g])


def statistic_of_groups(
    notes: WitnessNotes, params: CLParams, rows, start, count, f, half_h
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`group_statistics` of the groups ``start``, ``count`` (G,) of ``rows`` of
    ``notes`` (each group's notes consecutive in ``rows``): ``(T, judged)``."""
    G = len(start)
    T = np.zeros(G)
    judged = np.zeros(G, np.bool_)
    if G == 0:
        return T, judged
    rows = np.asarray(rows)
    gates = consistency_gates(float(np.max(params.witness_false_alarm)), int(np.max(count)))
    group_statistics(
        np.ascontiguousarray(notes.u[rows], dtype=float),
        np.ascontiguousarray(notes.Q[rows], dtype=float),
        np.ascontiguousarray(notes.P_pos[rows], dtype=float),
        np.ascontiguousarray(start, dtype=np.int64),
        np.ascontiguousarray(count, dtype=np.int64),
        np.ascontiguousarray(f, dtype=np.int64),
        np.ascontiguousarray(half_h, dtype=float),
        gates,
        np.full(G, -np.inf),
        T,
        judged,
    )
    WITNESS_RUNS["statistics"] += 1
    return T, judged


def fast_statistic(
    notes: WitnessNotes, params: CLParams, robots: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """:func:`~resloc.cl.detection_witness.witness_statistic` compiled (the groups: the
    notes on each robot); None with the numpy backend."""
    if backend() != "numba":
        return None
    rows, ids, start, count = note_groups(notes, robots)
    T, judged = fast_groups(notes, params, rows, start, count, ids)
    return ids, T, judged


def fast_groups(notes, params, rows, start, count, ids) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`~resloc.cl.detection_witness.group_statistic` compiled (group ``g`` on robot
    ``ids[g]``); None with the numpy backend."""
    if backend() != "numba":
        return None
    f = liars_at(params, ids)
    half_h = 0.5 * np.broadcast_to(np.asarray(at_robots(params.witness_h, ids), float), ids.shape)
    return statistic_of_groups(notes, params, rows, start, count, f, half_h)
