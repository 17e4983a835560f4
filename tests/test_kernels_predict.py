"""The compiled prediction (:mod:`resloc.cl.kernels_predict`) against the numpy reference
(:func:`resloc.cl.step.predict` with the numpy backend)."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.angles import wrap_angle
from resloc.cl import CLParams, kernels, predict
from resloc.cl import kernels_predict as kp
from resloc.errors import NumericalError
from resloc.filters import SigmaPointFilter, make_filter
from resloc.filters.base import FilterKind
from resloc.filters.sigma_points import cubature_rule, merwe_scaled_rule

needs_numba = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")
FILTERS = {
    "ckf": make_filter("ckf"),
    "ukf": make_filter("ukf", 0.8, 2.0, 1.0),
    "ukf-default": make_filter("ukf"),
    "ekf": make_filter("ekf"),
    "ckf-arith": SigmaPointFilter(FilterKind.CKF, cubature_rule(3), cubature_rule(6), False),
}


def random_state(seed: int, B: int = 300):
    """Headings everywhere on the circle (some at +-pi exactly), standard deviations from
    1e-4 to 0.3 (wider heading spreads with the UKF's negative centre weight make the
    circular mean ill-conditioned: both paths are then right to their rounding only),
    some turning fast enough to wrap during the step, some standing still."""
    rng = np.random.default_rng(seed)
    x = np.column_stack([rng.uniform(-50, 50, (B, 2)), rng.uniform(-np.pi, np.pi, B)])
    x[:4, 2] = [np.pi - 1e-12, -np.pi, np.pi - 0.01, -np.pi + 1e-9]
    sd = 10.0 ** rng.uniform(-4, -0.5, B)
    A = rng.normal(size=(B, 3, 3)) * sd[:, None, None]
    P = A @ np.swapaxes(A, 1, 2) + 1e-10 * np.eye(3)
    u = np.column_stack([rng.uniform(-1, 1, B), rng.uniform(-20, 20, B)])
    u[5:9] = 0.0
    return x, P, u


def reference(filt, x, P, u, dt, params):
    with kernels.use_backend("numpy"):
        return predict(filt, x, P, u, dt, params)


def assert_close(a, b):
    (xa, Pa), (xb, Pb) = a, b
    d = xa - xb
    d[:, 2] = wrap_angle(d[:, 2])
    np.testing.assert_allclose(d, 0.0, atol=1e-9)
    np.testing.assert_allclose(Pa, Pb, rtol=1e-9, atol=1e-12)


@needs_numba
@pytest.mark.parametrize("name", sorted(FILTERS))
@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_predict_equals_numpy(name, seed, monkeypatch):
    filt = FILTERS[name]
    x, P, u = random_state(seed)
    params = CLParams(odometry_std=(0.02, 0.1), process_floor_std=(1e-3, 2e-3, 3e-3))
    ran = []
    for loop in ("_predict_robots", "predict_lanes"):  # robot by robot, or in lanes
        original = getattr(kp, loop)

        def spy(*args, original=original):
            ran.append(True)
            return original(*args)

        monkeypatch.setattr(kp, loop, spy)
    with kernels.use_backend("numba"):
        got = predict(filt, x, P, u, 0.05, params)
    assert ran, "the compiled prediction did not run"
    assert_close(got, reference(filt, x, P, u, 0.05, params))
    # Symmetric output, and the inputs untouched.
    np.testing.assert_array_equal(got[1], np.swapaxes(got[1], 1, 2))


@needs_numba
def test_compiled_predict_per_robot_odometry_noise_and_batch_of_one():
    filt = FILTERS["ckf"]
    x, P, u = random_state(3, B=50)
    odo = np.column_stack([np.linspace(0.01, 0.1, 50), np.linspace(0.05, 0.2, 50)])
    params = CLParams(odometry_std=odo)
    with kernels.use_backend("numba"):
        assert kp.fast_predict(filt, x, P, u, 0.033, params) is not None
        got = predict(filt, x, P, u, 0.033, params)
        one = predict(filt, x[:1], P[:1], u[:1], 0.033, CLParams())
    assert_close(got, reference(filt, x, P, u, 0.033, params))
    assert_close(one, reference(filt, x[:1], P[:1], u[:1], 0.033, CLParams()))


@needs_numba
def test_compiled_predict_gives_up_where_the_reference_raises():
    filt = FILTERS["ckf"]
    x, P, u = random_state(4, B=10)
    P_bad = P.copy()
    P_bad[3] = -np.eye(3)
    P_nan = P.copy()
    P_nan[2, 0, 0] = np.nan
    with kernels.use_backend("numba"):
        assert kp.fast_predict(filt, x, P_bad, u, 0.033, CLParams()) is None
        assert kp.fast_predict(filt, x, P_nan, u, 0.033, CLParams()) is None
        with pytest.raises(NumericalError):
            predict(filt, x, P_bad, u, 0.033, CLParams())
        # Shapes other than the documented ones go to the reference path.
        assert kp.fast_predict(filt, x[:, :2], P, u, 0.033, CLParams()) is None


def test_numpy_backend_and_unknown_filters_are_refused():
    x, P, u = random_state(5, B=5)
    with kernels.use_backend("numpy"):
        assert kp.fast_predict(FILTERS["ckf"], x, P, u, 0.033, CLParams()) is None

    class Other(SigmaPointFilter):
        pass

    other = Other(FilterKind.UKF, merwe_scaled_rule(3, 1, 0, 0), merwe_scaled_rule(6, 1, 0, 0))
    assert kp.predict_kernel_spec(other) is None
    spec = kp.predict_kernel_spec(FILTERS["ukf"])
    assert spec.mirror.tolist() == [-1, -1, -1, -1, 1, 2, 3]  # centre, +e_k, -e_k


def moderate_state(seed: int, B: int = 700):
    """Headings everywhere (some at +-pi), standard deviations up to 0.1, turns up to
    2 rad/s: every robot in the lanes' range."""
    rng = np.random.default_rng(seed)
    x = np.column_stack([rng.uniform(-50, 50, (B, 2)), rng.uniform(-np.pi, np.pi, B)])
    x[:4, 2] = [np.pi - 1e-12, -np.pi, np.pi - 0.01, -np.pi + 1e-9]
    sd = 10.0 ** rng.uniform(-4, -1, B)
    A = rng.normal(size=(B, 3, 3)) * sd[:, None, None] / 3.0
    P = A @ np.swapaxes(A, 1, 2) + 1e-10 * np.eye(3)
    P[::7] = np.diag([1e-4, 1e-4, 0.0])  # singular: the factor needs jitter in its lane
    u = np.column_stack([rng.uniform(-1, 1, B), rng.uniform(-2, 2, B)])
    return x, P, u


