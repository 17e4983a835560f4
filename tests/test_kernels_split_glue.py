"""Split CI's once-per-step glue compiled: the independent parts' prediction in one compiled
call and ``fusion_state``'s working copy with the observers' bound (docs/performance.md,
"Split CI's glue")."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from resloc.cl import kernels

pytest.importorskip("numba")


def _spd(rng, n: int) -> np.ndarray:
    A = rng.normal(size=(n, 3, 3))
    return A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(3)


@pytest.mark.parametrize("per_robot", [False, True])
def test_compiled_independent_prediction_is_the_reference(per_robot: bool) -> None:
    """One compiled call (the result allocated and the floor scaled by ``dt`` inside) gives
    the separate steps' result bit for bit (the floor's ``floor_std**2 * dt`` by numpy, the
    propagation kernel) and the numpy reference's to 1e-12, also from a non-contiguous
    ``x``; the numpy backend computes nothing."""
    from resloc.cl.fusion import propagate_independent
    from resloc.cl.kernels_fusion_step import _propagate_independent, compiled_independent_predict
    from resloc.experiments.config import default_scenario

    rng = np.random.default_rng(5)
    B, dt = 17, 0.1
    params = default_scenario().cl_params()
    odometry = np.array(params.odometry_std) * (1.0 + rng.uniform(size=(B, 2)) if per_robot else 1)
    params = replace(params, odometry_std=odometry, process_floor_std=(2e-3, 1e-3, 3e-3))
    wide = rng.normal(size=(B, 5))
    x = wide[:, 1:4]  # (not C-contiguous)
    u = np.column_stack([rng.uniform(0.1, 1.0, B), rng.normal(size=B)])
    P_ind = _spd(rng, B)
    before = P_ind.copy()
    out = compiled_independent_predict(x, P_ind, u, dt, params)
    assert out is not None and out is not P_ind
    np.testing.assert_array_equal(P_ind, before)  # the input is not written
    floor = np.asarray(params.process_floor_std, dtype=float) ** 2 * dt
    separate = np.empty((B, 3, 3))
    odometry_var = np.ascontiguousarray(np.atleast_2d(np.asarray(odometry, dtype=float) ** 2))
    _propagate_independent(np.ascontiguousarray(x), P_ind, u, dt, odometry_var, floor, separate)
    assert out.tobytes() == separate.tobytes()
    reference = propagate_independent(
        x, P_ind, u, dt, np.asarray(params.odometry_std), np.asarray(params.process_floor_std)
    )
    np.testing.assert_allclose(out, reference, rtol=1e-12, atol=1e-15)
    with kernels.use_backend("numpy"):
        assert compiled_independent_predict(x, P_ind, u, dt, params) is None


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_split_fusion_state_copies_the_parts_and_bounds_the_observers(criterion: str) -> None:
    """``fusion_state``'s split CI branch: a C-contiguous working copy of
    ``memory.independent`` (equal to it, not it), the transmitted parts, the criterion's
    flag from a string or a ``CICriterion``; None when an observer is not one of the parts'
    robots (the kernel does not check indices) and, with observers up to the last robot,
    the state."""
    from resloc.cl.fusion import CICriterion
    from resloc.cl.kernels_fusion import SPLIT_CI, fusion_state

    rng = np.random.default_rng(8)
    B, E = 17, 40
    memory = SimpleNamespace(independent=_spd(rng, B))
    i = np.sort(rng.integers(0, B - 1, E))
    links = SimpleNamespace(i=i, P_nb_ind=_spd(rng, E))
    for given in (criterion, CICriterion(criterion)):
        fusion = fusion_state("split_ci", given, memory, links, E)
        assert fusion is not None and fusion.code == SPLIT_CI
        assert fusion.det is (criterion == "det")
        assert fusion.independent is not memory.independent
        assert fusion.independent.flags.c_contiguous
        assert fusion.independent.tobytes() == memory.independent.tobytes()
        np.testing.assert_array_equal(fusion.P_nb_ind, links.P_nb_ind)
    i[-1] = B - 1  # the last robot: in range
    assert fusion_state("split_ci", criterion, memory, links, E) is not None
    i[-1] = B  # one past: refused
    assert fusion_state("split_ci", criterion, memory, links, E) is None
    i[-1] = B - 1
    strided = SimpleNamespace(independent=np.repeat(memory.independent, 2, axis=0)[::2])
    fusion = fusion_state("split_ci", criterion, strided, links, E)  # (not C-contiguous)
    assert fusion is not None and fusion.independent.tobytes() == memory.independent.tobytes()
    links.P_nb_ind = links.P_nb_ind[:-1]
    assert fusion_state("split_ci", criterion, memory, links, E) is None


def test_the_compiled_glue_takes_pickled_arrays() -> None:
    """A pickled array (a worker's, a checkpoint's) has a dtype object of its own: the
    compiled finish, prediction and working copy still take it (dtypes compared by value)."""
    import pickle

    from resloc.cl.kernels_fusion import fusion_state
    from resloc.cl.kernels_fusion_step import compiled_independent_predict
    from resloc.cl.kernels_split import compiled_independent_finish
    from resloc.experiments.config import default_scenario

    rng = np.random.default_rng(9)
    B, E = 17, 30
    independent, x, u, i, j, delivered, P_nb_ind = pickle.loads(
        pickle.dumps(
            (
                _spd(rng, B), rng.normal(size=(B, 3)), rng.uniform(size=(B, 2)),
                np.sort(rng.integers(0, B, E)), rng.integers(0, B, E), rng.uniform(size=E) < 0.5,
                _spd(rng, E),
            )
        )
    )  # fmt: skip
    assert independent.dtype is not np.dtype(float)  # (what the test is about)
    params = default_scenario().cl_params()
    assert compiled_independent_predict(x, independent, u, 0.1, params) is not None
    links = SimpleNamespace(i=i, P_nb_ind=P_nb_ind)
    assert fusion_state("split_ci", "trace", SimpleNamespace(independent=independent), links, E)
    expected = independent.copy()
    expected[j[delivered]] = 0.0
    assert compiled_independent_finish(independent, j, delivered)
    np.testing.assert_array_equal(independent, expected)
