"""Tests of :mod:`resloc.models`: unicycle (eq. 2), range/bearing (eq. 3), Jacobians, noise."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.angles import wrap_angle
from resloc.linalg import is_positive_definite
from resloc.models import (
    measurement_noise,
    process_noise,
    range_bearing,
    range_bearing_jacobians,
    unicycle_input_jacobian,
    unicycle_state_jacobian,
    unicycle_step,
)
from resloc.models.measurement import MIN_RANGE

PI = np.pi
EPS = 1e-6  # central-difference step; truncation error O(EPS^2), round-off O(1e-16 / EPS)


def central_difference(f, x: np.ndarray, eps: float = EPS, angle_rows=()) -> np.ndarray:
    """Numerical Jacobian of a batched ``f: (B, n) -> (B, k)``, shape ``(B, k, n)``.

    Output components listed in ``angle_rows`` are differenced on the circle.
    """
    n = x.shape[1]
    cols = []
    for c in range(n):
        step = np.zeros(n)
        step[c] = eps
        d = f(x + step) - f(x - step)
        for r in angle_rows:
            d[:, r] = wrap_angle(d[:, r])
        cols.append(d / (2 * eps))
    return np.stack(cols, axis=-1)


def random_poses(rng: np.random.Generator, B: int, spread: float = 5.0) -> np.ndarray:
    x = rng.uniform(-spread, spread, size=(B, 3))
    x[:, 2] = rng.uniform(-PI, PI, size=B)
    return x


class TestUnicycleStep:
    def test_hand_computed(self) -> None:
        x = np.array([[1.0, 2.0, PI / 2], [0.0, 0.0, 0.0], [-1.0, 3.0, PI / 6]])
        u = np.array([[2.0, 0.5], [1.5, -1.0], [-0.4, 0.0]])
        out = unicycle_step(x, u, 0.1)
        expected = np.array(
            [
                [1.0, 2.2, PI / 2 + 0.05],
                [0.15, 0.0, -0.1],
                [-1.0 - 0.04 * np.sqrt(3) / 2, 3.0 - 0.02, PI / 6],
            ]
        )
        np.testing.assert_allclose(out, expected, atol=1e-15)

    def test_heading_wraps_across_seam(self) -> None:
        x = np.array([[0.0, 0.0, PI - 0.01]])
        u = np.array([[1.0, 0.5]])
        out = unicycle_step(x, u, 0.1)
        np.testing.assert_allclose(
            out[0], [0.1 * np.cos(PI - 0.01), 0.1 * np.sin(PI - 0.01), -PI + 0.04], atol=1e-14
        )

    def test_sigma_point_broadcasting(self, rng: np.random.Generator) -> None:
        X = random_poses(rng, 4 * 7).reshape(4, 7, 3)
        u = rng.normal(size=(4, 2))
        out = unicycle_step(X, u[:, None, :], 0.2)
        assert out.shape == (4, 7, 3)
        ref = unicycle_step(X.reshape(-1, 3), np.repeat(u, 7, axis=0), 0.2).reshape(4, 7, 3)
        np.testing.assert_array_equal(out, ref)

    def test_does_not_modify_input(self, rng: np.random.Generator) -> None:
        x = random_poses(rng, 5)
        x0 = x.copy()
        unicycle_step(x, rng.normal(size=(5, 2)), 0.1)
        np.testing.assert_array_equal(x, x0)


class TestMotionJacobians:
    @pytest.mark.parametrize("dt", [0.01, 0.1, 1.0])
    def test_state_jacobian_vs_finite_difference(self, dt: float, rng: np.random.Generator) -> None:
        x = random_poses(rng, 64)
        u = np.column_stack([rng.uniform(-2, 2, 64), rng.uniform(-3, 3, 64)])
        F = unicycle_state_jacobian(x, u, dt)
        F_num = central_difference(lambda xx: unicycle_step(xx, u, dt), x, angle_rows=(2,))
        assert F.shape == (64, 3, 3)
        np.testing.assert_allclose(F, F_num, atol=1e-8)

    @pytest.mark.parametrize("dt", [0.01, 0.1, 1.0])
    def test_input_jacobian_vs_finite_difference(self, dt: float, rng: np.random.Generator) -> None:
        x = random_poses(rng, 64)
        u = np.column_stack([rng.uniform(-2, 2, 64), rng.uniform(-3, 3, 64)])
        G = unicycle_input_jacobian(x, dt)
        G_num = central_difference(lambda uu: unicycle_step(x, uu, dt), u, angle_rows=(2,))
        assert G.shape == (64, 3, 2)
        np.testing.assert_allclose(G, G_num, atol=1e-8)


class TestRangeBearing:
    def test_hand_computed(self) -> None:
        x_i = np.array([[1.0, 1.0, PI / 4], [0.0, 0.0, 0.0]])
        x_j = np.array([[4.0, 5.0, 0.3], [0.0, -2.0, 1.0]])
        z = range_bearing(x_i, x_j)
        np.testing.assert_allclose(
            z, [[5.0, np.arctan2(4.0, 3.0) - PI / 4], [2.0, -PI / 2]], atol=1e-15
        )

    def test_bearing_at_the_seam(self) -> None:
        x_i = np.zeros((5, 3))
        x_i[3:, 2] = [3.0, -3.0]
        x_j = np.array(
            [
                [-1.0, 1e-9, 0.0],  # just above the negative x axis
                [-1.0, -1e-9, 0.0],  # just below
                [-1.0, 0.0, 0.0],  # exactly behind: +pi maps to -pi
                [np.cos(-3.0), np.sin(-3.0), 0.0],  # heading 3, target at -3: -6 -> 2pi-6
                [np.cos(3.0), np.sin(3.0), 0.0],  # heading -3, target at 3: 6 -> 6-2pi
            ]
        )
        z = range_bearing(x_i, x_j)
        np.testing.assert_allclose(z[:, 0], 1.0, atol=1e-12)
        np.testing.assert_allclose(
            z[:, 1], [PI - 1e-9, -PI + 1e-9, -PI, 2 * PI - 6.0, 6.0 - 2 * PI], atol=1e-12
        )
        assert np.all((z[:, 1] >= -PI) & (z[:, 1] < PI))

    def test_broadcasting(self, rng: np.random.Generator) -> None:
        x_i = random_poses(rng, 3)
        x_j = random_poses(rng, 3 * 4).reshape(3, 4, 3)
        z = range_bearing(x_i[:, None, :], x_j)
        assert z.shape == (3, 4, 2)
        np.testing.assert_array_equal(z[1], range_bearing(np.repeat(x_i[1:2], 4, 0), x_j[1]))

    def test_jacobians_vs_finite_difference(self, rng: np.random.Generator) -> None:
        E = 128
        x_i = random_poses(rng, E)
        # Keep ranges away from zero (the Jacobian is singular there).
        offset = rng.uniform(0.3, 6.0, E)[:, None] * np.column_stack(
            [np.cos(a := rng.uniform(-PI, PI, E)), np.sin(a)]
        )
        x_j = np.column_stack([x_i[:, :2] + offset, rng.uniform(-PI, PI, E)])
        H_i, H_j = range_bearing_jacobians(x_i, x_j)
        Hi_num = central_difference(lambda xx: range_bearing(xx, x_j), x_i, angle_rows=(1,))
        Hj_num = central_difference(lambda xx: range_bearing(x_i, xx), x_j, angle_rows=(1,))
        assert H_i.shape == H_j.shape == (E, 2, 3)
        np.testing.assert_allclose(H_i, Hi_num, atol=1e-7)
        np.testing.assert_allclose(H_j, Hj_num, atol=1e-7)

    def test_jacobians_at_the_bearing_seam(self) -> None:
        # Target straight behind the observer: the bearing jumps from pi to -pi there, the
        # derivative does not.
        x_i = np.array([[0.0, 0.0, 0.0]])
        x_j = np.array([[-2.0, 1e-12, 0.0]])
        H_i, H_j = range_bearing_jacobians(x_i, x_j)
        Hi_num = central_difference(lambda xx: range_bearing(xx, x_j), x_i, angle_rows=(1,))
        Hj_num = central_difference(lambda xx: range_bearing(x_i, xx), x_j, angle_rows=(1,))
        np.testing.assert_allclose(H_i, Hi_num, atol=1e-7)
        np.testing.assert_allclose(H_j, Hj_num, atol=1e-7)

    def test_jacobians_finite_at_zero_range(self) -> None:
        x = np.array([[1.0, 2.0, 0.3]])
        H_i, H_j = range_bearing_jacobians(x, x.copy())
        assert np.all(np.isfinite(H_i))
        assert np.all(np.isfinite(H_j))
        assert H_i[0, 1, 2] == -1.0
        # Tiny but non-zero range: entries bounded by 1 / MIN_RANGE.
        x_j = x + np.array([[1e-9, 0.0, 0.0]])
        H_i, H_j = range_bearing_jacobians(x, x_j)
        assert np.abs(H_j).max() <= 1.0 / MIN_RANGE


def test_process_noise_formula_symmetric_pd(rng: np.random.Generator) -> None:
    B, dt = 40, 0.1
    x = random_poses(rng, B)
    odo = np.array([0.02, 0.1])
    floor = np.array([1e-3, 2e-3, 3e-3])
    Q = process_noise(x, dt, odo, floor)
    assert Q.shape == (B, 3, 3)
    # Symmetric up to round-off in the einsum's summation order.
    np.testing.assert_allclose(Q, np.swapaxes(Q, -1, -2), rtol=1e-14, atol=1e-22)
    assert np.all(is_positive_definite(Q))
    # Hand formula for one robot: G diag(odo^2) G^T + diag(floor^2 dt).
    c, s = np.cos(x[7, 2]), np.sin(x[7, 2])
    G = np.array([[c * dt, 0.0], [s * dt, 0.0], [0.0, dt]])
    expected = G @ np.diag(odo**2) @ G.T + np.diag(floor**2 * dt)
    np.testing.assert_allclose(Q[7], expected, rtol=1e-13, atol=1e-20)
    # The floor alone keeps Q PD when the odometry noise vanishes (rank-deficient G M G^T).
    Q0 = process_noise(x, dt, np.zeros(2), floor)
    assert np.all(is_positive_definite(Q0))
    np.testing.assert_allclose(Q0, np.broadcast_to(np.diag(floor**2 * dt), (B, 3, 3)))


def test_process_noise_per_robot_odometry_std(rng: np.random.Generator) -> None:
    x = random_poses(rng, 3)
    odo = np.array([[0.01, 0.05], [0.1, 0.0], [0.0, 0.3]])
    Q = process_noise(x, 0.5, odo, np.full(3, 1e-4))
    for b in range(3):
        single = process_noise(x[b : b + 1], 0.5, odo[b], np.full(3, 1e-4))
        np.testing.assert_allclose(Q[b], single[0])
    assert np.all(is_positive_definite(Q))


def test_measurement_noise() -> None:
    R = measurement_noise(0.1, 0.02)
    np.testing.assert_allclose(R, np.diag([0.01, 0.0004]), rtol=1e-14, atol=0)
