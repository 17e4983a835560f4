"""Cross-checks of every resloc filter against FilterPy (STYLE habit 10).

Each filter is run against FilterPy on the same nonlinear problem (unicycle prediction,
eq. 2, then a relative range/bearing update, eq. 3, with a neighbour j) and the same
parameters; means and covariances of robot i must agree to 1e-9 at every one of 200 steps.

The common mapping, used by every test below
--------------------------------------------
* Our relative update of robot i is the x_i-marginal of a joint Kalman update over
  ``[x_i; x_j]`` with covariance ``blockdiag(P_i, P_j)`` (the paper keeps no
  cross-correlation). FilterPy runs that joint update on a 6-D state; we compare only the
  ``x_i`` block (``x[:3]``, ``P[:3, :3]``) and discard its ``x_j`` block.
* Prediction uses a separate 3-D FilterPy filter with the same ``Q`` (computed once per
  step from our estimate with :func:`resloc.models.process_noise`).
* FilterPy's callbacks (``fx``, ``hx``, Jacobians, means, residuals) are written here from
  the equations, independently of :mod:`resloc.models` and :mod:`resloc.angles`.
* FilterPy's filter objects never re-wrap their state; we wrap ``x[2]`` (heading) after
  each of its steps, which our filters do internally.

FilterPy 2.0 traps and how they are mapped (one per filter, stated in each test too)
-----------------------------------------------------------------------------------
* ``UnscentedKalmanFilter.update`` and ``CubatureKalmanFilter.update`` use whatever is in
  ``sigmas_f``; our filters redraw the points from ``chol(P_pred)`` in the update
  (Algorithm 1). Mapping: ``sigmas_f`` is overwritten with freshly drawn joint points
  before every ``update``.
* ``CubatureKalmanFilter`` averages angles arithmetically and ignores ``x_mean_fn``.
  Mapping: our ``SigmaPointFilter(..., circular=False)`` and a trajectory that keeps
  headings and bearings away from the +-pi seam.
* ``ExtendedKalmanFilter.predict`` is linear (``F x + B u``). Mapping: a subclass whose
  ``predict_x`` applies the unicycle model, with ``F`` set to its Jacobian before each call.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

filterpy_kalman = pytest.importorskip("filterpy.kalman")
from filterpy.kalman import (  # noqa: E402
    CubatureKalmanFilter,
    ExtendedKalmanFilter,
    MerweScaledSigmaPoints,
    UnscentedKalmanFilter,
)
from filterpy.kalman.CubatureKalmanFilter import spherical_radial_sigmas  # noqa: E402

from resloc.filters import (  # noqa: E402
    ExtendedFilter,
    FilterKind,
    SigmaPointFilter,
    cubature_rule,
    innovation,
    kalman_update,
    make_filter,
    merwe_scaled_rule,
)
from resloc.linalg import cholesky_jitter  # noqa: E402
from resloc.models import process_noise  # noqa: E402

TOL = 1e-9
N_STEPS = 200
DT = 0.1
ODO_STD = np.array([0.05, 0.1])
FLOOR_STD = np.array([1e-3, 1e-3, 1e-3])
R = np.diag([0.05**2, 0.03**2])


# --------------------------------------------------------------------------------------
# Reference model, written from eqs. (2) and (3) for FilterPy's one-vector callbacks.
# --------------------------------------------------------------------------------------
def wrap(a):
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def fx(x, dt, u):
    """Unicycle, eq. (2), one state ``(3,)``; heading wrapped."""
    v, w = u
    return np.array(
        [x[0] + v * np.cos(x[2]) * dt, x[1] + v * np.sin(x[2]) * dt, wrap(x[2] + w * dt)]
    )


def F_jac(x, dt, u):
    return np.array(
        [
            [1.0, 0.0, -u[0] * np.sin(x[2]) * dt],
            [0.0, 1.0, u[0] * np.cos(x[2]) * dt],
            [0.0, 0.0, 1.0],
        ]
    )


def hx_joint(xx):
    """Range/bearing of j (``xx[3:]``) seen by i (``xx[:3]``), eq. (3)."""
    dx, dy = xx[3] - xx[0], xx[4] - xx[1]
    return np.array([np.hypot(dx, dy), wrap(np.arctan2(dy, dx) - xx[2])])


def H_joint(xx):
    dx, dy = xx[3] - xx[0], xx[4] - xx[1]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    Hj = np.array([[dx / r, dy / r, 0.0], [-dy / q, dx / q, 0.0]])
    Hi = -Hj
    Hi[1, 2] = -1.0
    return np.hstack([Hi, Hj])


def pose_mean(sigmas, Wm):
    """Positions by weighted sum, heading by weighted circular mean (FilterPy x_mean_fn)."""
    return np.array(
        [
            Wm @ sigmas[:, 0],
            Wm @ sigmas[:, 1],
            np.arctan2(Wm @ np.sin(sigmas[:, 2]), Wm @ np.cos(sigmas[:, 2])),
        ]
    )


def pose_residual(a, b):
    d = np.subtract(a, b)
    d[2] = wrap(d[2])
    return d


def joint_residual(a, b):
    d = np.subtract(a, b)
    d[2] = wrap(d[2])
    d[5] = wrap(d[5])
    return d


def joint_add(a, b):
    s = np.add(a, b)
    s[2] = wrap(s[2])
    s[5] = wrap(s[5])
    return s


def z_mean(sigmas, Wm):
    """Range by weighted sum, bearing by weighted circular mean (FilterPy z_mean_fn)."""
    return np.array(
        [Wm @ sigmas[:, 0], np.arctan2(Wm @ np.sin(sigmas[:, 1]), Wm @ np.cos(sigmas[:, 1]))]
    )


def z_residual(a, b):
    d = np.subtract(a, b)
    d[1] = wrap(d[1])
    return d


def blockdiag(A, B):
    out = np.zeros((6, 6))
    out[:3, :3] = A
    out[3:, 3:] = B
    return out


# --------------------------------------------------------------------------------------
# A seeded scenario: truth of i, odometry, neighbour j's estimate (x_j, P_j), measurements.
# --------------------------------------------------------------------------------------
@dataclass
class Scenario:
    u: np.ndarray  # (T, 2) measured odometry
    x_j: np.ndarray  # (T, 3) neighbour estimate at each update
    P_j: np.ndarray  # (T, 3, 3)
    z: np.ndarray  # (T, 2)
    x0: np.ndarray  # (3,) initial estimate of i
    P0: np.ndarray  # (3, 3)


def make_scenario(seed: int, seam: bool) -> Scenario:
    """``seam=False``: headings in about [-1.2, 1.6] and bearings in about [-1, 1] (far from
    +-pi). ``seam=True``: i's heading and the bearing to j both cross +-pi repeatedly."""
    rng = np.random.default_rng(seed)
    k = np.arange(N_STEPS)
    if seam:
        v_true = 0.5 + 0.1 * np.sin(0.1 * k)
        w_true = np.full(N_STEPS, 0.6)  # about two turns in 200 steps
        bearing_true = np.pi + 0.5 * np.sin(0.07 * k)
        th0 = 2.9
    else:
        v_true = 0.5 + 0.1 * np.sin(0.1 * k)
        w_true = 0.4 * np.cos(0.03 * k)
        bearing_true = 0.7 * np.sin(0.05 * k)
        th0 = 0.2
    truth = np.array([0.0, 0.0, th0])
    u = np.column_stack([v_true, w_true]) + ODO_STD * rng.normal(size=(N_STEPS, 2))
    x_j = np.empty((N_STEPS, 3))
    P_j = np.empty((N_STEPS, 3, 3))
    z = np.empty((N_STEPS, 2))
    for t in range(N_STEPS):
        truth = fx(truth, DT, (v_true[t], w_true[t]))
        rng_ij = 2.0 + 0.5 * np.sin(0.02 * t)
        ang = truth[2] + bearing_true[t]
        truth_j = np.array(
            [truth[0] + rng_ij * np.cos(ang), truth[1] + rng_ij * np.sin(ang), wrap(ang - 1.0)]
        )
        A = 0.05 * rng.normal(size=(3, 3))
        P_j[t] = np.diag([0.02, 0.03, 0.01]) * (1.0 + 0.5 * np.sin(0.1 * t)) + A @ A.T
        x_j[t] = truth_j + np.linalg.cholesky(P_j[t]) @ rng.normal(size=3)
        x_j[t, 2] = wrap(x_j[t, 2])
        z[t] = hx_joint(np.concatenate([truth, truth_j])) + np.sqrt(np.diag(R)) * rng.normal(size=2)
        z[t, 1] = wrap(z[t, 1])
    x0 = np.array([0.3, -0.2, wrap(th0 + 0.1)])
    P0 = np.diag([0.1, 0.1, 0.05])
    return Scenario(u, x_j, P_j, z, x0, P0)


