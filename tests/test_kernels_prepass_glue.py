"""The compiled glue of the defences' pre-passes.

* The comparison of two per-link stores' keys (:func:`resloc.cl.kernels_memory.same_keys`):
  the detector stages that see every link of every step share one store's slots when their
  keys are equal (``kernels_detection.shared_slots``); it gives ``np.array_equal``'s answer
  and runs.
* Zone trust's restore of the pre-passes' state on the rows it withheld or substituted
  (:func:`resloc.cl.kernels_zone.restore_unjudged`): the numpy restore's result, and it
  runs.
* The per-robot stores of the defence share the first one's slots
  (``kernels_defence.defence_state``) and put everything back on ``undo``."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.cl import (
    kernels,
    kernels_detection,
    kernels_memory,
    kernels_zone,
    kernels_zone_verdicts,
)
from resloc.cl.kernels_defence import defence_state
from resloc.cl.memory import LinkMemory, LinkStatistic
from resloc.cl.params import CLParams

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")


@pytest.mark.parametrize(
    "a, b",
    [
        ([1, 5, 9], [1, 5, 9]),
        ([1, 5, 9], [1, 5, 8]),
        ([1, 5, 9], [1, 5]),
        ([], []),
        ([7], [3]),
        ([0, 2, 4, 6], [0, 2, 4, 7]),
    ],
)
def test_same_keys_is_array_equal(a, b) -> None:
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    assert kernels_memory.same_keys(a, b) == np.array_equal(a, b)


def _spy_same_keys(monkeypatch) -> list:
    """Records every result of the compiled key comparison (``kernels_detection.same_keys``)."""
    calls = []
    real = kernels_detection.same_keys

    def spy(a, b):
        calls.append(real(a, b))
        return calls[-1]

    monkeypatch.setattr(kernels_detection, "same_keys", spy)
    return calls


def test_shared_slots_compares_the_keys_compiled(monkeypatch) -> None:
    calls = _spy_same_keys(monkeypatch)
    i, j = np.array([0, 0, 1, 2]), np.array([1, 2, 0, 1])
    store, other = LinkStatistic(3), LinkStatistic(3)
    slots = other.slots(i, j)
    store.slots(i, j)
    saved: list = []
    assert kernels_detection.shared_slots(store, other, slots, saved) is slots
    assert calls == [True] and len(saved) == 1
    store.slots(np.array([2]), np.array([0]))  # one key more: not shared
    assert kernels_detection.shared_slots(store, other, slots, saved) is None
    other.slots(np.array([2]), np.array([2]))  # as many keys, one different
    assert kernels_detection.shared_slots(store, other, other.slots(i, j), saved) is None
    assert calls == [True, False]


def _store_with_values(rng, n_nodes: int, i, j, width: int) -> LinkStatistic:
    store = LinkStatistic(n_nodes, width=width)
    store.slots(i, j)
    store.values[...] = rng.normal(size=store.values.shape)
    return store


def test_zone_restores_the_unjudged_rows_compiled() -> None:
    """Rows 1 and 3 withheld / substituted: their slots get the saved values back, every
    other slot keeps what the step wrote; the numpy restore agrees."""
    rng = np.random.default_rng(3)
    i, j = np.array([0, 0, 1, 2, 2]), np.array([1, 2, 0, 0, 1])
    results = []
    for compiled in (True, False):
        store = _store_with_values(rng if compiled else np.random.default_rng(3), 3, i, j, 6)
        saved: list = []
        slots = kernels_detection.store_slots(store, i, j, saved)
        before = store.values.copy()
        store.values += 1.0  # what the step's pre-pass wrote
        verdict = np.array(
            [0, kernels_zone_verdicts.WITHHELD, 0, kernels_zone_verdicts.SUBSTITUTED, 0]
        )
        if compiled:
            runs = kernels_zone.RESTORE_RUNS["compiled"]
            state = kernels_detection.DetectorState(None, tuple(saved))
            fix = kernels_zone.ZoneState(kernels_zone.KernelZone(True, None, None, verdict))
            kernels_zone.keep_unjudged_state(fix, [None, _Verdict(state)], i, j)
            assert kernels_zone.RESTORE_RUNS["compiled"] == runs + 1
        else:
            kernels_zone._restore(saved[0], np.flatnonzero(verdict), i, j)
        back = slots[[1, 3]]
        kept = slots[[0, 2, 4]]
        np.testing.assert_array_equal(store.values[back], before[back])
        np.testing.assert_array_equal(store.values[kept], before[kept] + 1.0)
        results.append(store.values.copy())
    np.testing.assert_array_equal(*results)


class _Verdict:
    def __init__(self, state) -> None:
        self.state = state


def test_the_defence_stores_share_slots_and_undo_puts_them_back(monkeypatch) -> None:
    params = CLParams(detector_norm="nis", robot_cusum=True, recovery=True)
    memory = LinkMemory(4)
    i = np.array([0, 0, 1, 2, 2, 3])
    first = defence_state(params, memory, i)  # inserts the robots' keys in every store
    calls = _spy_same_keys(monkeypatch)
    state = defence_state(params, memory, i)
    # one group (kernels_stores): no comparison store by store, every store the same slots
    assert calls == []
    slots = state.kernel[4], state.kernel[10], state.kernel[12], state.kernel[14]
    for s in slots[1:]:
        assert s is slots[0]
    np.testing.assert_array_equal(slots[0], first.kernel[4])
    stores = [state.kernel[k] for k in (3, 9, 11, 13)]
    before = [s.copy() for s in stores]
    for s in stores:
        s += 2.0
    state.undo()
    for s, b in zip(stores, before, strict=True):
        np.testing.assert_array_equal(s, b)


@pytest.mark.parametrize("seed", range(4))
def test_stored_positions_is_searchsorted(seed: int) -> None:
    """The compiled look-up of a step's links in a store (``kernels_memory.stored_positions``,
    one walk over both sorted lists) gives ``np.searchsorted``'s positions: a per-robot
    store's key repeated on a robot's rows, links in key order with gaps, keys out of order
    (searched), and False when a key is missing."""
    rng = np.random.default_rng(seed)
    keys = np.unique(rng.integers(0, 400, 60)).astype(np.int64)
    n_nodes = 20
    cases = [
        np.repeat(keys[::3], rng.integers(1, 5, len(keys[::3]))),  # (i, i): repeated
        keys[rng.random(len(keys)) < 0.4],  # in order, with gaps
        rng.permutation(keys)[:25],  # out of order
        keys[[5, 5, 2, 9, 9, 9, 0, len(keys) - 1]],  # back and forth, the ends
    ]
    for wanted in cases:
        i, j = wanted // n_nodes, wanted % n_nodes
        pos = np.full(len(wanted), -7, np.int64)
        assert kernels_memory.stored_positions(keys, n_nodes, i, j, pos)
        np.testing.assert_array_equal(pos, np.searchsorted(keys, wanted))
        missing = np.setdiff1d(np.arange(keys[-1] + 2), keys)[rng.integers(0, 5)]
        for at in (0, len(wanted) // 2, len(wanted)):  # a key not stored: False
            bad = np.insert(wanted, at, missing)
            pos = np.empty(len(bad), np.int64)
            assert not kernels_memory.stored_positions(
                keys, n_nodes, bad // n_nodes, bad % n_nodes, pos
            )


def test_same_keys_are_compared_once_per_pair_of_key_arrays(monkeypatch) -> None:
    """Stores that keep their key arrays (a run's steady state) are compared once: the
    answer is remembered for that pair of arrays; a store that inserts gets a new array,
    which is compared again (its answer may change), and ``undo`` puts the old array back,
    whose pair is judged again too."""
    calls = _spy_same_keys(monkeypatch)
    i, j = np.array([0, 0, 1, 2, 2]), np.array([1, 2, 0, 0, 1])
    store, other = LinkStatistic(3), LinkStatistic(3)
    slots = other.slots(i, j)
    assert kernels_detection.shared_slots(store, other, slots, []) is None  # (empty)
    store.slots(i, j)
    for _ in range(5):  # the steady state: one compiled comparison
        assert kernels_detection.shared_slots(store, other, slots, []) is slots
    assert calls == [True], calls
    other_keys = other.keys
    other.slots(np.array([1]), np.array([1]))  # an insertion: a new array
    assert kernels_detection.shared_slots(store, other, slots, []) is None  # (shapes)
    store.slots(np.array([1]), np.array([1]))
    for _ in range(3):  # both new arrays, equal: compared once
        assert kernels_detection.shared_slots(store, other, other.slots(i, j), []) is not None
    assert calls == [True, True], calls
    other.keys = other_keys  # as undo puts it back
    assert kernels_detection.shared_slots(store, other, slots, []) is None
    different = LinkStatistic(3)
    different.slots(np.array([0, 0, 1, 2, 2, 2]), np.array([1, 2, 0, 0, 1, 2]))
    for _ in range(3):  # as many keys, one different: compared once, False
        assert kernels_detection.shared_slots(different, store, slots, []) is None
    assert calls == [True, True, False], calls
    for a, b in ((store.keys, different.keys), (store.keys, store.keys.copy())):
        pair = type("S", (), {"keys": a})(), type("S", (), {"keys": b})()
        assert kernels_detection._same_keys(*pair) == np.array_equal(a, b)
