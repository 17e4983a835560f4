"""Distributed lambda2 estimation (issue 6)."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.cl.connectivity import DistributedLambda2
from resloc.cl.graph import component_lambda2
from resloc.experiments.config import default_scenario
from resloc.experiments.runner import run_scenario


def _edges(n, kind, rng):
    if kind == "path":
        i = np.arange(n - 1)
        return i, i + 1
    if kind == "complete":
        i, j = np.triu_indices(n, 1)
        return i, j
    if kind == "ring":
        i = np.arange(n)
        return i, (i + 1) % n
    p = rng.uniform(0, 1, size=(n, 2))  # random geometric graph, kept connected
    for r in np.linspace(0.3, 1.5, 50):
        d = np.hypot(*(p[:, None] - p[None]).transpose(2, 0, 1))
        i, j = np.nonzero(np.triu(d <= r, 1))
        if component_lambda2(i, j, n, "global")[0] > 0:
            return i, j
    raise AssertionError("unreachable")


@pytest.mark.parametrize(
    ("kind", "n", "steps", "leak", "tol"),
    [
        ("complete", 6, 30, 0.01, 0.01),
        ("ring", 8, 400, 0.0, 0.01),
        ("path", 5, 1000, 0.0, 0.01),
        ("rgg", 15, 2000, 0.0, 0.05),
    ],
)
def test_converges_on_a_static_graph(rng, kind, n, steps, leak, tol):
    i, j = _edges(n, kind, rng)
    true = component_lambda2(i, j, n, "global")[0]
    dl = DistributedLambda2(n, n, rounds=3, leak=leak, rng=rng)
    for _ in range(steps):
        est = dl.step(i, j)
    np.testing.assert_allclose(est, true, rtol=tol)
    assert dl.messages == steps * 3 * 2 * len(np.unique(np.sort(np.c_[i, j], 1), axis=0))


def test_components_and_isolated_robots(rng):
    # Two teams (batched trials) plus an isolated robot: each robot its own component's value.
    i = np.array([0, 1, 2, 4, 5])
    j = np.array([1, 2, 0, 5, 6])
    n = 8  # robot 3 and 7 isolated
    dl = DistributedLambda2(n, 4, rounds=3, rng=rng)
    for _ in range(200):
        est = dl.step(i, j)
    true = component_lambda2(i, j, n, "component")
    np.testing.assert_allclose(est, true, rtol=0.05, atol=1e-9)
    assert est[3] == 0.0 and est[7] == 0.0


def test_validation():
    with pytest.raises(ValueError):
        DistributedLambda2(3, 3, rounds=0)
    with pytest.raises(ValueError):
        DistributedLambda2(3, 3, leak=1.0)


def test_runner_distributed_mode_records_the_error():
    sc = default_scenario().replace(
        **{
            "trigger.lambda2": "distributed",
            "trigger.lambda2_rounds": 3,
            "run.steps": 80,
            "run.trials": 2,
            "team.robots": 7,
            "run.filters": ["ekf"],
            "run.dead_reckoning": False,
            "sdz": [],
            "cdz": [],
        }
    )
    res = run_scenario(sc)
    meta = res.meta["lambda2"]
    assert meta["true_mean"] > 0
    assert 0 <= meta["abs_rel_error_series"][-1] < 0.2
    assert meta["messages"] > 0
    assert res.summary()["ekf"]["comm_rate"] > 0
    # Batching does not change a team's estimates (per-trial initial vectors).
    alone = run_scenario(sc.replace(**{"run.trials": 1}))
    np.testing.assert_allclose(
        alone.estimators["ekf"].series["msle"][:, 0], res.estimators["ekf"].series["msle"][:, 0]
    )