def run_ours(filt, sc: Scenario):
    """Our filter on the scenario; returns per-step predicted and corrected (x, P) and Q."""
    x, P = sc.x0[None].copy(), sc.P0[None].copy()
    out = {"xp": [], "Pp": [], "x": [], "P": [], "Q": []}
    for t in range(N_STEPS):
        Q = process_noise(x, DT, ODO_STD, FLOOR_STD)
        x, P = filt.predict(x, P, sc.u[t][None], DT, Q)
        out["Q"].append(Q[0])
        out["xp"].append(x[0])
        out["Pp"].append(P[0])
        m = filt.relative_moments(x, P, sc.x_j[t][None], sc.P_j[t][None], R)
        x, P = kalman_update(x, P, innovation(sc.z[t][None], m.z_hat), m)
        out["x"].append(x[0])
        out["P"].append(P[0])
    return {key: np.array(val) for key, val in out.items()}


def assert_pose_close(actual, desired, what: str, t: int) -> None:
    d = np.asarray(actual, float) - np.asarray(desired, float)
    d[..., 2] = wrap(d[..., 2])
    err = float(np.abs(d).max())
    assert err < TOL, f"{what} differs by {err:.3e} at step {t}"


def assert_cov_close(actual, desired, what: str, t: int) -> None:
    err = float(np.abs(np.asarray(actual) - np.asarray(desired)).max())
    assert err < TOL, f"{what} differs by {err:.3e} at step {t}"


