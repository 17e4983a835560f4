"""The compiled comparison of two per-link stores' keys (:func:`resloc.cl.kernels_memory.
same_keys`): the detector stages that see every link of every step share one store's slots
when their keys are equal (``kernels_detection.shared_slots``); the compiled comparison
gives ``np.array_equal``'s answer and runs."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.cl import kernels, kernels_detection, kernels_memory
from resloc.cl.memory import LinkStatistic

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


def test_shared_slots_compares_the_keys_compiled(monkeypatch) -> None:
    calls = []
    real = kernels_detection.same_keys

    def spy(a, b):
        calls.append(real(a, b))
        return calls[-1]

    monkeypatch.setattr(kernels_detection, "same_keys", spy)
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
