"""The lock-out floor's compiled passes against the numpy specification."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from resloc.cl import kernels
from resloc.cl.detection_lockout import LOCKOUT_STATE, lockout_floor, record_lockout
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed")


class _Batch(SimpleNamespace):
    def __len__(self):
        return len(self.i)


def _run(backend, params, steps, B=9, seed=0):
    """``steps`` steps of random links (sorted by observer, some jammed), discards (a
    share that rises and falls) and covariances: the covariances each floor returned and
    the store at the end."""
    rng = np.random.default_rng(seed)
    memory = LinkMemory(B)
    used = []
    with kernels.use_backend(backend):
        for k in range(steps):
            E = int(rng.integers(5, 30))
            i = np.sort(rng.integers(0, B - 1, E))  # robot B - 1 only sends
            j = rng.integers(0, B, E)
            links = _Batch(i=i, j=j, channel_ok=rng.random(E) > 0.2)
            P = np.tile(np.eye(3), (B, 1, 1)) * rng.uniform(1e-7, 4e-4, (B, 1, 1))
            P[0, 0, 0] = np.nan if k == 7 else P[0, 0, 0]  # nan wins, as in numpy
            out = lockout_floor(params, memory, links, P)
            used.append((P, out.copy()))
            bad = 0.8 if (k // 6) % 2 else 0.1
            outcome = SimpleNamespace(detected=rng.random(E) < bad)
            x = rng.uniform(-2.0, 2.0, (B, 3))
            record_lockout(params, memory, links, outcome, x)
    state = memory.stage_statistic(LOCKOUT_STATE, width=2)
    return used, state.keys.copy(), state.values.copy()


@pytest.mark.parametrize("zone", [False, True])
def test_the_compiled_passes_equal_the_spec(zone):
    from resloc.cl.kernels_lockout import LOCKOUT_RUNS

    params = CLParams(lockout_share=0.45, lockout_window=3.0, lockout_floor_std=0.01)
    if zone:
        params = CLParams(
            lockout_share=0.45,
            lockout_window=3.0,
            lockout_floor_std=0.01,
            zone_trust=True,
            zone_trust_map=((0.0, 0.0, 1.5),),
        )
    spec = _run("numpy", params, 40)
    before = dict(LOCKOUT_RUNS)
    fast = _run("numba", params, 40)
    floors, idle = (LOCKOUT_RUNS[k] - before[k] for k in ("floors", "idle"))
    assert floors >= 20 and idle >= 3 and floors + idle >= 35
    assert LOCKOUT_RUNS["records"] - before["records"] >= 30
    # robots raised in some steps, not in others (the share rises and falls)
    raised = [int((out[:, 1, 1] > P[:, 1, 1]).sum()) for P, out in spec[0]]
    assert sum(raised) >= 10 and raised.count(0) >= 5
    for (_, u), (_, v) in zip(spec[0], fast[0], strict=True):
        np.testing.assert_array_equal(u, v)
    np.testing.assert_array_equal(spec[1], fast[1])
    np.testing.assert_array_equal(spec[2], fast[2])


def test_a_floor_after_a_record_by_the_spec_is_not_skipped():
    """The floor is skipped while the store holds the arrays the last compiled record found
    idle (nobody above the share, no factor above 1): a record by the numpy spec in
    between writes those same arrays in place, and the next floor must see it."""
    from resloc.cl.kernels_lockout import LOCKOUT_RUNS

    params = CLParams(lockout_share=0.45, lockout_window=1.0, lockout_floor_std=0.01)
    B = 4
    i = np.repeat(np.arange(B), 2)
    links = _Batch(i=i, j=(i + 1) % B, channel_ok=np.ones(2 * B, bool))
    P = np.tile(np.eye(3) * 1e-6, (B, 1, 1))
    x = np.zeros((B, 3))
    memory = LinkMemory(B)
    calm, alarmed = (SimpleNamespace(detected=np.full(2 * B, d)) for d in (False, True))
    with kernels.use_backend("numba"):
        for _ in range(2):  # (nobody stored at first: the spec's, then compiled: idle)
            lockout_floor(params, memory, links, P)
            record_lockout(params, memory, links, calm, x)
        before = dict(LOCKOUT_RUNS)
        assert lockout_floor(params, memory, links, P) is P
        assert LOCKOUT_RUNS["idle"] == before["idle"] + 1, "an idle store's floor was run"
    with kernels.use_backend("numpy"):
        record_lockout(params, memory, links, alarmed, x)  # every share 1, in place
    with kernels.use_backend("numba"):
        before = dict(LOCKOUT_RUNS)
        out = lockout_floor(params, memory, links, P)
        assert LOCKOUT_RUNS["floors"] == before["floors"] + 1, "not compiled"
    np.testing.assert_allclose(out[:, 0, 0], 1e-4, rtol=1e-12)  # raised to 0.01 m
