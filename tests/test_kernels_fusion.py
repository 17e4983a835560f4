"""The compiled covariance-intersection update (``ci`` fusion,
:mod:`resloc.cl.kernels_ci_update`) against the numpy reference over multi-step runs: same
estimates, covariances and decisions to 1e-9 at every step with the compiled path asserted,
for both weight criteria, with links whose weight is 1 (the prior kept) and links fused
with a weight below 1."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world
from resloc.cl import fusion as cl_fusion
from resloc.cl import kernels
from resloc.cl.backend import kernel_refusal
from resloc.experiments.config import default_scenario
from resloc.filters import make_filter
from test_engine import lockstep_both_backends, random_batch

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

FILTERS = {
    "ckf": make_filter("ckf"),
    "ukf": make_filter("ukf", 0.8, 2.0, 1.0),
    "ekf": make_filter("ekf"),
}


@pytest.fixture
def ci_weights_seen(monkeypatch):
    """The weights the reference chose (to check both branches ran)."""
    seen: list[np.ndarray] = []
    weights = cl_fusion.ci_weights

    def recorded(*args, **kwargs):
        w = weights(*args, **kwargs)
        seen.append(w)
        return w

    monkeypatch.setattr(cl_fusion, "ci_weights", recorded)
    return seen


@pytest.mark.parametrize("criterion", ["trace", "det"])
@pytest.mark.parametrize("name", list(FILTERS))
def test_compiled_ci_matches_reference_over_a_run(name, criterion, ci_weights_seen):
    params = replace(default_scenario().cl_params(), fusion="ci", ci_criterion=criterion)
    assert kernel_refusal(FILTERS[name], params, random_batch(0)[2]) is None
    world = default_world(2, 11)
    fused = 0
    for res, _ in lockstep_both_backends(world, FILTERS[name], params, 120):
        fused += int(res["numpy"][2].fused.sum())
    assert fused > 0
    w = np.concatenate(ci_weights_seen)
    assert (w < 1.0).any() and (w == 1.0).any(), "both CI branches must run"


def test_compiled_ci_with_the_full_defence_and_recovery():
    """CI under the detector stages, with re-admissions on an inflated covariance."""
    from resloc.experiments.defences import DEFENCES

    base = default_scenario().replace(**DEFENCES["full"]).cl_params()
    params = replace(base, fusion="ci", rho=1.2, recovery_after=2.0, recovery_gate=3.0)
    world = default_world(2, 12)
    for _ in lockstep_both_backends(world, FILTERS["ekf"], params, 60):
        pass


@pytest.mark.parametrize(
    ("name", "changes"),
    [
        ("ckf", {}),
        ("ekf", {"update_without_transmission": True}),
        ("ukf", {"update_without_transmission": True, "threshold_innovation": "last_sent"}),
        ("ckf", {"fusion": "ci"}),
        ("ckf", {"cusum": True, "detector_norm": "nis", "rho": 1.5, "recovery": True,
                 "recovery_after": 2.0, "recovery_gate": 3.0, "update_without_transmission": True}),
    ],
)  # fmt: skip
def test_compiled_cached_neighbour_estimates_match_reference(name, changes):
    """``cached``: moments from j's last received estimate, the trigger firing at the first
    reception, fusion without transmission, a delivered link fused with the fresh estimate
    (the kernel's second pass), with the link memory the same after every step."""
    params = replace(default_scenario().cl_params(), neighbour_estimate="cached", **changes)
    assert kernel_refusal(FILTERS[name], params, random_batch(0)[2]) is None
    world = default_world(2, 13)
    untransmitted = 0
    for res, memories in lockstep_both_backends(world, FILTERS[name], params, 80):
        out = res["numpy"][2]
        untransmitted += int((out.fused & ~out.delivered).sum())
        fast, ref = memories["numba"], memories["numpy"]
        np.testing.assert_array_equal(fast.keys, ref.keys)
        np.testing.assert_allclose(fast.x, ref.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(fast.last_norm, ref.last_norm, rtol=1e-12, atol=1e-12)
    assert (untransmitted > 0) == bool(params.update_without_transmission)


@pytest.mark.parametrize("split", [False, True])
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_grid_costs_are_the_reference_posterior_costs(criterion, split):
    """The vectorized grid search (``kernels_ci_weight.grid_costs``, compiled and called
    here directly) gives the reference's cost at every candidate weight, for both
    criteria, with and without independent parts."""
    from resloc.cl.fusion import CI_GRID, CICriterion, _posterior_cost
    from resloc.cl.kernels_ci_weight import grid_costs
    from resloc.cl.kernels_fusion import _GRID
    from resloc.models.measurement import range_bearing_jacobians

    rng = np.random.default_rng(5)
    R = np.diag([0.01, 0.003])

    def spd(scale):
        A = rng.normal(size=(3, 3)) * scale
        return A @ A.T + 0.01 * scale * np.eye(3)

    for _ in range(5):
        x_i = rng.normal(size=(1, 3))
        x_j = x_i + rng.normal(size=(1, 3))
        H_i, H_j = (h[0] for h in range_bearing_jacobians(x_i, x_j))
        Di, Dj = spd(0.2), spd(0.1)
        Ii, Ij = (spd(0.05), spd(0.05)) if split else (np.zeros((3, 3)), np.zeros((3, 3)))
        Cd, Ci = Di @ H_i.T, Ii @ H_i.T
        a, ai = H_i @ Cd, H_i @ Ci
        b, bi = H_j @ Dj @ H_j.T, (H_j @ Ij @ H_j.T + R if split else np.zeros((2, 2)))
        quad = [a, ai, b, bi, Cd.T @ Cd, Cd.T @ Ci, Ci.T @ Ci]
        cost = np.full(CI_GRID.size, np.nan)
        np.testing.assert_array_equal(_GRID[0], CI_GRID)
        grid_costs(
            _GRID, criterion == "det", split, np.trace(Di), np.linalg.det(Di),
            *(tuple(m.ravel()) for m in quad), tuple(Di.ravel()), tuple(Ii.ravel()),
            np.trace(Ii), tuple(R.ravel()), cost,
        )  # fmt: skip
        ref = _posterior_cost(
            H_i[None], H_j[None], Di[None], Ii[None] if split else None, Dj[None],
            Ij[None] if split else None, R, CI_GRID, CICriterion(criterion),
        )[0]  # fmt: skip
        np.testing.assert_allclose(cost, ref, rtol=1e-12, atol=0)


def test_first_best_is_the_scalar_search():
    """``kernels_ci_weight.first_best`` (four interleaved searches, merged) finds the index
    the scalar search ``best = cost[0]; cost[t] < best`` finds, with ties, infinities and
    NaNs (first or later), for every length."""
    from resloc.cl.kernels_ci_weight import first_best

    rng = np.random.default_rng(8)
    values = np.array([0.0, -0.0, 1.0, 2.0, -1.0, np.inf, -np.inf, np.nan])
    for trial in range(2000):
        n = int(rng.integers(1, 40))
        if trial % 2:
            cost = rng.choice(values, size=n)
        else:
            cost = rng.normal(size=n)
        best, k = cost[0], 0
        for t in range(1, n):
            if cost[t] < best:
                best, k = cost[t], t
        got_best, got_k = first_best(cost, n)
        assert got_k == k, (cost, got_k, k)
        assert got_best == best or (np.isnan(got_best) and np.isnan(best))
