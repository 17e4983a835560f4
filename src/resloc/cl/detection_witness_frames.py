"""Witness notes as they travel: each receiver judges the notes it received.

The notes of step ``t`` (:func:`~resloc.cl.detection_witness.step_notes`) wait in the
memory (:func:`record_witness`, at the end of the step) and travel in each observer's frame
of step ``t + 1``, one frame per robot and step whatever the event trigger decides for its
estimate messages, over the link's channel: receiver r gets observer o's frame when the
step has the link (r, o) (in sensing and radio range) and its channel draw lets o's
messages to r through (``channel_ok``: the CDZ's jamming, the same draw as o's estimate
message to r that step), and it holds its own notes. At the start of step ``t + 1``
(:func:`deliver_witness`, before any verdict) every receiver r updates its own statistic
``S_{r,j}`` on every robot j with the notes on j it received (the statistic of
:mod:`resloc.cl.detection_witness` on that set of notes; a pair that received none decays
by ``k``); receiver r discards the links (r, j) while ``S_{r,j} > h``
(:class:`~resloc.cl.detection_witness.WitnessCheck`).

Most receivers hold the same notes on a robot (the default team is nearly fully
connected): :func:`received_statistic` judges each distinct set of notes once.
:func:`delivered_store` and :func:`record_witness` run their compiled twins
(:mod:`resloc.cl.kernels_witness_frames`, :mod:`resloc.cl.kernels_witness_pending`) with
the numba backend; the numpy functions here
are their specification (:func:`reference_delivered_store`, :func:`reference_record`).
"""

from __future__ import annotations

import numpy as np

from resloc.cl.detection_witness import (
    STATE,
    WitnessNotes,
    consistency_gates,
    group_statistic,
    liars_at,
    note_information,
    set_statistic,
    witness_cusum,
)
from resloc.cl.memory import LinkMemory, LinkStatistic
from resloc.cl.params import CLParams, at_robots

__all__ = [
    "PENDING",
    "deliver_witness",
    "delivered_store",
    "pending_notes",
    "put_store",
    "received_groups",
    "received_state",
    "received_statistic",
    "record_witness",
    "reference_delivered_store",
    "reference_record",
    "row_words",
    "whole_set_statistic",
]

#: The notes of the step before, waiting for this step's frames, keyed (observer, j):
#: ``u`` (2), ``Q`` (4), ``P_pos`` (4), then 1 for a note waiting (0: none).
PENDING = "witness_pending"
_PENDING_WIDTH = 11
PENDING_WIDTH = _PENDING_WIDTH


def pending_notes(memory: LinkMemory) -> WitnessNotes:
    """The notes the observers sent with this step's frames (the step before's, sent)."""
    store = memory.stage_statistic(PENDING, width=_PENDING_WIDTH)
    v = store.values
    keep = np.flatnonzero(v[:, 10] > 0.0)
    keys = store.keys[keep]
    v = v[keep]
    n = len(keep)
    return WitnessNotes(
        v[:, 0:2],
        v[:, 2:6].reshape(n, 2, 2),
        v[:, 6:10].reshape(n, 2, 2),
        keys // store.n_nodes,
        keys % store.n_nodes,
        np.ones(n, bool),
    )


#: Per note row, a random 64-bit word: a group's set of rows is identified by their sum.
_ROW_WORDS: list[np.ndarray] = [np.zeros(0, np.uint64)]


def row_words(n: int) -> np.ndarray:
    """A random odd 64-bit word per note row ``0 .. n - 1`` (fixed for the run)."""
    if len(_ROW_WORDS[0]) < n:
        rng = np.random.default_rng(20261127)
        size = max(n, 2 * len(_ROW_WORDS[0]), 1024)
        _ROW_WORDS[0] = rng.integers(0, 2**63, size, dtype=np.uint64) * np.uint64(2) + np.uint64(1)
    return _ROW_WORDS[0][:n]


