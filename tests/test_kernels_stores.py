"""The detector's and the defence's stores by group (:mod:`resloc.cl.kernels_stores`).

Stores holding the same keys get the slots of one look-up and their values saved for
``undo`` by one compiled call (:func:`resloc.cl.kernels_memory.slots_and_snapshot`, or
``slots_and_snapshot2`` for two stores): the slots are each store's own
(``LinkStatistic.slots``), ``undo`` puts every store back, a store that replaced its arrays
(an insertion, an ``undo``) makes the group be built again, and a link not stored yet, or
stores with different keys, answer None with nothing
recorded (the store-by-store path then inserts)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from resloc.cl import kernels, kernels_memory, kernels_stores
from resloc.cl.kernels_defence import defence_state
from resloc.cl.kernels_detection import DetectorState, detector_state
from resloc.cl.memory import LinkMemory, LinkStatistic
from resloc.cl.params import CLParams

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

OBS = np.array([0, 0, 1, 2, 2, 3, 3, 3], np.int64)
NBR = np.array([1, 3, 2, 0, 3, 0, 1, 2], np.int64)


def _stores(rng, widths=(None, 4, None, None)) -> tuple:
    stores = tuple(LinkStatistic(4, width=w) for w in widths)
    for store in stores:
        store.slots(OBS, NBR)
        store.values[...] = rng.normal(size=store.values.shape)
    return stores


@pytest.mark.parametrize("count", [1, 2, 4])
def test_a_group_gets_each_stores_slots_and_undo_puts_every_store_back(count: int) -> None:
    rng = np.random.default_rng(count)
    stores = _stores(rng)[:count]
    before = [s.values.copy() for s in stores]
    saved: list = []
    pos = kernels_stores.group_slots(stores, OBS, NBR, saved)
    assert pos is not None and len(saved) == count
    for store in stores:
        np.testing.assert_array_equal(pos, store.slots(OBS, NBR))
    for store in stores:  # what the step writes
        store.values[pos] += rng.normal(size=store.values[pos].shape)
    DetectorState(None, tuple(saved)).undo()
    for store, b in zip(stores, before, strict=True):
        np.testing.assert_array_equal(store.values, b)


def test_a_store_with_new_arrays_makes_the_group_be_built_again() -> None:
    rng = np.random.default_rng(7)
    stores = _stores(rng)
    assert kernels_stores.group_slots(stores, OBS, NBR, []) is not None
    # the same keys, a new values array (as undo after an insertion puts back)
    stores[3].values = rng.normal(size=stores[3].values.shape)
    before = stores[3].values.copy()
    saved: list = []
    pos = kernels_stores.group_slots(stores, OBS, NBR, saved)
    stores[3].values[pos] = 99.0
    DetectorState(None, tuple(saved)).undo()
    np.testing.assert_array_equal(stores[3].values, before)
    # one store with one key more: not a group; nothing recorded
    stores[1].slots(np.array([1], np.int64), np.array([1], np.int64))
    saved = []
    assert kernels_stores.group_slots(stores, OBS, NBR, saved) is None and saved == []
    for store in stores[:1] + stores[2:]:
        store.slots(np.array([1], np.int64), np.array([1], np.int64))
    assert kernels_stores.group_slots(stores, OBS, NBR, saved) is not None
    # a link not stored: None, nothing recorded (the store-by-store path inserts it)
    saved = []
    i, j = np.append(OBS, 3), np.append(NBR, 3)
    assert kernels_stores.group_slots(stores, i, j, saved) is None and saved == []


def _counted(call, calls: list):
    def counted(*args):
        calls.append(1)
        return call(*args)

    return counted


def test_the_full_defences_stores_take_two_compiled_calls_a_step(monkeypatch) -> None:
    """detector_state and defence_state of the ``full`` stages in a steady state: one call
    of the group's look-up and save each, no store-by-store look-up, and the slots and
    undo those of the store-by-store path."""
    params = CLParams(
        detector_norm="nis", cusum=True, mean_cusum=True, robot_cusum=True, recovery=True
    )
    memory = LinkMemory(4)
    detector_state(params, memory, OBS, NBR)  # inserts every key
    defence_state(params, memory, OBS)
    rng = np.random.default_rng(3)
    stores = [memory.cusum, memory.mean_cusum]
    stores += [memory.stage_statistic(n) for n in ("robot_cusum", "recovery")]
    stores += [memory.stage_statistic(n) for n in ("recovery_spread", "recovery_applied")]
    for store in stores:
        store.values[...] = rng.normal(size=store.values.shape)
    before = [s.values.copy() for s in stores]
    calls = []
    for name in ("slots_and_snapshot", "slots_and_snapshot2"):  # (looked up by new groups)
        monkeypatch.setattr(kernels_memory, name, _counted(getattr(kernels_memory, name), calls))
    monkeypatch.setattr(LinkStatistic, "slots", None)  # the store-by-store look-up
    detection = detector_state(params, memory, OBS, NBR)
    defence = defence_state(params, memory, OBS)
    assert len(calls) == 2
    monkeypatch.undo()
    np.testing.assert_array_equal(detection.kernel.cusum_slot, memory.cusum.slots(OBS, NBR))
    np.testing.assert_array_equal(detection.kernel.mean_slot, memory.cusum.slots(OBS, NBR))
    robot_slots = stores[2].slots(OBS, OBS)
    for k in (4, 10, 12, 14):
        np.testing.assert_array_equal(defence.kernel[k], robot_slots)
    for store in stores:
        store.values += 1.0
    defence.undo()
    detection.undo()
    for store, b in zip(stores, before, strict=True):
        np.testing.assert_array_equal(store.values, b)


def test_a_copied_store_leaves_the_group_behind() -> None:
    """A deep copy (a runtime checkpoint) or a shallow one (an attacker's scratch memory)
    of a store in a group has no group: the copy's first call builds its own, whose saved
    values are the copy's (a deep-copied group would save from copies of the views)."""
    rng = np.random.default_rng(11)
    stores = _stores(rng)
    assert kernels_stores.group_slots(stores, OBS, NBR, []) is not None
    copies = copy.deepcopy(stores)
    assert all(s.group is None for s in copies)
    assert copy.copy(stores[0]).group is None
    for store in copies:
        store.values[...] = rng.normal(size=store.values.shape)
    before = [s.values.copy() for s in copies]
    saved: list = []
    pos = kernels_stores.group_slots(copies, OBS, NBR, saved)
    for store in copies:
        store.values[pos] = 5.0
    DetectorState(None, tuple(saved)).undo()
    for store, b in zip(copies, before, strict=True):
        np.testing.assert_array_equal(store.values, b)


FULL = dict(detector_norm="nis", cusum=True, mean_cusum=True, robot_cusum=True, recovery=True)


def _full_stores(memory) -> list:
    stores = [memory.cusum, memory.mean_cusum]
    stores += [memory.stage_statistic(n) for n in ("robot_cusum", "recovery")]
    return stores + [memory.stage_statistic(n) for n in ("recovery_spread", "recovery_applied")]


def _assert_states_of(params, memory, i, j, detection, defence) -> None:
    """The states' gains are ``params``', their slots the store-by-store look-up's and
    their arrays the stores'."""
    kernel = detection.kernel
    assert kernel.cusum_h[0] == params.cusum_h and kernel.mean_h[0] == params.mean_cusum_h
    assert defence.kernel.robot_h[0] == params.robot_cusum_h
    np.testing.assert_array_equal(kernel.cusum_slot, memory.cusum.slots(i, j))
    np.testing.assert_array_equal(kernel.mean_slot, memory.mean_cusum.slots(i, j))
    assert kernel.cusum_g is memory.cusum.values and kernel.mean_g is memory.mean_cusum.values
    stores = _full_stores(memory)
    for k, store in zip((4, 10, 12, 14), stores[2:], strict=True):
        np.testing.assert_array_equal(defence.kernel[k], store.slots(i, i))
        assert defence.kernel[k - 1] is store.values


def test_a_steady_step_reuses_the_last_state_with_this_steps_slots_and_save(
    monkeypatch,
) -> None:
    """From the third step of the same links and parameters, detector_state and
    defence_state return the states of the step before (no group built, no state built):
    one compiled call each looks the links up and saves the values *of this step* for
    undo. Another parameters object, fewer links or a link not stored yet give a state
    built again, with that step's gains and slots."""
    params = CLParams(**FULL)
    memory = LinkMemory(4)
    rng = np.random.default_rng(5)
    states = []
    for _ in range(2):  # the first inserts every key, the second builds the groups
        states.append(
            (detector_state(params, memory, OBS, NBR), defence_state(params, memory, OBS))
        )
    stores = _full_stores(memory)
    for store in stores:  # what the second step's loop wrote
        store.values[...] = rng.normal(size=store.values.shape)
    before = [s.values.copy() for s in stores]
    calls = []
    for store in (memory.cusum, stores[2]):  # the groups' compiled calls, counted
        monkeypatch.setattr(store.group, "call", _counted(store.group.call, calls))
    monkeypatch.setattr(kernels_stores, "_build", None)  # no group built
    detection = detector_state(params, memory, OBS, NBR)
    defence = defence_state(params, memory, OBS)
    assert detection is states[1][0] and defence is states[1][1]
    assert len(calls) == 2
    monkeypatch.undo()
    _assert_states_of(params, memory, OBS, NBR, detection, defence)
    for store in stores:
        store.values += 1.0
    defence.undo()
    detection.undo()
    for store, b in zip(stores, before, strict=True):  # this step's values, not the last's
        np.testing.assert_array_equal(store.values, b)
    # another parameters object (other gains): states built again
    other = CLParams(**FULL, cusum_h=7.0, mean_cusum_h=4.0, robot_cusum_h=9.0)
    detection = detector_state(other, memory, OBS, NBR)
    defence = defence_state(other, memory, OBS)
    assert detection is not states[1][0] and defence is not states[1][1]
    _assert_states_of(other, memory, OBS, NBR, detection, defence)
    # fewer links (every one stored), then a link not stored yet: their own slots
    for i, j in ((OBS[2:], NBR[2:]), (np.append(OBS, 3), np.append(NBR, 3))):
        detection = detector_state(other, memory, i, j)
        defence = defence_state(other, memory, i)
        _assert_states_of(other, memory, i, j, detection, defence)


def test_a_store_holding_given_arrays_is_the_constructors_store() -> None:
    """``LinkStatistic.holding`` (the witness stage's delivered store, built each step
    without the constructor's empty arrays) has the constructor's attributes, with the
    arrays given, and behaves as a scalar store: its ``get`` and ``set``."""
    keys, values = np.array([1, 7, 9], np.int64), np.array([0.5, 2.0, -1.0])
    held = LinkStatistic.holding(4, keys, values)
    made = LinkStatistic(4)
    made.keys, made.values = keys, values
    assert held.keys is keys and held.values is values
    assert sorted(vars(held)) == sorted(vars(made))
    for name, value in vars(made).items():
        assert type(getattr(held, name)) is type(value), name
        if not isinstance(value, np.ndarray):
            assert getattr(held, name) == value, name
    np.testing.assert_array_equal(held.get([0, 1, 2], [1, 3, 0]), [0.5, 2.0, 0.0])
    held.set(np.array([3]), np.array([3]), np.array([4.0]))
    np.testing.assert_array_equal(held.keys, [1, 7, 9, 15])
    np.testing.assert_array_equal(held.get([3, 2], [3, 1]), [4.0, -1.0])
