"""Tests of :mod:`resloc.angles`: one wrap, one circular mean (STYLE habit 4)."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.angles import circular_mean, wrap_angle

PI = np.pi


class TestWrapAngle:
    def test_range_is_half_open_minus_pi_to_pi(self) -> None:
        assert wrap_angle(PI) == pytest.approx(-PI)
        assert wrap_angle(-PI) == pytest.approx(-PI)
        assert wrap_angle(0.0) == 0.0
        # Just inside the seam on either side stays where it is.
        assert wrap_angle(PI - 1e-9) == pytest.approx(PI - 1e-9, abs=1e-12)
        assert wrap_angle(-PI + 1e-9) == pytest.approx(-PI + 1e-9, abs=1e-12)

    @pytest.mark.parametrize(
        ("angle", "expected"),
        [
            (1e3 * PI + 0.1, 0.1),  # even multiple of pi
            (1001 * PI + 0.1, -PI + 0.1),  # odd multiple of pi
            (-1e3 * PI - 0.1, -0.1),
            (3 * PI / 2, -PI / 2),
            (-3 * PI / 2, PI / 2),
            (2 * PI, 0.0),
            (7.0, 7.0 - 2 * PI),
        ],
    )
    def test_large_multiples(self, angle: float, expected: float) -> None:
        # 1e3 pi carries ~1e-13 of rounding in the input itself.
        assert float(wrap_angle(angle)) == pytest.approx(expected, abs=1e-9)

    def test_arrays_keep_shape_and_agree_with_atan2(self, rng: np.random.Generator) -> None:
        a = rng.uniform(-1e4, 1e4, size=(7, 5, 3))
        w = wrap_angle(a)
        assert w.shape == a.shape
        assert np.all(w >= -PI)
        assert np.all(w < PI)
        # Same point on the circle: independent reference via atan2(sin, cos).
        ref = np.arctan2(np.sin(a), np.cos(a))
        diff = np.abs(w - ref)
        assert np.all((diff < 1e-9) | (np.abs(diff - 2 * PI) < 1e-9))
        # Integer number of turns removed.
        turns = (a - w) / (2 * PI)
        np.testing.assert_allclose(turns, np.round(turns), atol=1e-9)

    def test_idempotent(self, rng: np.random.Generator) -> None:
        a = rng.uniform(-50, 50, size=1000)
        np.testing.assert_array_equal(wrap_angle(wrap_angle(a)), wrap_angle(a))

    def test_scalar_input_gives_scalar(self) -> None:
        out = wrap_angle(4.0)
        assert np.ndim(out) == 0
        assert float(out) == pytest.approx(4.0 - 2 * PI)


class TestCircularMean:
    def test_across_the_seam(self) -> None:
        a = np.array([PI - 0.1, -PI + 0.1])
        m = circular_mean(a, np.array([0.5, 0.5]))
        # The arithmetic mean would be 0, the opposite direction.
        assert abs(wrap_angle(m - PI)) < 1e-12
        assert m.shape == ()

    def test_across_the_seam_weighted(self) -> None:
        a = np.array([PI - 0.1, -PI + 0.3])
        m = circular_mean(a, np.array([0.75, 0.25]))
        # Points 0.4 rad apart on the circle; weighted mean ~ 0.25 of the way from the first.
        expected = np.arctan2(
            0.75 * np.sin(a[0]) + 0.25 * np.sin(a[1]), 0.75 * np.cos(a[0]) + 0.25 * np.cos(a[1])
        )
        assert float(m) == pytest.approx(expected, abs=1e-14)
        # On the short arc between them, a quarter of the way from the first: about pi.
        assert abs(wrap_angle(m - PI)) < 2e-3

    def test_zero_weight_entries_are_ignored(self, rng: np.random.Generator) -> None:
        a = rng.uniform(-PI, PI, size=(4, 6))
        w = np.array([0.2, 0.0, 0.5, 0.0, 0.3, 0.0])
        m = circular_mean(a, w)
        # Replacing the zero-weight samples by anything does not change the mean.
        b = a.copy()
        b[:, [1, 3, 5]] = rng.uniform(-100, 100, size=(4, 3))
        np.testing.assert_allclose(circular_mean(b, w), m, atol=1e-14)
        # ...and equals the mean over the non-zero entries alone.
        np.testing.assert_allclose(
            circular_mean(a[:, [0, 2, 4]], np.array([0.2, 0.5, 0.3])), m, atol=1e-14
        )

    def test_weights_need_not_sum_to_one(self, rng: np.random.Generator) -> None:
        a = rng.uniform(-PI, PI, size=(3, 5))
        w = rng.uniform(0.1, 1.0, size=5)
        np.testing.assert_allclose(circular_mean(a, 7.0 * w), circular_mean(a, w), atol=1e-14)

    def test_small_spread_equals_arithmetic_mean(self, rng: np.random.Generator) -> None:
        centre = rng.uniform(-3.0, 3.0, size=(10, 1))
        a = centre + 1e-4 * rng.normal(size=(10, 7))
        w = rng.dirichlet(np.ones(7))
        np.testing.assert_allclose(circular_mean(a, w), a @ w, atol=1e-11)

    def test_axis_argument(self, rng: np.random.Generator) -> None:
        a = rng.uniform(-PI, PI, size=(4, 5, 6))
        w = rng.uniform(0.1, 1.0, size=5)
        out = circular_mean(a, w, axis=1)
        assert out.shape == (4, 6)
        np.testing.assert_allclose(out, circular_mean(np.swapaxes(a, 1, 2), w), atol=1e-14)

    def test_output_wrapped_and_shift_equivariant(self, rng: np.random.Generator) -> None:
        a = rng.normal(0.0, 0.3, size=(50, 5))
        w = rng.dirichlet(np.ones(5))
        shift = 1e3 * PI + 0.7
        m0 = circular_mean(a, w)
        m1 = circular_mean(a + shift, w)
        assert np.all((m1 >= -PI) & (m1 < PI))
        np.testing.assert_allclose(wrap_angle(m1 - m0 - shift), 0.0, atol=1e-9)
