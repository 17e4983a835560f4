"""Gauge fusion (issue 6): the team's unobservable rigid-body error, tracked beside the
paper's estimates (resloc.cl.gauge)."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.cl.gauge import GaugeCovariance, gauge_jacobian
from resloc.filters.base import make_filter
from resloc.models.measurement import range_bearing, range_bearing_jacobians
from resloc.models.motion import unicycle_state_jacobian, unicycle_step

R = np.diag([0.005**2, 0.05**2])


def _poses(rng, n):
    return np.column_stack(
        [rng.uniform(-1.5, 1.5, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-3, 3, n)]
    )


def test_relative_measurements_do_not_see_the_gauge(rng):
    """``H_i J_i + H_j J_j = 0``, and a finite rigid motion leaves z unchanged."""
    xi, xj = _poses(rng, 50), _poses(rng, 50)
    H_i, H_j = range_bearing_jacobians(xi, xj)
    np.testing.assert_allclose(H_i @ gauge_jacobian(xi) + H_j @ gauge_jacobian(xj), 0.0, atol=1e-12)
    g = np.array([0.3, -0.2, 0.4])  # finite: rotate by 0.4 rad about the origin, translate
    c, s = np.cos(g[2]), np.sin(g[2])

    def move(x):
        out = x.copy()
        out[:, 0] = c * x[:, 0] - s * x[:, 1] + g[0]
        out[:, 1] = s * x[:, 0] + c * x[:, 1] + g[1]
        out[:, 2] = x[:, 2] + g[2]
        return out

    z0, z1 = range_bearing(xi, xj), range_bearing(move(xi), move(xj))
    np.testing.assert_allclose(z1[:, 0], z0[:, 0], atol=1e-12)
    np.testing.assert_allclose(np.angle(np.exp(1j * (z1[:, 1] - z0[:, 1]))), 0.0, atol=1e-12)


def test_the_gauge_is_constant_under_the_motion_model(rng):
    """``F_i J_i(x) = J_i(f(x))``: a rigid motion commutes with the unicycle (first order)."""
    x = _poses(rng, 40)
    u = np.column_stack([rng.uniform(0, 0.3, 40), rng.uniform(-1, 1, 40)])
    F = unicycle_state_jacobian(x, u, 0.05)
    np.testing.assert_allclose(
        F @ gauge_jacobian(x), gauge_jacobian(unicycle_step(x, u, 0.05)), atol=1e-12
    )


def _team_fit(x):
    J = gauge_jacobian(x)
    M = sum(Jl.T @ Jl for Jl in J)
    Lbig = np.linalg.solve(M, np.hstack([Jl.T for Jl in J]))  # (3, 3N)
    return Lbig


def test_gauge_bookkeeping_matches_the_stacked_linear_maps(rng, random_spd):
    """One team: G_0 = L blockdiag(P0) L^T; prediction adds L blockdiag(Q) L^T; a correction
    adds L (M - I) blockdiag(D) (M - I)^T L^T + L blockdiag(N) L^T for the stacked step map
    M and measurement-noise covariance N (two rounds, one-sided and symmetric links)."""
    N = 4
    x = _poses(rng, N)
    P0 = random_spd(rng, N, 3, scale=0.003, cond=5)
    gc = GaugeCovariance(x, P0, N)

    def bd(blocks):
        out = np.zeros((3 * N, 3 * N))
        for r, b in enumerate(blocks):
            out[3 * r : 3 * r + 3, 3 * r : 3 * r + 3] = b
        return out

    L = _team_fit(x)
    np.testing.assert_allclose(gc.G[0], L @ bd(P0) @ L.T, atol=1e-15)
    Q = random_spd(rng, N, 3, scale=1e-5)
    D = random_spd(rng, N, 3, scale=0.002, cond=5)
    u = np.column_stack([rng.uniform(0, 0.2, N), rng.uniform(-1, 1, N)])
    G_before = gc.G[0].copy()
    gc.predict(x, u, 0.1, Q, D)
    np.testing.assert_allclose(gc.G[0], G_before + L @ bd(Q) @ L.T, atol=1e-15)
    G_before = gc.G[0].copy()
    xp = unicycle_step(x, u, 0.1)
    ekf = make_filter("ekf")
    M = np.eye(3 * N)
    noise = np.zeros((3 * N, 3 * N))
    Dcur = D.copy()
    # round 1: 0 <- 1, 1 <- 0 (symmetric), 2 <- 3; round 2: 0 <- 2
    for i, j in ((np.array([0, 1, 2]), np.array([1, 0, 3])), (np.array([0]), np.array([2]))):
        m = ekf.relative_moments(xp[i], Dcur[i], xp[j], D[j], R)
        K = m.Pxz @ np.linalg.inv(m.S)
        H_i, H_j = range_bearing_jacobians(xp[i], xp[j])
        for e in range(len(i)):
            rows = slice(3 * i[e], 3 * i[e] + 3)
            Gk = np.eye(3) - K[e] @ H_i[0 + e]
            Mi = Gk @ M[rows]
            Mi[:, 3 * j[e] : 3 * j[e] + 3] -= K[e] @ H_j[e]
            M[rows] = Mi
            noise[rows, rows] = Gk @ noise[rows, rows] @ Gk.T + K[e] @ R @ K[e].T
            Dcur[i[e]] = Gk @ Dcur[i[e]] @ Gk.T + K[e] @ R @ K[e].T
        gc.update(i, j, xp[i], xp[j], m, R, Dcur[i])
    gc.finish(Dcur)
    leak = L @ (M - np.eye(3 * N))
    expect = G_before + leak @ bd(D) @ leak.T + L @ noise @ L.T
    np.testing.assert_allclose(gc.G[0], expect, rtol=1e-12, atol=1e-18)
    assert np.linalg.eigvalsh(gc.G[0])[0] > 0


def _run(fusion, steps=300, trials=4, filt="ekf", **extra):
    from resloc.experiments.config import default_scenario
    from resloc.experiments.runner import run_scenario

    sc = default_scenario().replace(
        **{
            "run.trials": trials,
            "run.steps": steps,
            "run.filters": [filt],
            "run.dead_reckoning": False,
            "estimator.fusion": fusion,
            "sdz": [],
            "cdz": [],
            **extra,
        }
    )
    return run_scenario(sc).estimators[filt]


@pytest.mark.parametrize("filt", ["ckf", "ekf"])
def test_gauge_keeps_the_paper_estimates_and_makes_them_consistent(filt):
    """Same estimates as naive fusion (the reference path vs the compiled one: to 1e-9),
    NEES near 3 instead of hundreds."""
    naive = _run("naive", filt=filt)
    gauge = _run("gauge", filt=filt)
    np.testing.assert_allclose(gauge.track, naive.track, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        gauge.per_trial("msle_mean"), naive.per_trial("msle_mean"), rtol=1e-7
    )
    n_naive = naive.per_trial("nees_mean").mean()
    n_gauge = gauge.per_trial("nees_mean").mean()
    assert n_naive > 50.0
    assert 1.0 < n_gauge < 8.0, n_gauge


def test_gauge_sums_by_consensus_converge_to_the_exact_ones(rng, random_spd):
    """Every robot's own G: consensus keeps the team's sum of contributions exactly and, on a
    connected graph, converges to it; once the fit L has converged, increments are exact."""
    N = 5
    x = _poses(rng, N)
    P0 = random_spd(rng, N, 3, scale=0.003, cond=5)
    exact = GaugeCovariance(x, P0, N)
    cons = GaugeCovariance(x, P0, N, rounds=200)
    i, j = np.array([0, 1, 2, 3]), np.array([1, 2, 3, 4])  # a path: connected, not complete
    cons.exchange(i, j)
    J = gauge_jacobian(x)
    np.testing.assert_allclose(
        cons.M_hat, np.broadcast_to((np.swapaxes(J, -1, -2) @ J).mean(0), (N, 3, 3)), rtol=1e-8
    )
    G_all = cons.robot_G()
    np.testing.assert_allclose(G_all, np.broadcast_to(G_all[0], G_all.shape), rtol=1e-8)
    Q = random_spd(rng, N, 3, scale=1e-5)
    u = np.zeros((N, 2))
    before_exact, before_cons = exact.G[0].copy(), cons.robot_G()[0].copy()
    exact.predict(x, u, 0.1, Q, P0)
    cons.predict(x, u, 0.1, Q, P0)
    cons.exchange(i, j)
    np.testing.assert_allclose(
        cons.robot_G()[0] - before_cons, exact.G[0] - before_exact, rtol=1e-7
    )
    assert cons.messages == 2 * 200 * 2 * len(i)


def test_gauge_consensus_in_a_run_stays_consistent():
    exact = _run("gauge", steps=200, filt="ekf")
    cons = _run("gauge", steps=200, filt="ekf", **{"estimator.gauge_sums": "consensus"})
    np.testing.assert_array_equal(cons.track, exact.track)  # estimates never depend on G
    a, b = exact.per_trial("nees_mean").mean(), cons.per_trial("nees_mean").mean()
    assert 0.5 * a < b < 1.5 * a, (a, b)
