"""Compiled look-ups of the per-link memory (:mod:`resloc.cl.memory`) for its steady state.

After a run's first steps every link of a step is already stored: the compiled path then
asks the stores for the positions of the step's links (:meth:`LinkStatistic.slots
<resloc.cl.memory.LinkStatistic.slots>`, a few per step with the detector's and defence's
stages) and overwrites the delivered links' estimates (:meth:`LinkMemory.store
<resloc.cl.memory.LinkMemory.store>`, ``cached`` neighbour estimates). In numpy each is a
handful of calls (keys, ``searchsorted``, the check that every key was found, the
scatters), about ten microseconds; here one call. Each function returns False, having
written nothing, when a link is not stored yet: the caller then inserts it by the numpy
code, the only code that inserts.

=============================  ==================================================
kernel function                numpy twin
=============================  ==================================================
:func:`stored_positions`       ``np.searchsorted`` of the keys, every key found
:func:`overwrite_stored`       ``LinkMemory.store`` when every link is stored
:func:`overwrite_delivered`    ``LinkMemory.store`` of a step's delivered links
:func:`same_keys`              ``np.array_equal`` of two stores' keys
:func:`slots_and_snapshot`     :func:`stored_positions` and ``values.copy()`` of up
                               to four stores holding the same keys (``...2``: two)
:func:`gather_cached`          ``LinkMemory.lookup`` and the ``np.where`` of the
                               stored and transmitted rows (``cached``)
:func:`store_gathered`         ``LinkMemory.store`` of the delivered links at the
                               positions :func:`gather_cached` found
=============================  ==================================================
"""

from __future__ import annotations

import numpy as np

from resloc.cl.kernels_math import jit, jit_inline, lower_bound

__all__ = [
    "gather_cached",
    "overwrite_delivered",
    "overwrite_stored",
    "same_keys",
    "slots_and_snapshot",
    "slots_and_snapshot2",
    "store_gathered",
    "stored_positions",
]


@jit
def _position(keys, key):
    """Position of ``key`` in the sorted ``keys`` (``np.searchsorted``, side left), -1 when
    it is not there."""
    lo = lower_bound(keys, key, 0, keys.shape[0])
    if lo < keys.shape[0] and keys[lo] == key:
        return lo
    return -1


@jit
def _walk(keys, key, last, p, first):
    """The position of ``key`` in the sorted ``keys`` (-1 when it is not there), walking on
    from ``p``, the previous key's (``last``) position; searched from the start for the
    ``first`` key or one out of order."""
    if first or key < last:
        return _position(keys, key)
    if key > last:
        p += 1
        while p < keys.shape[0] and keys[p] < key:
            p += 1
        if p >= keys.shape[0] or keys[p] != key:
            return -1
    return p


@jit
def stored_positions(keys, n_nodes, i, j, pos):
    """``pos[e]``: the position of link ``(i[e], j[e])`` (key ``i * n_nodes + j``) in the
    sorted ``keys`` (shapes (E,), int64); False (``pos`` partly written) when a link is not
    stored. Links come sorted by key (by observer, then neighbour; a per-robot store's key
    repeats on the robot's rows): the next one is found by walking on from the last one's
    position (both lists once, where a binary search per link cost several microseconds a
    call); the first key and one out of order are searched. Written as one loop: through
    :func:`_walk` the 260 links of a step took 4.1 us, here 0.75."""
    K = keys.shape[0]
    last = -1
    p = 0
    for e in range(i.shape[0]):
        key = i[e] * n_nodes + j[e]
        if e == 0 or key < last:  # binary search (np.searchsorted, side left)
            p = lower_bound(keys, key, 0, K)
        while p < K and keys[p] < key:
            p += 1
        if p >= K or keys[p] != key:
            return False
        pos[e] = p
        last = key
    return True


@jit_inline
def _copy(values, saved):
    for k in range(values.shape[0]):
        saved[k] = values[k]


@jit
def slots_and_snapshot(keys, n_nodes, i, j, pos, v0, s0, v1, s1, v2, s2, v3, s3):
    """:func:`stored_positions` of links ``(i, j)`` in ``keys`` into ``pos``, then ``s[:] =
    v[:]`` for each of the four pairs (1-D float64, equal lengths within a pair; an unused
    pair is two empty arrays): the look-up and the copies for ``undo`` of up to four stores
    holding the same keys in one call, where each was a call of its own (a numpy copy, ~0.4
    us). False, nothing copied, when a link is not stored."""
    if not stored_positions(keys, n_nodes, i, j, pos):
        return False
    _copy(v0, s0)
    _copy(v1, s1)
    _copy(v2, s2)
    _copy(v3, s3)
    return True


@jit
def slots_and_snapshot2(keys, n_nodes, i, j, pos, v0, s0, v1, s1):
    """:func:`slots_and_snapshot` of up to two stores (four array arguments fewer: a
    compiled call's dispatch costs ~0.07 us an argument)."""
    if not stored_positions(keys, n_nodes, i, j, pos):
        return False
    _copy(v0, s0)
    _copy(v1, s1)
    return True


