"""Consistent fusion (issue 6): CI, split CI, tracked and factorized cross-covariances."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.cl.fusion import (
    CI_GRID,
    CICriterion,
    FusionMethod,
    ci_weights,
    clip_independent,
    fused_update,
    propagate_independent,
)
from resloc.cl.tracking import JointCovariance
from resloc.filters.base import make_filter
from resloc.filters.update import innovation, kalman_update
from resloc.models.measurement import range_bearing, range_bearing_jacobians

R = np.diag([0.005**2, 0.05**2])


def _links(rng, E, scale=0.05):
    x_i = np.column_stack([rng.uniform(-1, 1, E), rng.uniform(-1, 1, E), rng.uniform(-3, 3, E)])
    d = rng.uniform(0.3, 0.9, E)
    a = rng.uniform(-np.pi, np.pi, E)
    x_j = x_i + np.column_stack([d * np.cos(a), d * np.sin(a), rng.uniform(-1, 1, E)])
    return x_i, x_j


def _posterior_brute(x_i, x_j, Pi, Pj, w, criterion):
    H_i, H_j = range_bearing_jacobians(x_i[None], x_j[None])
    A, B = Pi / w, Pj / (1 - w)
    S = H_i[0] @ A @ H_i[0].T + H_j[0] @ B @ H_j[0].T + R
    K = A @ H_i[0].T @ np.linalg.inv(S)
    P = A - K @ S @ K.T
    return np.linalg.det(P) if criterion == "det" else np.trace(P)


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_ci_weight_minimises_posterior(rng, random_spd, criterion):
    E = 20
    x_i, x_j = _links(rng, E)
    Pi = random_spd(rng, E, 3, scale=0.01, cond=20)
    Pj = random_spd(rng, E, 3, scale=0.002, cond=20)  # j better known: CI uses it
    w = ci_weights(x_i, Pi, x_j, Pj, R, criterion)
    for e in range(E):
        cost = [_posterior_brute(x_i[e], x_j[e], Pi[e], Pj[e], g, criterion) for g in CI_GRID]
        best = min(cost)
        got = _posterior_brute(x_i[e], x_j[e], Pi[e], Pj[e], w[e], criterion)
        assert got <= best * (1 + 1e-9)
        assert got < (np.linalg.det(Pi[e]) if criterion == "det" else np.trace(Pi[e]))


def test_ci_skips_a_neighbour_that_adds_nothing(rng):
    # CI can never beat the better input: equal, fully uncertain neighbours bring nothing.
    x_i, x_j = _links(rng, 5)
    P = np.broadcast_to(np.eye(3) * 1e-4, (5, 3, 3)).copy()
    w = ci_weights(x_i, P, x_j, 100.0 * P, R)
    assert np.all(w == 1.0)
    m = make_filter("ekf").relative_moments(x_i, P, x_j, 100.0 * P, R)
    nu = innovation(range_bearing(x_i, x_j), m.z_hat)
    x_new, P_new, _, _ = fused_update(x_i, P, x_j, 100.0 * P, nu, m, R, "ci")
    np.testing.assert_array_equal(x_new, x_i)
    np.testing.assert_array_equal(P_new, P)


def test_ci_is_consistent_for_any_correlation(rng, random_spd):
    """The CI posterior bounds the actual error covariance whatever the cross-covariance."""
    E = 200
    x_i, x_j = _links(rng, E)
    J = random_spd(rng, E, 6, scale=0.004, cond=50)  # arbitrary correlated joint
    Pi, Pj = J[:, :3, :3], J[:, 3:, 3:]
    m = make_filter("ekf").relative_moments(x_i, Pi, x_j, Pj, R)
    nu = np.zeros((E, 2))
    _, P_ci, _, w = fused_update(x_i, Pi, x_j, Pj, nu, m, R, "ci")
    # Actual covariance of e_i+ = (I - K H_i) e_i - K H_j e_j + K v for the gain CI used.
    H_i, H_j = range_bearing_jacobians(x_i, x_j)
    used = w < 1
    A = Pi / np.where(used, w, 0.5)[:, None, None]
    B = Pj / np.where(used, 1 - w, 0.5)[:, None, None]
    S = H_i @ A @ H_i.transpose(0, 2, 1) + H_j @ B @ H_j.transpose(0, 2, 1) + R
    K = A @ H_i.transpose(0, 2, 1) @ np.linalg.inv(S)
    K[~used] = 0.0
    M = np.concatenate([np.eye(3) - K @ H_i, -K @ H_j], axis=2)  # (E, 3, 6)
    actual = M @ J @ M.transpose(0, 2, 1) + K @ R @ K.transpose(0, 2, 1)
    assert np.linalg.eigvalsh(P_ci - actual)[:, 0].min() > -1e-12


def test_split_ci_limits(rng, random_spd):
    """split CI: all-dependent parts give CI; all-independent parts give the naive update."""
    E = 30
    x_i, x_j = _links(rng, E)
    Pi = random_spd(rng, E, 3, scale=0.004, cond=10)
    Pj = random_spd(rng, E, 3, scale=0.002, cond=10)
    z = range_bearing(x_i, x_j) + rng.normal(size=(E, 2)) * [0.005, 0.05]
    for kind in ("ekf", "ckf"):
        m = make_filter(kind).relative_moments(x_i, Pi, x_j, Pj, R)
        nu = innovation(z, m.z_hat)
        zero = np.zeros_like(Pi)
        x_ci, P_ci, _, _ = fused_update(x_i, Pi, x_j, Pj, nu, m, R, "ci")
        x_s, P_s, _, _ = fused_update(x_i, Pi, x_j, Pj, nu, m, R, "split_ci", "trace", zero, zero)
        np.testing.assert_allclose(x_s, x_ci, atol=1e-12)
        np.testing.assert_allclose(P_s, P_ci, atol=1e-12)
        # Fully independent: the bound is the naive joint whatever w (the filter's own update).
        x_n, P_n, P_ind, _ = fused_update(
            x_i, Pi, x_j, Pj, nu, m, R, "split_ci", "trace", Pi.copy(), Pj.copy()
        )
        x_k, P_k = kalman_update(x_i, Pi, nu, m)
        np.testing.assert_allclose(x_n, x_k, atol=1e-9)
        np.testing.assert_allclose(P_n, P_k, atol=1e-9)
        assert np.linalg.eigvalsh(P_n - P_ind)[:, 0].min() > -1e-12


def test_fused_update_ekf_matches_the_bound_as_joint(rng, random_spd):
    """EKF: the extended moments equal an update whose joint covariance is the CI bound."""
    E = 10
    x_i, x_j = _links(rng, E)
    Pi = random_spd(rng, E, 3, scale=0.004, cond=10)
    Pj = random_spd(rng, E, 3, scale=0.001, cond=10)
    ekf = make_filter("ekf")
    m = ekf.relative_moments(x_i, Pi, x_j, Pj, R)
    nu = rng.normal(size=(E, 2)) * [0.005, 0.05]
    x_new, P_new, _, w = fused_update(x_i, Pi, x_j, Pj, nu, m, R, "ci")
    assert np.all(w < 1)
    A, B = Pi / w[:, None, None], Pj / (1 - w)[:, None, None]
    m2 = ekf.relative_moments(x_i, A, x_j, B, R)
    x2, P2 = kalman_update(x_i, A, nu, m2)
    np.testing.assert_allclose(x_new, x2, atol=1e-12)
    np.testing.assert_allclose(P_new, P2, atol=1e-12)


def test_clip_independent(rng, random_spd):
    P = random_spd(rng, 8, 3)
    P_ind = 3.0 * P  # too big: shrunk to at most P
    out = clip_independent(P, P_ind)
    assert np.linalg.eigvalsh(P - out)[:, 0].min() > -1e-12
    small = 0.5 * P
    np.testing.assert_allclose(clip_independent(P, small), small)


def test_propagate_independent_adds_process_noise(rng):
    x = np.zeros((2, 3))
    P_ind = np.zeros((2, 3, 3))
    out = propagate_independent(x, P_ind, np.array([[0.1, 0.0]] * 2), 0.1, [0.01, 0.05], [0, 0, 0])
    assert np.all(np.linalg.eigvalsh(out)[:, -1] > 0)


def test_fusion_enum_coerced():
    from resloc.cl.params import CLParams

    assert CLParams(fusion="ci").fusion is FusionMethod.CI
    assert CLParams(ci_criterion="det").ci_criterion is CICriterion.DET


# ----------------------------------------------------------------------------- tracking


def test_joint_covariance_matches_brute_force(rng, random_spd):
    """One team, EKF moments: the bookkeeping equals the joint covariance propagated by the
    stacked linear maps (prediction and one-sided updates from predicted estimates)."""
    N = 4
    P0 = random_spd(rng, N, 3, scale=0.003, cond=5)
    jc = JointCovariance(P0, N)
    big = np.zeros((3 * N, 3 * N))
    for r in range(N):
        big[3 * r : 3 * r + 3, 3 * r : 3 * r + 3] = P0[r]
    np.testing.assert_allclose(jc.sigma[0], big)
    x = np.column_stack([rng.uniform(-1, 1, N), rng.uniform(-1, 1, N), rng.uniform(-3, 3, N)])
    u = np.column_stack([rng.uniform(0, 0.2, N), rng.uniform(-1, 1, N)])
    Q = random_spd(rng, N, 3, scale=1e-5)
    from resloc.models.motion import unicycle_state_jacobian, unicycle_step

    F = unicycle_state_jacobian(x, u, 0.1)
    Fb = np.zeros_like(big)
    Qb = np.zeros_like(big)
    for r in range(N):
        Fb[3 * r : 3 * r + 3, 3 * r : 3 * r + 3] = F[r]
        Qb[3 * r : 3 * r + 3, 3 * r : 3 * r + 3] = Q[r]
    P_pred = jc.predict(x, u, 0.1, Q)
    big = Fb @ big @ Fb.T + Qb
    np.testing.assert_allclose(jc.sigma[0], big, atol=1e-15)
    xp = unicycle_step(x, u, 0.1)
    # Two rounds: robot 0 and 1 update from 2 and 3 (round 1), robot 0 from 1 (round 2).
    M = np.eye(3 * N)
    noise = np.zeros_like(big)
    xs = xp.copy()
    ekf = make_filter("ekf")
    for i, j in ((np.array([0, 1]), np.array([2, 3])), (np.array([0]), np.array([1]))):
        m = jc.moments(ekf, xs[i], None, xp[j], None, i, j, R)
        P_i = jc.current(i)
        for e in range(len(i)):  # brute-force moments from the stacked joint
            H_i, H_j = range_bearing_jacobians(xs[i[e]][None], xp[j[e]][None])
            Mi = M[3 * i[e] : 3 * i[e] + 3]
            C = Mi @ big[:, 3 * j[e] : 3 * j[e] + 3]
            Pii = Mi @ big @ Mi.T + noise[3 * i[e] : 3 * i[e] + 3, 3 * i[e] : 3 * i[e] + 3]
            np.testing.assert_allclose(P_i[e], Pii, atol=1e-15)
            Pjj = big[3 * j[e] : 3 * j[e] + 3, 3 * j[e] : 3 * j[e] + 3]
            S = (
                H_i[0] @ Pii @ H_i[0].T
                + H_i[0] @ C @ H_j[0].T
                + H_j[0] @ C.T @ H_i[0].T
                + H_j[0] @ Pjj @ H_j[0].T
                + R
            )
            np.testing.assert_allclose(m.S[e], S, atol=1e-15)
        K = m.Pxz @ np.linalg.inv(m.S)
        for e in range(len(i)):
            H_i, H_j = range_bearing_jacobians(xs[i[e]][None], xp[j[e]][None])
            rows = slice(3 * i[e], 3 * i[e] + 3)
            Mi = (np.eye(3) - K[e] @ H_i[0]) @ M[rows]
            Mi[:, 3 * j[e] : 3 * j[e] + 3] -= K[e] @ H_j[0]
            M[rows] = Mi
            IKH = np.eye(3) - K[e] @ H_i[0]
            noise[rows, rows] = IKH @ noise[rows, rows] @ IKH.T + K[e] @ R @ K[e].T
        P_new = jc.update(i, j, xs[i], xp[j], m, R)
        assert np.linalg.eigvalsh(P_new)[:, 0].min() > 0
    P_fin = jc.finish()
    expect = M @ big @ M.T + noise
    np.testing.assert_allclose(jc.sigma[0], expect, atol=1e-15)
    assert np.linalg.eigvalsh(jc.sigma[0])[0] > 0
    assert P_fin.shape == (N, 3, 3)
    assert P_pred.shape == (N, 3, 3)


@pytest.mark.parametrize("kind", ["ckf", "ukf", "ekf"])
def test_tracked_moments_without_correlation_equal_the_filters(rng, random_spd, kind):
    N = 3
    P0 = random_spd(rng, N, 3, scale=0.003, cond=5)
    jc = JointCovariance(P0, N)
    x = np.column_stack([[0.0, 0.5, -0.4], [0.0, 0.3, 0.6], [0.1, -0.2, 2.0]])
    i, j = np.array([0, 1]), np.array([1, 2])
    filt = make_filter(kind)
    m = jc.moments(filt, x[i], None, x[j], None, i, j, R)
    ref = filt.relative_moments(x[i], P0[i], x[j], P0[j], R)
    np.testing.assert_allclose(m.z_hat, ref.z_hat, atol=1e-12)
    np.testing.assert_allclose(m.S, ref.S, atol=1e-12)
    np.testing.assert_allclose(m.Pxz, ref.Pxz, atol=1e-12)


# ----------------------------------------------------------------------------- factorized


def _small_run(fusion: str, robots: int, filt: str = "ekf", steps: int = 120):
    from resloc.experiments.config import default_scenario
    from resloc.experiments.runner import run_scenario

    sc = default_scenario().replace(
        **{
            "team.robots": robots,
            "run.trials": 2,
            "run.steps": steps,
            "run.filters": [filt],
            "run.dead_reckoning": False,
            "estimator.fusion": fusion,
            "trigger.enabled": False,  # fuse every measurement: the cross terms matter
            "sdz": [],
            "cdz": [],
        }
    )
    return run_scenario(sc).estimators[filt]


def test_factorized_equals_tracked_for_two_robots():
    """With two robots no third-robot term exists: Luft et al.'s factors are exact, so the
    EKF (whose covariance equals the joint's block) matches tracked fusion step by step."""
    a = _small_run("tracked", 2)
    b = _small_run("factorized", 2)
    np.testing.assert_allclose(b.track, a.track, rtol=0, atol=1e-10)
    np.testing.assert_allclose(b.per_trial("nees_mean"), a.per_trial("nees_mean"), rtol=1e-8)
    naive = _small_run("naive", 2)
    assert np.abs(naive.track - a.track).max() > 1e-6  # the cross terms do matter


def test_factorized_factors_follow_prediction_and_pair_updates(rng, random_spd):
    """Factors: prediction left-multiplies by F_i; a pair that fused gets
    C = [A_a, B_ac] P_pred [B_ca, A_c]^T stored as (C, I)."""
    from resloc.cl.factorized import FactorizedCovariance
    from resloc.models.motion import unicycle_state_jacobian, unicycle_step

    N = 3
    fc = FactorizedCovariance(N, N)
    fc.sig[0, 1] = random_spd(rng, 1, 3, scale=0.01)[0]
    fc.sig[1, 0] = np.eye(3)
    x = np.column_stack([[0.0, 0.5, -0.4], [0.0, 0.3, 0.6], [0.1, -0.2, 2.0]])
    u = np.column_stack([[0.1, 0.2, 0.0], [0.3, -0.5, 0.1]])
    P_pred = random_spd(rng, N, 3, scale=0.003, cond=5)
    F = unicycle_state_jacobian(x, u, 0.1)
    sig_before = fc.sig.copy()
    fc.predict(x, u, 0.1, np.zeros((N, 3, 3)), P_pred)
    np.testing.assert_allclose(fc.sig[0, 1], F[0] @ sig_before[0, 1])
    C01 = fc.cross(np.array([0]), np.array([1]))[0]
    np.testing.assert_allclose(C01, F[0] @ sig_before[0, 1] @ F[1].T, atol=1e-15)
    xp = unicycle_step(x, u, 0.1)
    ekf = make_filter("ekf")
    i, j = np.array([0]), np.array([1])
    m = fc.moments(ekf, xp[i], P_pred[i], xp[j], P_pred[j], i, j, R)
    fc.update(i, j, xp[i], xp[j], m, R, P_pred[i])
    fc.finish(P_pred)
    K = m.Pxz[0] @ np.linalg.inv(m.S[0])
    H_i, H_j = range_bearing_jacobians(xp[i], xp[j])
    A0, B01 = np.eye(3) - K @ H_i[0], -K @ H_j[0]
    expect = A0 @ C01 + B01 @ P_pred[1]  # robot 1 did not update: A_1 = I, B_10 = 0
    np.testing.assert_allclose(fc.sig[0, 1] @ fc.sig[1, 0].T, expect, atol=1e-15)
    np.testing.assert_allclose(fc.sig[1, 0], np.eye(3))
    assert not fc.sig[0, 2].any() and not fc.sig[2, 0].any()  # never correlated


def test_valid_cross_shrinks_only_impossible_correlations(rng, random_spd):
    from resloc.cl.factorized import valid_cross

    Pi = random_spd(rng, 20, 3, scale=0.01, cond=10)
    Pj = random_spd(rng, 20, 3, scale=0.01, cond=10)
    C = rng.normal(size=(20, 3, 3)) * 0.05  # mostly far too large to be a cross-covariance
    Cv = valid_cross(Pi, Pj, C)
    J = np.block([[Pi, Cv], [np.swapaxes(Cv, -1, -2), Pj]])
    assert np.linalg.eigvalsh(J)[:, 0].min() > 0
    small = 1e-4 * C  # valid ones pass unchanged
    np.testing.assert_array_equal(valid_cross(Pi, Pj, small), small)
