"""The stores of the detector's and the defence's stages for one step, by one call per group.

The ``full`` defence keeps six :class:`~resloc.cl.memory.LinkStatistic` stores: the NIS
and mean-shift CUSUMs keyed by link ``(i, j)`` (:func:`resloc.cl.kernels_detection.detector_state`)
and the robot CUSUM and the recovery's three keyed ``(i, i)``
(:func:`resloc.cl.kernels_defence.defence_state`). Stores keyed alike hold the same keys in
a run's steady state, so :func:`group_slots` gives every store of a group the slots of one
look-up and, in the same compiled call (:func:`resloc.cl.kernels_memory.slots_and_snapshot`),
copies each store's values into a buffer the group keeps for
:meth:`~resloc.cl.kernels_detection.DetectorState.undo` (reused from step to step: ``undo``
only runs within the step that saved). Before, each store paid a look-up or a comparison of
keys, and a numpy copy, its own.

A group is known to be in its steady state by identity: it remembers every store's keys and
values arrays, which a store replaces when it inserts (and ``undo`` puts the old ones
back); the keys are compared only when one of them changed. Anything else (a link not
stored yet, arrays not as the compiled path passes them) answers None and the caller takes
the store-by-store path, the only one that inserts.

A group also keeps the stage's state built on it (:func:`keep_state`): on a later step with
the same parameters, stores and number of links, :func:`steady_state` gives it back after
the group's call, with no kernel tuple or ``undo`` record built again.
"""

from __future__ import annotations

import numpy as np

from resloc.cl import kernels_memory
from resloc.cl.kernels_memory import int64_rows, same_keys

__all__ = ["StoreGroup", "group_slots", "keep_state", "steady_state"]

_EMPTY = np.zeros(0)


class StoreGroup:
    """Stores with the same keys and the buffers their values are saved in (kept by the
    first store, :attr:`LinkStatistic.group <resloc.cl.memory.LinkStatistic>`)."""

    __slots__ = ("arrays", "call", "keys", "pos", "saved", "state", "stores", "views")

    def __init__(self, stores: tuple, keys: np.ndarray) -> None:
        self.stores = stores
        self.keys = keys  # the stores' keys (the first's array; the others' are equal)
        # (store, its keys, its values) when the group was built, flat
        self.arrays = tuple(a for s in stores for a in (s, s.keys, s.values))
        values = tuple(s.values for s in stores)
        flat = tuple(v.reshape(-1) for v in values)  # C-contiguous: views
        buffers = tuple(np.empty_like(f) for f in flat)
        self.views = tuple(b.reshape(v.shape) for b, v in zip(buffers, values, strict=True))
        # the compiled call for the group's size (up to two stores: four arguments fewer)
        size = 2 if len(stores) <= 2 else 4
        four = kernels_memory.slots_and_snapshot
        self.call = kernels_memory.slots_and_snapshot2 if size == 2 else four
        pad = (_EMPTY,) * (size - len(stores))
        # the compiled call's arguments after the links: (values, buffer) per store, padded
        self.saved = tuple(a for pair in zip(flat + pad, buffers + pad, strict=True) for a in pair)
        # the slots, reused from step to step (read within the step that looked them up)
        self.pos = np.empty(0, np.int64)
        # (key, the stage's state built on the group's arrays: keep_state), or None
        self.state = None

    def current(self, stores: tuple) -> bool:
        """Whether ``stores`` are this group's, each with the arrays it was built on."""
        if len(stores) * 3 != len(self.arrays):
            return False
        arrays = self.arrays
        k = 0
        for store in stores:  # (a loop of identity tests: zip and all() cost twice as much)
            if store is not arrays[k]:
                return False
            if store.keys is not arrays[k + 1] or store.values is not arrays[k + 2]:
                return False
            k += 3
        return True


def _float_rows(values) -> bool:
    return type(values) is np.ndarray and values.dtype == np.float64 and values.flags.c_contiguous


def _build(stores: tuple) -> StoreGroup | None:
    """A group of ``stores`` when their keys are equal and their values as the compiled
    path takes them; None otherwise."""
    keys = int64_rows(stores[0].keys)
    if keys is None or len(stores) > 4:
        return None
    for store in stores:
        other = int64_rows(store.keys)
        if other is None or not same_keys(keys, other):
            return None
        if not _float_rows(store.values) or len(store.values) != len(keys):
            return None
    return StoreGroup(stores, keys)


def group_slots(stores: tuple, i: np.ndarray, j: np.ndarray, saved: list) -> np.ndarray | None:
    """The slots of links ``(i, j)`` in every one of ``stores`` (up to four stores holding
    the same keys), recording in ``saved`` what
    :meth:`~resloc.cl.kernels_detection.DetectorState.undo` needs to put each back; None,
    nothing recorded, when a link is not stored yet or the stores do not form a group.

    ``i``, ``j``: int64 (E,), sorted by key (as :func:`~resloc.cl.kernels_memory.stored_positions`
    takes them). The slots array is the group's, rewritten by its next call (the next
    step's)."""
    ri = int64_rows(i)
    rj = ri if j is i else int64_rows(j)
    if ri is None or rj is None or len(ri) != len(rj):
        return None
    group = stores[0].group
    if group is None or not group.current(stores):
        group = _build(stores)
        if group is None:
            return None
        stores[0].group = group
    pos = group.pos
    if len(pos) != len(ri):
        pos = group.pos = np.empty(len(ri), np.int64)
    if not group.call(group.keys, stores[0].n_nodes, ri, rj, pos, *group.saved):
        return None
    for store, view in zip(stores, group.views, strict=True):
        saved.append((store, store.keys, None, pos, view))
    return pos


def keep_state(stores: tuple, key, state, slots: np.ndarray) -> None:
    """Remember ``state`` (a :class:`~resloc.cl.kernels_detection.DetectorState` built by
    ``key``, the step's :class:`~resloc.cl.params.CLParams`, on ``stores``' group with the
    group's ``slots``) for :func:`steady_state`; nothing when ``slots`` are not the
    group's (the store-by-store path)."""
    group = stores[0].group
    if group is not None and slots is group.pos:
        group.state = (key, state)


def steady_state(stores: tuple, key, i: np.ndarray, j: np.ndarray):
    """The state :func:`keep_state` remembered for ``key`` on ``stores``' group, after this
    step's look-up of links ``(i, j)`` into the group's slots and the save of every
    store's values into the group's buffers (:func:`group_slots`' call); None (the caller
    builds the state, nothing done) when the group is not in its steady state: another
    ``key``, a store with new arrays, a step with another number of links or a link not
    stored.

    Everything the state holds is the group's and the stores' own arrays (the values,
    written in place by the loops; the slots and the buffers, rewritten by each call), so
    one built on an earlier step of the same arrays is this step's: a step of the full
    defence rebuilt two kernel tuples, their gains' look-ups and the ``undo`` records,
    ~1 us of Python each."""
    group = stores[0].group
    if group is None or group.state is None or group.state[0] is not key:
        return None
    ri = int64_rows(i)
    rj = ri if j is i else int64_rows(j)
    pos = group.pos
    if ri is None or rj is None or len(ri) != len(pos) or len(rj) != len(pos):
        return None
    if not group.current(stores):
        return None
    if not group.call(group.keys, stores[0].n_nodes, ri, rj, pos, *group.saved):
        return None
    return group.state[1]