@jit
def overwrite_stored(keys, n_nodes, i, j, x, P, norm, mem_x, mem_P, mem_last, pos):
    """``mem_x[p] = x[e]``, ``mem_P[p] = P[e]``, ``mem_last[p] = norm[e]`` at the position
    ``p`` of every link ``(i[e], j[e])`` when every link is stored (``pos``: (E,) int64
    scratch); False, nothing written, when one is not."""
    if not stored_positions(keys, n_nodes, i, j, pos):
        return False
    for e in range(i.shape[0]):
        p = pos[e]
        for a in range(3):
            mem_x[p, a] = x[e, a]
            for b in range(3):
                mem_P[p, a, b] = P[e, a, b]
        mem_last[p] = norm[e]
    return True


@jit
def same_keys(a, b):
    """Whether the keys ``a`` and ``b`` (int64, (K,)) are equal (``np.array_equal``: a
    few microseconds of dispatch for the ~300 keys of a step, here a fraction of one)."""
    if a.shape[0] != b.shape[0]:
        return False
    for k in range(a.shape[0]):
        if a[k] != b[k]:
            return False
    return True


def int64_rows(a) -> np.ndarray | None:
    """``a`` when it is a C-contiguous one-dimensional int64 array (what the compiled
    look-ups take without a conversion), else None."""
    if type(a) is np.ndarray and a.dtype == np.int64 and a.ndim == 1 and a.flags.c_contiguous:
        return a
    return None


@jit
def overwrite_delivered(keys, n_nodes, i, j, delivered, rows, x, P, norm, mem, pos):
    """For every link ``e`` with ``delivered[e]`` (links sorted by key, as
    :func:`stored_positions` takes them): ``mem_x[p] = x[rows[e]]``, ``mem_P[p] =
    P[rows[e]]``, ``mem_last[p] = norm[e]`` at the position ``p`` of ``(i[e], j[e])``
    (``mem = (mem_x, mem_P, mem_last)``; ``pos``: (E,) int64 scratch). False, nothing
    written, when a delivered link is not stored. Twin: ``LinkMemory.store`` of the rows
    ``delivered`` selects."""
    last = -1
    p = 0
    d = 0
    for e in range(i.shape[0]):
        if not delivered[e]:
            continue
        key = i[e] * n_nodes + j[e]
        p = _walk(keys, key, last, p, d == 0)
        if p < 0:
            return False
        pos[d] = p
        d += 1
        last = key
    mem_x, mem_P, mem_last = mem
    d = 0
    for e in range(i.shape[0]):
        if not delivered[e]:
            continue
        _write_row(pos[d], rows[e], norm[e], x, P, mem_x, mem_P, mem_last)
        d += 1
    return True


@jit
def gather_cached(
    keys, n_nodes, mem_x, mem_P, mem_last, li, lj, rows, x_nb, P_nb, x_link, P_link, x_ref,
    P_ref, known, last, pos,
):  # fmt: skip
    """The per-link inputs of ``cached`` neighbour estimates in one pass (``mem_x``,
    ``mem_P``, ``mem_last``: the store's arrays; the others written): per link ``e``,
    ``x_link[e] = x_nb[rows[e]]`` (``P`` alike), the position ``pos[e]`` of ``(li[e],
    lj[e])`` in the sorted ``keys`` (-1: not stored; a binary search), ``known[e] = pos[e]
    >= 0``, ``x_ref[e]`` the stored estimate where known, else the transmitted one (``P``
    alike), and, when ``last`` is not empty, the stored last norm (else 0).
    Twin: ``LinkMemory.lookup`` and the ``np.where`` of the stored and transmitted rows
    (``resloc.cl.step._decide``)."""
    K = keys.shape[0]
    for e in range(li.shape[0]):
        n = rows[e]
        key = li[e] * n_nodes + lj[e]
        lo = lower_bound(keys, key, 0, K)
        found = lo < K and keys[lo] == key
        q = lo if found else -1
        pos[e] = q
        known[e] = found
        for a in range(3):
            x_link[e, a] = x_nb[n, a]
            x_ref[e, a] = mem_x[q, a] if found else x_nb[n, a]
            for b in range(3):
                P_link[e, a, b] = P_nb[n, a, b]
                P_ref[e, a, b] = mem_P[q, a, b] if found else P_nb[n, a, b]
        if last.shape[0] > 0:
            last[e] = mem_last[q] if found else 0.0


@jit
def store_gathered(pos, delivered, rows, x, P, norm, mem_x, mem_P, mem_last):
    """For every link ``e`` with ``delivered[e]``: ``mem_x[pos[e]] = x[rows[e]]``,
    ``mem_P[pos[e]] = P[rows[e]]``, ``mem_last[pos[e]] = norm[e]`` (``pos``: the positions
    :func:`gather_cached` found in the same keys; ``mem_x``, ``mem_P``, ``mem_last``: the
    store's arrays).
    False, nothing written, when a delivered link was not stored (``pos[e] < 0``).
    Twin: ``LinkMemory.store`` of the rows ``delivered`` selects."""
    for e in range(pos.shape[0]):
        if delivered[e] and pos[e] < 0:
            return False
    for e in range(pos.shape[0]):
        if not delivered[e]:
            continue
        _write_row(pos[e], rows[e], norm[e], x, P, mem_x, mem_P, mem_last)
    return True


@jit_inline
def _write_row(p, r, norm, x, P, mem_x, mem_P, mem_last):
    """The store's row ``p`` takes ``x[r]``, ``P[r]`` and the link's ``norm``."""
    for a in range(3):
        mem_x[p, a] = x[r, a]
        for b in range(3):
            mem_P[p, a, b] = P[r, a, b]
    mem_last[p] = norm