@needs_numba
@pytest.mark.parametrize("name", ["ckf", "ukf", "ukf-default", "ckf-arith"])
def test_predict_in_lanes_equals_numpy(name):
    """Sigma-point predictions of many robots run in lanes
    (:mod:`resloc.cl.kernels_predict_lanes`; asserted), equal to the numpy path."""
    x, P, u = moderate_state(6)
    params = CLParams(odometry_std=(0.02, 0.1), process_floor_std=(1e-3, 2e-3, 3e-3))
    before = kp.PREDICT_RUNS.copy()
    with kernels.use_backend("numba"):
        got = predict(FILTERS[name], x, P, u, 0.05, params)
    assert kp.PREDICT_RUNS - before == {"lanes": 1}
    assert_close(got, reference(FILTERS[name], x, P, u, 0.05, params))


@needs_numba
def test_predict_lanes_fall_back_to_robot_by_robot():
    """A heading spread the lanes' polynomials do not cover: the scalar kernel runs."""
    x, P, u = moderate_state(7)
    P[10] = np.diag([0.01, 0.01, 1.0])  # heading standard deviation 1 rad
    params = CLParams()
    before = kp.PREDICT_RUNS.copy()
    with kernels.use_backend("numba"):
        got = predict(FILTERS["ckf"], x, P, u, 0.05, params)
    assert kp.PREDICT_RUNS - before == {"lanes_fallback": 1, "robots": 1}
    assert_close(got, reference(FILTERS["ckf"], x, P, u, 0.05, params))
