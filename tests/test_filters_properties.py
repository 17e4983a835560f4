"""Properties of the filter strategies: CKF = UKF(1, 0, 0), agreement in the linear limit,
batch independence, the shared Kalman correction, and positive definiteness on a long run."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.angles import wrap_angle
from resloc.filters import (
    ExtendedFilter,
    FilterKind,
    Moments,
    SigmaPointFilter,
    covariance_is_pd,
    cubature_rule,
    innovation,
    kalman_update,
    make_filter,
    merwe_scaled_rule,
    repair_covariance,
)
from resloc.linalg import cholesky_jitter, is_positive_definite
from resloc.models import process_noise, range_bearing

R = np.diag([0.05**2, 0.03**2])
ODO_STD = np.array([0.05, 0.1])
FLOOR_STD = np.array([1e-3, 1e-3, 1e-3])


def random_problem(rng: np.random.Generator, random_spd, B: int, p_scale: float = 0.1):
    """A batch of priors, odometry and neighbours at 0.5 to 4 m, ``P`` scaled by p_scale."""
    x = np.column_stack([rng.uniform(-5, 5, (B, 2)), rng.uniform(-np.pi, np.pi, B)])
    P = random_spd(rng, B, 3, scale=p_scale, cond=20.0)
    u = np.column_stack([rng.uniform(-1, 1, B), rng.uniform(-2, 2, B)])
    ang = rng.uniform(-np.pi, np.pi, B)
    dist = rng.uniform(0.5, 4.0, B)
    x_j = np.column_stack(
        [x[:, 0] + dist * np.cos(ang), x[:, 1] + dist * np.sin(ang), rng.uniform(-3, 3, B)]
    )
    P_j = random_spd(rng, B, 3, scale=p_scale, cond=20.0)
    z = range_bearing(x, x_j) + rng.normal(size=(B, 2)) * np.sqrt(np.diag(R))
    z[:, 1] = wrap_angle(z[:, 1])
    return x, P, u, x_j, P_j, z


def one_step(filt, x, P, u, x_j, P_j, z, dt=0.1):
    """Predict then one relative update; returns everything for comparison."""
    Q = process_noise(x, dt, ODO_STD, FLOOR_STD)
    xp, Pp = filt.predict(x, P, u, dt, Q)
    m = filt.relative_moments(xp, Pp, x_j, P_j, R)
    xu, Pu = kalman_update(xp, Pp, innovation(z, m.z_hat), m)
    return {"xp": xp, "Pp": Pp, "z_hat": m.z_hat, "S": m.S, "Pxz": m.Pxz, "x": xu, "P": Pu}


def assert_states_close(a: dict, b: dict, atol: float, rtol: float = 0.0) -> None:
    for key in a:
        da, db = a[key], b[key]
        if key in ("xp", "x"):
            d = da - db
            d[:, 2] = wrap_angle(d[:, 2])
            np.testing.assert_allclose(d, 0.0, atol=atol, err_msg=key)
        elif key == "z_hat":
            d = da - db
            d[:, 1] = wrap_angle(d[:, 1])
            np.testing.assert_allclose(d, 0.0, atol=atol, err_msg=key)
        else:
            np.testing.assert_allclose(da, db, atol=atol, rtol=rtol, err_msg=key)


# --------------------------------------------------------------------------------------
# CKF = UKF(alpha=1, beta=0, kappa=0)  (STYLE habit 3)
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [2, 3, 6])
def test_cubature_equals_unscented_1_0_0_moments(
    n: int, rng: np.random.Generator, random_spd
) -> None:
    """Same mean and covariance of a *nonlinear* function through either rule: the scaled
    unscented rule with alpha=1, beta=0, kappa=0 has a zero-weight centre point and the
    cubature points +-sqrt(n) e_k with weights 1/(2n)."""
    cub, mer = cubature_rule(n), merwe_scaled_rule(n, 1.0, 0.0, 0.0)
    assert mer.Wm[0] == 0.0
    assert mer.Wc[0] == 0.0
    np.testing.assert_allclose(mer.unit[1:], cub.unit, atol=1e-15)
    np.testing.assert_allclose(mer.Wm[1:], cub.Wm, atol=1e-15)
    np.testing.assert_allclose(mer.Wc[1:], cub.Wc, atol=1e-15)
    for rule in (cub, mer):  # both rules: first and second moments of N(0, I) exact
        np.testing.assert_allclose(rule.Wm @ rule.unit, 0.0, atol=1e-14)
        np.testing.assert_allclose(rule.unit.T @ (rule.Wc[:, None] * rule.unit), np.eye(n))

    x = rng.normal(size=(8, n))
    L = cholesky_jitter(random_spd(rng, 8, n, scale=0.5))

    def g(X):  # nonlinear, vector-valued
        return np.stack([np.sin(X[..., 0]) * X[..., -1], np.exp(0.3 * X[..., 1]), X[..., 0] ** 3])

    out = []
    for rule in (cub, mer):
        Y = np.moveaxis(g(rule.points(x, L)), 0, -1)  # (8, m, 3)
        mean = np.einsum("bmi,m->bi", Y, rule.Wm)
        d = Y - mean[:, None, :]
        out.append((mean, np.einsum("bmi,m,bmj->bij", d, rule.Wc, d)))
    np.testing.assert_allclose(out[0][0], out[1][0], rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(out[0][1], out[1][1], rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("circular", [True, False])
def test_ckf_filter_equals_ukf_1_0_0_filter(
    circular: bool, rng: np.random.Generator, random_spd
) -> None:
    """Predict, relative moments and the Kalman update agree to 1e-12 on the nonlinear
    unicycle/range-bearing problem (large covariances: strongly nonlinear)."""
    ckf = SigmaPointFilter(FilterKind.CKF, cubature_rule(3), cubature_rule(6), circular)
    ukf = SigmaPointFilter(
        FilterKind.UKF, merwe_scaled_rule(3, 1, 0, 0), merwe_scaled_rule(6, 1, 0, 0), circular
    )
    problem = random_problem(rng, random_spd, 64, p_scale=0.5)
    assert_states_close(one_step(ckf, *problem), one_step(ukf, *problem), atol=1e-12)
    # The factory's default CKF is that filter with circular means.
    if circular:
        assert_states_close(
            one_step(make_filter("ckf"), *problem),
            one_step(make_filter("ukf", 1.0, 0.0, 0.0), *problem),
            atol=1e-12,
        )


def test_ukf_with_beta_differs_from_ckf(rng: np.random.Generator, random_spd) -> None:
    """The equality above is not vacuous: beta=2 changes the covariances."""
    problem = random_problem(rng, random_spd, 16, p_scale=0.5)
    a = one_step(make_filter("ckf"), *problem)
    b = one_step(make_filter("ukf", 1.0, 2.0, 0.0), *problem)
    assert np.abs(a["Pp"] - b["Pp"]).max() > 1e-4


def test_merwe_rule_rejects_nonpositive_spread() -> None:
    with pytest.raises(ValueError, match="n \\+ lambda"):
        merwe_scaled_rule(3, 0.5, 2.0, -3.0)  # n + lambda = alpha^2 (n + kappa) = 0


def test_make_filter_kinds() -> None:
    assert make_filter("ckf").kind is FilterKind.CKF
    assert make_filter(FilterKind.UKF).kind is FilterKind.UKF
    assert isinstance(make_filter("ekf"), ExtendedFilter)
    with pytest.raises(ValueError):
        make_filter("pf")


# --------------------------------------------------------------------------------------
# Linear and linear-Gaussian limits: every filter agrees.
# --------------------------------------------------------------------------------------
FILTERS = {
    "ckf": make_filter("ckf"),
    "ukf": make_filter("ukf", 1.0, 2.0, 0.0),
    "ukf-kappa": make_filter("ukf", 0.8, 2.0, 1.0),
    "ekf": ExtendedFilter(),
}


def test_zero_speed_prediction_is_linear_and_exact(rng: np.random.Generator, random_spd) -> None:
    """With ``v = 0`` the unicycle is linear in x (``theta += omega dt``): every filter
    predicts exactly ``x = f(x)``, ``P = P + Q``."""
    x, P, u, *_ = random_problem(rng, random_spd, 32, p_scale=0.05)
    u[:, 0] = 0.0
    Q = process_noise(x, 0.1, ODO_STD, FLOOR_STD)
    expected_x = x.copy()
    expected_x[:, 2] = wrap_angle(x[:, 2] + 0.1 * u[:, 1])
    for name, filt in FILTERS.items():
        xp, Pp = filt.predict(x, P, u, 0.1, Q)
        d = xp - expected_x
        d[:, 2] = wrap_angle(d[:, 2])
        np.testing.assert_allclose(d, 0.0, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(Pp, P + Q, rtol=1e-10, atol=1e-14, err_msg=name)


def test_linear_gaussian_limit_all_filters_agree(rng: np.random.Generator, random_spd) -> None:
    """Tiny covariances (the models are linear over the cloud) and a tiny time step: the
    CKF, the UKFs and the EKF give the same predict, moments and update to first order.
    Differences are second order in the spread: means differ by ~P/range ~ 1e-8 (the
    first-order terms are ~sqrt(P) ~ 1e-4), covariances relatively by ~P."""
    p_scale = 1e-8
    problem = random_problem(rng, random_spd, 32, p_scale=p_scale)
    results = {name: one_step(filt, *problem, dt=1e-3) for name, filt in FILTERS.items()}
    ref = results["ekf"]
    for name, res in results.items():
        for key in ("xp", "x", "z_hat"):
            d = res[key] - ref[key]
            d[:, -1] = wrap_angle(d[:, -1]) if key != "xp" else d[:, -1]
            np.testing.assert_allclose(d, 0.0, atol=10 * p_scale, err_msg=f"{name} {key}")
        for key in ("Pp", "S", "Pxz", "P"):
            scale = np.abs(ref[key]).max(axis=(-1, -2), keepdims=True)
            err = np.abs(res[key] - ref[key]) / scale
            assert err.max() < 1e3 * p_scale, f"{name} {key}: relative difference {err.max():.2e}"


def test_large_covariance_filters_differ(rng: np.random.Generator, random_spd) -> None:
    """Control for the test above: with large covariances the nonlinearity shows."""
    problem = random_problem(rng, random_spd, 32, p_scale=0.5)
    a = one_step(FILTERS["ckf"], *problem)
    b = one_step(FILTERS["ekf"], *problem)
    assert np.abs(a["S"] - b["S"]).max() > 1e-3


# --------------------------------------------------------------------------------------
# Batch independence and the shared correction.
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(FILTERS))
def test_batch_equals_single_rows(name: str, rng: np.random.Generator, random_spd) -> None:
    filt = FILTERS[name]
    problem = random_problem(rng, random_spd, 6, p_scale=0.2)
    batch = one_step(filt, *problem)
    for b in range(6):
        single = one_step(filt, *(a[b : b + 1] for a in problem))
        for key, val in single.items():
            np.testing.assert_allclose(val[0], batch[key][b], rtol=1e-12, atol=1e-14)


def test_innovation_wraps_bearing() -> None:
    z = np.array([[1.0, np.pi - 0.1], [2.0, 0.3]])
    z_hat = np.array([[0.5, -np.pi + 0.1], [2.5, 0.1]])
    np.testing.assert_allclose(innovation(z, z_hat), [[0.5, -0.2], [-0.5, 0.2]], atol=1e-14)


def test_kalman_update_hand_computed_and_joseph(rng: np.random.Generator, random_spd) -> None:
    """``K = Pxz S^-1``; ``P - K S K^T`` without a Jacobian; with ``H_i`` and ``R_eff``
    the Joseph form, which for the optimal gain equals ``P - K S K^T``."""
    E = 10
    x = rng.normal(size=(E, 3))
    P = random_spd(rng, E, 3, scale=0.3)
    H = rng.normal(size=(E, 2, 3))
    R_eff = random_spd(rng, E, 2, scale=0.05)
    S = H @ P @ np.swapaxes(H, -1, -2) + R_eff
    Pxz = P @ np.swapaxes(H, -1, -2)
    nu = rng.normal(size=(E, 2))
    K = Pxz @ np.linalg.inv(S)
    x_exp = x + np.einsum("eij,ej->ei", K, nu)
    x_exp[:, 2] = wrap_angle(x_exp[:, 2])
    P_exp = P - K @ S @ np.swapaxes(K, -1, -2)

    x1, P1 = kalman_update(x, P, nu, Moments(np.zeros((E, 2)), S, Pxz))
    x2, P2 = kalman_update(x, P, nu, Moments(np.zeros((E, 2)), S, Pxz, H_i=H, R_eff=R_eff))
    for xa, Pa in ((x1, P1), (x2, P2)):
        np.testing.assert_allclose(xa, x_exp, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(Pa, P_exp, rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(Pa, np.swapaxes(Pa, -1, -2))
    # Joseph form with a suboptimal gain is PSD and differs from P - K S K^T: use a
    # wrong R_eff to see that the Joseph branch is the one taken.
    _, P3 = kalman_update(
        x, P, nu, Moments(np.zeros((E, 2)), S, Pxz, H_i=H, R_eff=R_eff + np.eye(2))
    )
    assert np.abs(P3 - P_exp).min() >= 0.0
    assert np.abs(P3 - P_exp).max() > 1e-3


def test_covariance_is_pd_and_repair(rng: np.random.Generator, random_spd) -> None:
    good = random_spd(rng, 50, 3, cond=1e6)
    A = rng.normal(size=(50, 3, 3))
    mixed = np.concatenate([good, 0.5 * (A + np.swapaxes(A, -1, -2))])
    np.testing.assert_array_equal(covariance_is_pd(mixed), is_positive_definite(mixed))
    bad = np.stack([np.diag([1.0, -1e-3, 1.0]), np.diag([np.nan, 1.0, 1.0]), np.ones((3, 3))])
    with np.errstate(invalid="ignore"):
        assert not covariance_is_pd(bad).any()
    fixed = repair_covariance(bad[[0, 2]])
    assert covariance_is_pd(fixed).all()
    np.testing.assert_allclose(fixed[0], np.diag([1.0, 0.0, 1.0]), atol=1e-11)
    np.testing.assert_allclose(fixed[1], np.ones((3, 3)), atol=1e-11)
    # PD matrices pass through (up to round-off).
    np.testing.assert_allclose(repair_covariance(good), good, rtol=1e-9, atol=1e-15)


# --------------------------------------------------------------------------------------
# Long run: covariances stay positive definite and finite.
# --------------------------------------------------------------------------------------
@pytest.mark.slow
def test_long_run_covariances_stay_pd() -> None:
    """100,000 robot-steps per filter (50 independent lanes x 2,000 sequential steps) of one
    robot plus one neighbour, for the CKF, UKF and EKF on the same random inputs: random
    odometry (with rare huge speeds), random neighbours, ~2% huge measurement outliers,
    ~2% near-zero ranges (the neighbour on top of the robot, to 1e-9 m), ~1% neighbours
    with huge or tiny covariances. Every covariance after every predict and update must
    pass ``covariance_is_pd`` and every state must be finite; no repair is applied."""
    lanes, steps, dt = 50, 2_000, 0.1
    rng = np.random.default_rng(12345)
    filters = [make_filter("ckf"), make_filter("ukf", 1.0, 2.0, 0.0), ExtendedFilter()]
    nf = len(filters)
    x = np.zeros((nf, lanes, 3))
    P = np.tile(np.diag([0.1, 0.1, 0.05]), (nf, lanes, 1, 1))
    truth = np.zeros((lanes, 3))
    first_bad: dict[str, int] = {}
    for k in range(steps):
        u = np.column_stack([rng.uniform(-0.5, 1.0, lanes), rng.uniform(-2.0, 2.0, lanes)])
        u[rng.random(lanes) < 0.005, 0] = 50.0
        u_meas = u + ODO_STD * rng.normal(size=(lanes, 2))
        truth[:, 0] += u[:, 0] * np.cos(truth[:, 2]) * dt
        truth[:, 1] += u[:, 0] * np.sin(truth[:, 2]) * dt
        truth[:, 2] = wrap_angle(truth[:, 2] + u[:, 1] * dt)
        # The neighbour, placed relative to the truth; its estimate and covariance.
        ang = rng.uniform(-np.pi, np.pi, lanes)
        dist = rng.uniform(0.2, 5.0, lanes)
        near = rng.random(lanes) < 0.02
        dist[near] = 1e-9
        truth_j = np.column_stack(
            [
                truth[:, 0] + dist * np.cos(ang),
                truth[:, 1] + dist * np.sin(ang),
                rng.uniform(-np.pi, np.pi, lanes),
            ]
        )
        sd_j = np.exp(rng.uniform(np.log(1e-3), np.log(0.3), lanes))
        odd = rng.random(lanes) < 0.01
        sd_j[odd] = rng.choice([1e-6, 1e2], odd.sum())
        P_j = (sd_j**2)[:, None, None] * np.eye(3)
        x_j = truth_j + sd_j[:, None] * rng.normal(size=(lanes, 3))
        x_j[:, 2] = wrap_angle(x_j[:, 2])
        z = range_bearing(truth, truth_j) + np.sqrt(np.diag(R)) * rng.normal(size=(lanes, 2))
        outlier = rng.random(lanes) < 0.02
        z[outlier] += rng.choice([-1.0, 1.0], (outlier.sum(), 2)) * [1e4, 3.0]
        z[:, 1] = wrap_angle(z[:, 1])
        for f, filt in enumerate(filters):
            Q = process_noise(x[f], dt, ODO_STD, FLOOR_STD)
            xf, Pf = filt.predict(x[f], P[f], u_meas, dt, Q)
            ok_pred = covariance_is_pd(Pf)
            m = filt.relative_moments(xf, Pf, x_j, P_j, R)
            xf, Pf = kalman_update(xf, Pf, innovation(z, m.z_hat), m)
            ok = ok_pred & covariance_is_pd(Pf) & np.isfinite(xf).all(axis=1)
            if not ok.all() and filt.kind.value not in first_bad:
                first_bad[filt.kind.value] = k
            x[f], P[f] = xf, Pf
    assert not first_bad, f"first non-PD / non-finite step per filter: {first_bad}"
    assert np.isfinite(P).all()
