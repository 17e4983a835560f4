"""The per-step fixed costs removed around the compiled kernels (docs/performance.md, "Fixed
per-step costs of the options"): the compiled look-ups of the per-link memory
(:mod:`resloc.cl.kernels_memory`) give the numpy code's positions and stores, and run; the
``tracked`` and ``factorized`` joints run the link loop's form of their own
(:data:`~resloc.cl.kernels_joint_links.JOINT_FORM`), and another form refuses them rather
than fusing without the joint."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world, runner_step, start_state
from resloc.cl import kernels, kernels_memory
from resloc.cl import kernels_rounds as rounds
from resloc.cl.backend import use_backend
from resloc.cl.fusion_methods import fusion_strategy
from resloc.cl.kernels_joint_links import JOINT_FORM
from resloc.cl.memory import LinkMemory, LinkStatistic
from resloc.experiments.config import default_scenario
from resloc.filters import make_filter
from test_kernel_forms import _forms_seen

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

PARAMS = default_scenario().cl_params()


def _outcomes(params, steps: int):
    """The outcomes of ``steps`` corrections of the default scenario (two trials) with
    ``params`` and the CKF, in the row-order loop (as a run steps it)."""
    filt = make_filter("ckf")
    world = default_world(2, 3)
    fusion = fusion_strategy(params.fusion)
    x, P, memory = start_state(world, fusion)
    saved = rounds.ROUNDS_MIN_LINKS
    rounds.ROUNDS_MIN_LINKS = 10**18
    try:
        for _ in range(steps):
            ws = world.step()
            x, P, out = runner_step(filt, x, P, ws, world.dt, params, fusion, memory)
            yield out
    finally:
        rounds.ROUNDS_MIN_LINKS = saved


def _spy(monkeypatch, name: str) -> list:
    """Calls of ``kernels_memory.<name>`` (the real function still runs), with results."""
    calls: list = []
    real = getattr(kernels_memory, name)

    def spy(*args):
        result = real(*args)
        calls.append(result)
        return result

    monkeypatch.setattr(kernels_memory, name, spy)
    return calls


def _links(rng, n_nodes: int, E: int, stored=None) -> tuple[np.ndarray, np.ndarray]:
    """Distinct links ``(i, j)`` sorted by key: ``E`` drawn at random, or (``stored``: a
    store's keys) about a third of the stored ones."""
    if stored is None:
        keys = np.unique(rng.integers(0, n_nodes * n_nodes, E))
    else:
        keys = stored[rng.random(len(stored)) < 0.3]
    return keys // n_nodes, keys % n_nodes


def test_compiled_slots_are_the_numpy_slots(monkeypatch) -> None:
    rng = np.random.default_rng(3)
    calls = _spy(monkeypatch, "stored_positions")
    for width in (None, 4):
        stores = {b: LinkStatistic(17, width=width) for b in ("numba", "numpy")}
        for step in range(6):
            known = stores["numpy"].keys if step >= 3 else None  # new links, then stored ones
            i, j = _links(rng, 17, 40, known)
            if step % 2:  # links out of key order: every search from the start
                order = rng.permutation(len(i))
                i, j = i[order], j[order]
            got = {}
            for backend, store in stores.items():
                with use_backend(backend):
                    got[backend] = store.slots(i, j)
                store.values[got[backend]] += 1.0
            np.testing.assert_array_equal(got["numba"], got["numpy"])
            assert got["numba"].dtype == np.int64
            np.testing.assert_array_equal(stores["numba"].keys, stores["numpy"].keys)
            np.testing.assert_array_equal(stores["numba"].values, stores["numpy"].values)
            if step >= 3:  # every link stored, in key order or not: the compiled look-up
                assert calls and calls[-1] is True, (step, calls)
    assert False in calls, "the compiled look-up never gave way to an insertion"


def test_compiled_store_is_the_numpy_store(monkeypatch) -> None:
    rng = np.random.default_rng(5)
    calls = _spy(monkeypatch, "overwrite_stored")
    memories = {b: LinkMemory(9) for b in ("numba", "numpy")}
    for step in range(8):
        i, j = _links(rng, 9, 30, memories["numpy"].keys if step >= 2 else None)
        x = rng.normal(size=(len(i), 3))
        P = rng.normal(size=(len(i), 3, 3))
        norm = rng.random(len(i))
        for backend, memory in memories.items():
            with use_backend(backend):
                memory.store(i, j, x, P, norm)
        a, b = memories["numba"], memories["numpy"]
        for name in ("keys", "x", "P", "last_norm"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert True in calls and False in calls, calls


def test_gathered_store_is_the_numpy_store(monkeypatch) -> None:
    """``cached``'s per-link inputs (``LinkMemory.cached_rows``) are the reference's
    look-up and ``np.where``, and the step's store at the positions they found is the
    numpy store, until a delivered link is new (the search path then inserts it)."""
    rng = np.random.default_rng(7)
    calls = _spy(monkeypatch, "store_gathered")
    memories = {b: LinkMemory(9) for b in ("numba", "numpy")}
    for step in range(8):
        i, j = _links(rng, 9, 30, memories["numpy"].keys if step >= 2 else None)
        E = len(i)
        x_nb = rng.normal(size=(9, 3))
        P_nb = rng.normal(size=(9, 3, 3))
        rows = rng.integers(0, 9, E).astype(np.int64)
        norm = rng.random(E)
        delivered = rng.random(E) < 0.5
        ref = memories["numpy"]
        found, pos = ref.lookup(i, j)
        expected = (
            x_nb[rows],
            P_nb[rows],
            np.where(found[:, None], ref.x[pos] if len(ref) else 0.0, x_nb[rows]),
            np.where(found[:, None, None], ref.P[pos] if len(ref) else 0.0, P_nb[rows]),
            found,
            np.where(found, ref.last_norm[pos] if len(ref) else 0.0, 0.0),
        )
        memory = memories["numba"]
        got = memory.cached_rows(i.astype(np.int64), j.astype(np.int64), rows, x_nb, P_nb, True)
        for name, a, b in zip(
            ("x", "P", "x_ref", "P_ref", "known", "last"), got, expected, strict=True
        ):
            np.testing.assert_array_equal(a, b, err_msg=name)
        with use_backend("numba"):
            memory.store_delivered(
                i.astype(np.int64), j.astype(np.int64), delivered, got[0], got[1],
                np.arange(E, dtype=np.int64), norm,
            )  # fmt: skip
        with use_backend("numpy"):
            ref.store(i[delivered], j[delivered], x_nb[rows][delivered], P_nb[rows][delivered],
                      norm[delivered])  # fmt: skip
        for name in ("keys", "x", "P", "last_norm"):
            np.testing.assert_array_equal(getattr(memory, name), getattr(ref, name), name)
        if step >= 2:  # every link stored: the store at the gathered positions
            assert calls[-1] is True, (step, calls)
    assert False in calls, "a new delivered link never gave way to the search path"


@pytest.mark.parametrize("method", ["tracked", "factorized"])
def test_the_joints_run_their_own_form_of_the_loop(method: str) -> None:
    params = replace(PARAMS, fusion=method)
    with _forms_seen() as seen:
        assert all(out.compiled for out in _outcomes(params, 2))
    assert seen and all(type(form) is int and form == JOINT_FORM for _, form in seen), seen
    with _forms_seen() as seen:  # the options' form: every switch the bool True
        assert all(out.compiled for out in _outcomes(replace(PARAMS, fusion="ci"), 1))
    assert seen and all(form is True for _, form in seen), seen


def test_another_form_refuses_the_joints(monkeypatch) -> None:
    """Run with the options' switch (True), the loop refuses a joint instead of fusing
    without it: the correction goes to the reference path."""
    monkeypatch.setattr(rounds, "beyond_paper", lambda *args: True)
    params = replace(PARAMS, fusion="tracked")
    with _forms_seen() as seen:
        outs = list(_outcomes(params, 2))
    assert seen and all(form is True for _, form in seen)
    assert not any(out.compiled for out in outs)
