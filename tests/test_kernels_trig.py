"""The kernels' arctangent (:func:`resloc.cl.kernels_trig.fast_atan2`) against libm's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from resloc.cl import kernels
from resloc.cl.kernels_trig import fast_atan2

needs_numba = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")


def _compiled_loop():
    import numba

    @numba.njit(cache=False)
    def loop(y, x, out):
        for k in range(y.shape[0]):
            out[k] = fast_atan2(y[k], x[k])

    return loop


@needs_numba
def test_fast_atan2_equals_libm_over_the_plane():
    rng = np.random.default_rng(0)
    n = 200_000
    y = rng.normal(size=n) * 10.0 ** rng.uniform(-8, 8, n)
    x = rng.normal(size=n) * 10.0 ** rng.uniform(-8, 8, n)
    # The reduction boundaries: |y| = |x| and |y| = tan(pi/8) |x|, in every quadrant.
    t = np.tan(np.pi / 8)
    edges = np.array([[1.0, 1.0], [t, 1.0], [1.0, t], [np.nextafter(t, 1), 1.0]])
    signs = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]])
    extra = (edges[:, None, :] * signs[None, :, :]).reshape(-1, 2)
    y = np.concatenate([y, extra[:, 0]])
    x = np.concatenate([x, extra[:, 1]])
    out = np.empty_like(y)
    _compiled_loop()(y, x, out)
    np.testing.assert_allclose(out, np.arctan2(y, x), rtol=0, atol=4.5e-16)
    assert np.all(np.abs(out) <= math.pi)


@needs_numba
@pytest.mark.parametrize(
    ("y", "x"),
    [
        (0.0, 1.0), (-0.0, 1.0), (0.0, -1.0), (-0.0, -1.0), (0.0, 0.0), (-0.0, -0.0),
        (1.0, 0.0), (-1.0, 0.0), (math.inf, 1.0), (1.0, -math.inf), (math.inf, math.inf),
        (math.nan, 1.0), (1.0, math.nan), (1e-310, 1.0), (1.0, 1e-310), (5e-324, -1.0),
    ],
)  # fmt: skip
def test_fast_atan2_special_values_are_libm_s(y, x):
    out = np.empty(1)
    _compiled_loop()(np.array([y]), np.array([x]), out)
    expected = math.atan2(y, x)
    if math.isnan(expected):
        assert math.isnan(out[0])
    else:
        assert out[0] == pytest.approx(expected, abs=4.5e-16)
        assert math.copysign(1.0, out[0]) == math.copysign(1.0, expected)


def test_fast_atan2_in_plain_python():
    """Without numba the same function runs as Python."""
    python = getattr(fast_atan2, "py_func", fast_atan2)
    for y, x in [(1.0, 1.0), (-2.0, -3.0), (0.3, -5.0), (-7.0, 0.1), (0.0, -2.0)]:
        assert python(y, x) == pytest.approx(math.atan2(y, x), abs=4.5e-16)


@needs_numba
def test_small_angle_sincos_equals_libm():
    import numba

    from resloc.cl.kernels_trig import SMALL_ANGLE, small_angle_sincos

    @numba.njit(cache=False)
    def loop(a, s, c):
        for k in range(a.shape[0]):
            s[k], c[k] = small_angle_sincos(a[k])

    rng = np.random.default_rng(1)
    a = np.concatenate(
        [rng.uniform(-1.5, 1.5, 100_000), [0.0, SMALL_ANGLE, -SMALL_ANGLE, 1e-300, 3.0, 1e5]]
    )
    a = np.concatenate([a, np.nextafter(a, np.inf)])
    s, c = np.empty_like(a), np.empty_like(a)
    loop(a, s, c)
    np.testing.assert_allclose(s, np.sin(a), rtol=0, atol=2.5e-16)
    np.testing.assert_allclose(c, np.cos(a), rtol=0, atol=2.5e-16)