def check_against(ours, predict_fp, update_fp, sc: Scenario) -> None:
    """Run FilterPy steps (closures over its own state) and compare at every step."""
    xf, Pf = sc.x0.copy(), sc.P0.copy()
    for t in range(N_STEPS):
        xf, Pf = predict_fp(xf, Pf, sc.u[t], ours["Q"][t])
        assert_pose_close(ours["xp"][t], xf, "predicted mean", t)
        assert_cov_close(ours["Pp"][t], Pf, "predicted covariance", t)
        xf, Pf = update_fp(xf, Pf, sc.x_j[t], sc.P_j[t], sc.z[t])
        assert_pose_close(ours["x"][t], xf, "corrected mean", t)
        assert_cov_close(ours["P"][t], Pf, "corrected covariance", t)


# --------------------------------------------------------------------------------------
# Point rules: the same points and weights as FilterPy's.
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [3, 6])
@pytest.mark.parametrize(("alpha", "beta", "kappa"), [(1.0, 2.0, 0.0), (0.8, 2.0, 1.0), (1, 0, 0)])
def test_merwe_rule_matches_filterpy_points_and_weights(
    n: int, alpha: float, beta: float, kappa: float, rng: np.random.Generator, random_spd
) -> None:
    """``merwe_scaled_rule`` = ``MerweScaledSigmaPoints`` (same order: centre, +k, -k;
    FilterPy's upper Cholesky rows are our lower factor's columns)."""
    rule = merwe_scaled_rule(n, alpha, beta, kappa)
    fp = MerweScaledSigmaPoints(n, alpha, beta, kappa)
    np.testing.assert_allclose(rule.Wm, fp.Wm, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(rule.Wc, fp.Wc, rtol=1e-14, atol=1e-15)
    x = rng.normal(size=(4, n))
    P = random_spd(rng, 4, n, cond=100.0)
    X = rule.points(x, cholesky_jitter(P))
    for b in range(4):
        np.testing.assert_allclose(X[b], fp.sigma_points(x[b], P[b]), rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("n", [3, 6])
def test_cubature_rule_matches_filterpy_points(
    n: int, rng: np.random.Generator, random_spd
) -> None:
    """``cubature_rule`` points = FilterPy's ``spherical_radial_sigmas`` (weights 1/(2n))."""
    rule = cubature_rule(n)
    np.testing.assert_allclose(rule.Wm, 1.0 / (2 * n))
    x = rng.normal(size=(4, n))
    P = random_spd(rng, 4, n, cond=100.0)
    X = rule.points(x, cholesky_jitter(P))
    for b in range(4):
        np.testing.assert_allclose(X[b], spherical_radial_sigmas(x[b], P[b]), rtol=1e-12)


# --------------------------------------------------------------------------------------
# UKF
# --------------------------------------------------------------------------------------
UKF_PARAMS = [(1.0, 2.0, 0.0), (0.8, 2.0, 1.0), (1.0, 0.0, 0.5)]


def ukf_steps(alpha: float, beta: float, kappa: float):
    pts3 = MerweScaledSigmaPoints(3, alpha, beta, kappa)
    pts6 = MerweScaledSigmaPoints(6, alpha, beta, kappa)
    pred = UnscentedKalmanFilter(
        3, 2, DT, hx=lambda x: x[:2], fx=fx, points=pts3,
        x_mean_fn=pose_mean, residual_x=pose_residual,
    )  # fmt: skip
    upd = UnscentedKalmanFilter(
        6, 2, DT, hx=hx_joint, fx=lambda x, dt: x, points=pts6,
        z_mean_fn=z_mean, residual_x=joint_residual, residual_z=z_residual,
        state_add=joint_add,
    )  # fmt: skip

    def predict_fp(x, P, u, Q):
        pred.x, pred.P, pred.Q = x.copy(), P.copy(), Q
        pred.predict(u=u)
        return pred.x.copy(), pred.P.copy()

    def update_fp(x, P, x_j, P_j, z):
        upd.x = np.concatenate([x, x_j])
        upd.P = blockdiag(P, P_j)
        upd.sigmas_f = pts6.sigma_points(upd.x, upd.P)  # the mapping for the reuse trap
        upd.update(z, R=R)
        return upd.x[:3].copy(), upd.P[:3, :3].copy()

    return predict_fp, update_fp


@pytest.mark.parametrize("seam", [False, True], ids=["no-seam", "seam"])
@pytest.mark.parametrize(("alpha", "beta", "kappa"), UKF_PARAMS)
def test_ukf_matches_filterpy_ukf_200_steps(
    alpha: float, beta: float, kappa: float, seam: bool
) -> None:
    """``make_filter('ukf', alpha, beta, kappa)`` vs FilterPy ``UnscentedKalmanFilter``.

    Mapping: predict = 3-D FilterPy UKF with ``MerweScaledSigmaPoints(3, alpha, beta,
    kappa)``, ``x_mean_fn`` = circular heading mean, ``residual_x`` wrapping the heading.
    Update = 6-D FilterPy UKF on ``[x_i; x_j]``, ``P = blockdiag(P_i, P_j)``,
    ``MerweScaledSigmaPoints(6, ...)``, ``sigmas_f`` overwritten by
    ``points.sigma_points(x, P)`` before ``update`` (our update redraws points from the
    predicted covariance), ``z_mean_fn`` = circular bearing mean, ``residual_z`` /
    ``residual_x`` / ``state_add`` wrapping angles. Compare the ``x_i`` block only. Both
    trajectories (with and without +-pi crossings) must agree: the UKF is circular on both
    sides.
    """
    sc = make_scenario(seed=11 if seam else 7, seam=seam)
    ours = run_ours(make_filter("ukf", alpha, beta, kappa), sc)
    check_against(ours, *ukf_steps(alpha, beta, kappa), sc)


# --------------------------------------------------------------------------------------
# CKF
# --------------------------------------------------------------------------------------
def ckf_steps():
    pred = CubatureKalmanFilter(3, 2, DT, hx=lambda x: x[:2], fx=fx)
    upd = CubatureKalmanFilter(6, 2, DT, hx=hx_joint, fx=lambda x, dt: x, residual_z=z_residual)

    def predict_fp(x, P, u, Q):
        pred.x, pred.P, pred.Q = x.copy(), P.copy(), Q
        pred.predict(fx_args=(u,))
        xn = pred.x.ravel().copy()  # FilterPy's CKF returns a column (3, 1)
        xn[2] = wrap(xn[2])
        return xn, pred.P.copy()

    def update_fp(x, P, x_j, P_j, z):
        # FilterPy's CKF keeps x as a column (6, 1); z must be a column too, or x + K y
        # broadcasts to (6, 6).
        upd.x = np.concatenate([x, x_j])[:, None]
        upd.P = blockdiag(P, P_j)
        upd.sigmas_f = spherical_radial_sigmas(upd.x, upd.P)  # the mapping for reuse
        upd.update(z[:, None], R=R)
        xn = upd.x[:3, 0].copy()
        xn[2] = wrap(xn[2])
        return xn, upd.P[:3, :3].copy()

    return predict_fp, update_fp


def test_ckf_arithmetic_matches_filterpy_ckf_200_steps() -> None:
    """``SigmaPointFilter(CKF, cubature_rule(3), cubature_rule(6), circular=False)`` vs
    FilterPy ``CubatureKalmanFilter``.

    Mapping: FilterPy's CKF averages angles arithmetically and ignores ``x_mean_fn``:
    hence ``circular=False`` on our side and a trajectory with headings and bearings far
    from +-pi (``seam=False``), where wrapping is the identity. FilterPy's ``update``
    reuses the propagated ``sigmas_f``: overwritten with ``spherical_radial_sigmas(x, P)``
    of the joint ``[x_i; x_j]`` before each update. FilterPy's covariance uses
    ``sum X X^T / m - x x^T`` (cancellation is ~1e-14 here, positions stay < 20 m).
    """
    sc = make_scenario(seed=5, seam=False)
    assert np.abs(wrap(sc.z[:, 1])).max() < 2.0
    filt = SigmaPointFilter(FilterKind.CKF, cubature_rule(3), cubature_rule(6), circular=False)
    ours = run_ours(filt, sc)
    assert np.abs(ours["x"][:, 2]).max() < 2.0  # far from the seam: the mapping holds
    check_against(ours, *ckf_steps(), sc)


def test_ckf_circular_equals_arithmetic_away_from_seam() -> None:
    """Closes the loop to the default CKF: away from +-pi the circular mean of a tight
    cloud differs from the arithmetic one only at second order in the spread; our
    default (circular) CKF stays within 1e-3 of the FilterPy-equivalent one here."""
    sc = make_scenario(seed=5, seam=False)
    arith = run_ours(
        SigmaPointFilter(FilterKind.CKF, cubature_rule(3), cubature_rule(6), circular=False), sc
    )
    circ = run_ours(make_filter("ckf"), sc)
    diff = circ["x"] - arith["x"]
    diff[:, 2] = wrap(diff[:, 2])
    assert 0.0 < np.abs(diff).max() < 1e-3


def test_filterpy_ckf_update_reuses_propagated_points() -> None:
    """Documents the trap behind the CKF mapping: without overwriting ``sigmas_f``,
    FilterPy's CKF updates with the points it propagated in ``predict`` (a different
    cloud from the one drawn from ``P_pred``), so it no longer matches Algorithm 1."""
    pred = CubatureKalmanFilter(3, 2, DT, hx=lambda x: np.array([x[0], x[1]]), fx=fx)
    pred.x, pred.P = np.array([0.0, 0.0, 0.3]), np.diag([0.2, 0.2, 0.3])
    pred.Q = np.diag([1e-2, 1e-2, 1e-2])
    pred.predict(fx_args=((1.0, 0.5),))
    fresh = spherical_radial_sigmas(pred.x, pred.P)
    assert np.abs(pred.sigmas_f - fresh).max() > 1e-3


# --------------------------------------------------------------------------------------
# EKF
# --------------------------------------------------------------------------------------
class UnicycleEKF(ExtendedKalmanFilter):
    """FilterPy EKF whose state prediction is the nonlinear unicycle (``u = (u, dt)``)."""

    def predict_x(self, u=0):
        u_k, dt = u
        self.x = fx(self.x, dt, u_k)


def ekf_steps():
    pred = UnicycleEKF(3, 2)
    upd = ExtendedKalmanFilter(6, 2)

    def predict_fp(x, P, u, Q):
        pred.x, pred.P, pred.Q = x.copy(), P.copy(), Q
        pred.F = F_jac(x, DT, u)  # Jacobian at the prior, as x = f(x, u) uses
        pred.predict(u=(u, DT))
        return pred.x.copy(), pred.P.copy()

    def update_fp(x, P, x_j, P_j, z):
        upd.x = np.concatenate([x, x_j])
        upd.P = blockdiag(P, P_j)
        upd.update(z, HJacobian=H_joint, Hx=hx_joint, R=R, residual=z_residual)
        xn = upd.x[:3].copy()
        xn[2] = wrap(xn[2])
        return xn, upd.P[:3, :3].copy()

    return predict_fp, update_fp


@pytest.mark.parametrize("seam", [False, True], ids=["no-seam", "seam"])
def test_ekf_matches_filterpy_ekf_200_steps(seam: bool) -> None:
    """``ExtendedFilter`` vs FilterPy ``ExtendedKalmanFilter``.

    Mapping: predict = subclass with ``predict_x`` applying the unicycle and ``F`` set to
    its Jacobian at the prior before ``predict`` (FilterPy's own ``predict_x`` is linear);
    ``P = F P F^T + Q`` as ours. Update = 6-D EKF on ``[x_i; x_j]`` with
    ``P = blockdiag(P_i, P_j)``, ``H = [H_i, H_j]``, ``residual`` wrapping the bearing;
    FilterPy's Joseph form ``(I-KH) P (I-KH)^T + K R K^T`` on the joint state has as its
    ``x_i`` block our ``(I-K_i H_i) P_i (.)^T + K_i (H_j P_j H_j^T + R) K_i^T``.
    FilterPy does not wrap the state: we wrap its heading after each step.
    """
    sc = make_scenario(seed=3 if seam else 2, seam=seam)
    ours = run_ours(ExtendedFilter(), sc)
    check_against(ours, *ekf_steps(), sc)


def test_ekf_moments_are_joint_linearization(rng: np.random.Generator, random_spd) -> None:
    """Single-step batch check of ``ExtendedFilter.relative_moments``: ``S``, ``Pxz`` and
    ``R_eff`` are the blocks of the joint ``H blockdiag(P_i, P_j) H^T + R``."""
    E = 16
    x_i = np.column_stack([rng.normal(size=(E, 2)), rng.uniform(-np.pi, np.pi, E)])
    x_j = x_i + np.column_stack([rng.uniform(1, 3, E), rng.uniform(1, 3, E), np.zeros(E)])
    P_i, P_j = random_spd(rng, E, 3, 0.1), random_spd(rng, E, 3, 0.1)
    m = ExtendedFilter().relative_moments(x_i, P_i, x_j, P_j, R)
    for e in range(E):
        xx = np.concatenate([x_i[e], x_j[e]])
        H = H_joint(xx)
        Pjoint = blockdiag(P_i[e], P_j[e])
        np.testing.assert_allclose(m.z_hat[e], hx_joint(xx), atol=1e-14)
        np.testing.assert_allclose(m.S[e], H @ Pjoint @ H.T + R, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(m.Pxz[e], (Pjoint @ H.T)[:3], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(
            m.R_eff[e], H[:, 3:] @ P_j[e] @ H[:, 3:].T + R, rtol=1e-12, atol=1e-15
        )