def _ranges(lo: np.ndarray, count: np.ndarray) -> np.ndarray:
    """``concatenate([arange(l, l + c) for l, c in zip(lo, count)])``."""
    total = int(count.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    first = np.cumsum(count) - count
    return np.repeat(lo - first, count) + np.arange(total)


def received_groups(
    notes: WitnessNotes,
    i: np.ndarray,
    j: np.ndarray,
    channel_ok: np.ndarray,
    robots: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The notes each receiver holds: receiver r gets observer o's frame when this step
    has the link (r, o) and its channel is ok (``channel_ok``, the draw o's estimate
    message to r gets), and its own notes; never the notes on itself.

    Parameters
    ----------
    notes : WitnessNotes
        The notes sent (only the ``sent`` rows travel).
    i, j, channel_ok : ndarray, shape (E,)
        The step's links: receiver, sender, whether the sender's message gets through.
    robots : ndarray of int, optional
        Only the notes on these robots.

    Returns
    -------
    receiver, on : ndarray of int, shape (G,)
        Each group's receiver and the robot its notes are on (sorted by receiver, then on).
    rows : ndarray of int, shape (M,)
        Rows of ``notes``, group after group (ascending within a group).
    start, count : ndarray of int, shape (G,)
        Each group's first position in ``rows`` and its size.
    """
    sel = np.flatnonzero(notes.sent)
    if robots is not None:
        sel = sel[np.isin(notes.j[sel], robots)]
    by_obs = sel[np.argsort(notes.i[sel], kind="stable")]
    obs = notes.i[by_obs]
    ok = np.flatnonzero(channel_ok)
    own = np.unique(obs)
    recv = np.concatenate([np.asarray(i)[ok], own]).astype(np.int64)
    sender = np.concatenate([np.asarray(j)[ok], own]).astype(np.int64)
    lo = np.searchsorted(obs, sender, side="left")
    n = np.searchsorted(obs, sender, side="right") - lo
    rows = by_obs[_ranges(lo, n)]
    recv = np.repeat(recv, n)
    keep = notes.j[rows] != recv
    recv, rows = recv[keep], rows[keep]
    order = np.lexsort((rows, notes.j[rows], recv))
    recv, rows = recv[order], rows[order]
    on = notes.j[rows]
    if len(rows) == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty, empty, empty, empty
    new = np.r_[True, (recv[1:] != recv[:-1]) | (on[1:] != on[:-1])]
    start = np.flatnonzero(new)
    count = np.diff(np.r_[start, len(rows)])
    return recv[start], on[start], rows, start, count


def received_statistic(
    notes: WitnessNotes, params: CLParams, on: np.ndarray, rows, start, count
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`group_statistic` of the receivers' groups (:func:`received_groups`), each
    distinct set of notes judged once (most receivers hold the same notes on a robot)."""
    G = len(start)
    if G == 0:
        return np.zeros(0), np.zeros(0, bool)
    words = row_words(len(notes))[rows]
    sums = np.add.reduceat(words, start) if len(rows) else np.zeros(G, np.uint64)
    # one word per group: the rows' sum mixed with the robot and the size (a collision of
    # two different sets has probability ~G^2 / 2^64)
    mix = np.asarray(on, np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    mix += np.asarray(count, np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
    key = (sums + mix).view(np.int64)
    _, first, back = np.unique(key, return_index=True, return_inverse=True)
    rep_rows = rows[_ranges(start[first], count[first])]
    rep_start = np.cumsum(count[first]) - count[first]
    T, judged = group_statistic(notes, params, rep_rows, rep_start, count[first], on[first])
    back = back.ravel()
    return T[back], judged[back]


def received_state(
    notes: WitnessNotes,
    params: CLParams,
    state,
    i: np.ndarray,
    j: np.ndarray,
    channel_ok: np.ndarray,
    robots: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every receiver's ``S_{r,j}`` after the notes it received this step (:func:`received_
    groups`), from ``state`` (a :class:`~resloc.cl.memory.LinkStatistic` keyed (r, j)):
    ``(receiver, on, S)``, shapes (G,)."""
    recv, on, rows, start, count = received_groups(notes, i, j, channel_ok, robots)
    k = np.broadcast_to(np.asarray(at_robots(params.witness_k, on), float), on.shape)
    h = np.broadcast_to(np.asarray(at_robots(params.witness_h, on), float), on.shape)
    S = state.get(recv, on)
    T, consistent = whole_set_statistic(notes, params, rows, start, count)
    judged = count > liars_at(params, on)
    # A pair whose whole set of notes is consistent and leaves S at 0 needs no smaller
    # statistic (the smallest is at most the whole set's, and the CUSUM clips at 0): its
    # sets are not enumerated (the honest steady state: most pairs).
    need = np.flatnonzero(~(judged & consistent & (S + T - k <= 0.0)))
    if len(need):
        sub = rows[_ranges(start[need], count[need])]
        T[need], _ = received_statistic(
            notes, params, on[need], sub, np.cumsum(count[need]) - count[need], count[need]
        )
    return recv, on, witness_cusum(S, T, judged, k, h)


def whole_set_statistic(
    notes: WitnessNotes, params: CLParams, rows, start, count
) -> tuple[np.ndarray, np.ndarray]:
    """Each group's ``T_K`` and consistency for ``K`` all its notes (no note dropped),
    shapes (G,), by the formulas of :func:`~resloc.cl.detection_witness.reference_groups`."""
    G = len(start)
    if G == 0:
        return np.zeros(0), np.zeros(0, bool)
    P = notes.P_pos[rows]
    sums = np.add.reduceat(note_information(notes.u[rows], notes.Q[rows]), start)
    # j's claim: the first largest trace of the group's claims
    trace = P[:, 0, 0] + P[:, 1, 1]
    group = np.repeat(np.arange(G), count)
    top = np.flatnonzero(trace == np.repeat(np.maximum.reduceat(trace, start), count))
    _, first = np.unique(group[top], return_index=True)
    if len(first) != G:  # a claim that is not a number: every set enumerated
        return np.full(G, np.nan), np.zeros(G, bool)
    Pj = P[top[first]]
    spread, T = set_statistic(sums, Pj[:, 0, 0], 0.5 * (Pj[:, 0, 1] + Pj[:, 1, 0]), Pj[:, 1, 1])
    p_fa = float(np.max(params.witness_false_alarm))
    gate = consistency_gates(p_fa, int(count.max()))[count]
    consistent = (count < 2) | (spread <= gate)
    return T, consistent & np.isfinite(T)


def delivered_store(
    params: CLParams,
    memory: LinkMemory,
    i: np.ndarray,
    j: np.ndarray,
    channel_ok: np.ndarray,
    robots: np.ndarray | None = None,
) -> LinkStatistic:
    """The statistic store (keyed (r, j)) after the notes waiting in ``memory`` arrive
    with this step's frames (the step's links: receivers ``i``, senders ``j``,
    ``channel_ok``, shapes (E,)); pairs that received no note decay by ``k``. ``memory`` is
    unchanged (the CL step puts the result in it: :func:`deliver_witness`). ``robots``:
    only the statistics on these robots (the store then holds no other). In one robot's
    process the store its runtime delivered (``memory.delivered_witness``, put there by
    :meth:`~resloc.cl.node.RobotNode.receive_witness`) is taken instead. The compiled
    pass with the numba backend (:func:`~resloc.cl.kernels_witness_frames.fast_delivered`),
    else the numpy spec."""
    if memory.delivered_witness is not None:  # one robot's process: delivered over the wire
        store, memory.delivered_witness = memory.delivered_witness, None
        return store
    from resloc.cl.kernels_witness_frames import fast_delivered  # numba's import, on first use

    fast = fast_delivered(params, memory, i, j, channel_ok, robots)
    if fast is not None:
        return fast
    return reference_delivered_store(params, memory, i, j, channel_ok, robots)


def reference_delivered_store(
    params: CLParams,
    memory: LinkMemory,
    i: np.ndarray,
    j: np.ndarray,
    channel_ok: np.ndarray,
    robots: np.ndarray | None = None,
) -> LinkStatistic:
    """:func:`delivered_store` in numpy (its executable specification)."""
    stat = memory.stage_statistic(STATE)
    recv, on, S = received_state(pending_notes(memory), params, stat, i, j, channel_ok, robots)
    n = stat.n_nodes
    silent = stat.keys[~np.isin(stat.keys, recv * n + on)]
    if robots is not None:
        silent = silent[np.isin(silent % n, robots)]
    if len(silent):
        r0, j0 = silent // n, silent % n
        k = np.broadcast_to(np.asarray(at_robots(params.witness_k, j0), float), j0.shape)
        recv = np.concatenate([recv, r0])
        on = np.concatenate([on, j0])
        S = np.concatenate([S, np.maximum(stat.get(r0, j0) - k, 0.0)])
    out = LinkStatistic(n)
    out.set(recv, on, S)
    return out


def deliver_witness(params: CLParams, memory: LinkMemory | None, links) -> None:
    """The notes of the step before arrive with this step's frames (at the start of the
    step, before any verdict): every receiver's statistic is updated in ``memory``."""
    if memory is None:
        raise ValueError("detector witness (params.witness) needs a LinkMemory")
    put_store(memory, delivered_store(params, memory, links.i, links.j, links.channel_ok))


def put_store(memory: LinkMemory, store: LinkStatistic) -> None:
    """Make ``store`` the receivers' statistic in ``memory``."""
    stat = memory.stage_statistic(STATE)
    stat.keys, stat.values = store.keys, store.values


def record_witness(notes: WitnessNotes | None, params: CLParams, memory: LinkMemory | None):
    """Keep the step's sent notes in ``memory`` for the next step's frames (at the end of
    the step)."""
    if notes is None:
        return
    if memory is None:
        raise ValueError("detector witness (params.witness) needs a LinkMemory")
    from resloc.cl.kernels_witness_pending import fast_record  # numba's import, on first use

    if not fast_record(notes, memory):
        reference_record(notes, memory)


def reference_record(notes: WitnessNotes, memory: LinkMemory) -> None:
    """:func:`record_witness` in numpy (its executable specification)."""
    store = memory.stage_statistic(PENDING, width=_PENDING_WIDTH)
    rows = np.flatnonzero(notes.sent)
    n = len(rows)
    pos = store.slots(notes.i[rows], notes.j[rows])  # (the missing links inserted)
    v = store.values
    v[:, 10] = 0.0
    v[pos, 0:2] = notes.u[rows]
    v[pos, 2:6] = notes.Q[rows].reshape(n, 4)
    v[pos, 6:10] = notes.P_pos[rows].reshape(n, 4)
    v[pos, 10] = 1.0
