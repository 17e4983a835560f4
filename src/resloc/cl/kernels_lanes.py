"""Branch-free scalar math for loops over lanes (robots) that the compiler vectorizes.

The link loop of :mod:`resloc.cl.kernels_rounds` evaluates the same expression for many
robots at once; LLVM turns such a loop into SIMD instructions only when its body has no
calls and no branches it cannot turn into selects. numba compiles ``math.atan2``,
``math.sin`` and ``math.cos`` to calls of the C library's scalar functions, so these
functions give the same values from polynomials and selects alone:

* :func:`atan2_lanes` is :func:`resloc.cl.kernels_trig.fast_atan2` (same polynomial) with
  its reductions written as selects and one division instead of two (within 2e-16 of
  ``math.atan2``), without its special-value branch: the caller guarantees finite input,
  not ``(0, 0)``;
* :func:`sincos_lanes` reduces ``a`` by multiples of ``pi/2`` (Cody-Waite, two parts) to
  ``|r| <= pi/4`` and evaluates the Taylor polynomials of
  :func:`~resloc.cl.kernels_trig.small_angle_sincos` (within 2e-16 of libm for
  ``|a| <= SINCOS_LANES_MAX``; the caller checks the range);
* :func:`wrap_lanes` is :func:`resloc.cl.kernels_math.wrap` for ``|a| < 3 pi`` (bit for
  bit: the floored modulo of ``a + pi`` is one subtraction or addition of ``2 pi`` there).

Twins (tested): :func:`math.atan2`, :func:`math.sin`, :func:`math.cos`,
:func:`resloc.angles.wrap_angle`.
"""

from __future__ import annotations

import math

from resloc.cl.backend import HAVE_NUMBA
from resloc.cl.kernels_trig import ATAN_COEFFICIENTS

if HAVE_NUMBA:  # the optional extra ``fast``
    import numba

    _jit_inline = numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
else:  # pragma: no cover - exercised only where numba is absent

    def _jit_inline(func):
        return func


__all__ = [
    "CHUNK",
    "FALLBACK",
    "SINCOS_LANES_MAX",
    "atan2_lanes",
    "sincos_lanes",
    "small_sincos_lanes",
    "wrap_lanes",
]

#: Robots per chunk of the lane kernels (lanes of a stage): a chunk's working arrays stay
#: in the L1/L2 cache (measured for the link rounds at 1,000,000 robots: 64 lanes 1.4x the
#: time of 256, 128 lanes 1.06x, 512 lanes 1.18x).
CHUNK = 256
#: Status of a lane kernel: a robot or link needs the scalar kernel's special cases; the
#: outputs are partial and must be discarded (the caller runs the scalar kernel).
FALLBACK = 2

_C0, _C1, _C2, _C3, _C4, _C5, _C6, _C7, _C8, _C9, _C10 = ATAN_COEFFICIENTS
_TAN_PI_8 = 0.41421356237309503
_PI = math.pi
_PI_2 = math.pi / 2.0
_PI_4 = math.pi / 4.0
_TWO_PI = 2.0 * math.pi
_TWO_OVER_PI = 2.0 / math.pi
# pi/2 in two parts (fdlibm's pio2_1, pio2_1t): n * _PIO2_HI is exact for |n| < 2^20
_PIO2_HI = 1.57079632673412561417e00
_PIO2_LO = 6.07710050650619224932e-11
#: :func:`sincos_lanes` is within 2e-16 of libm up to this ``|a|`` (the reduction's error
#: grows with the multiple of pi/2 taken off).
SINCOS_LANES_MAX = 64.0


@_jit_inline
def atan2_lanes(y, x):
    """``atan2(y, x)`` for finite ``(y, x) != (0, 0)``, without branches.
    Twin: :func:`math.atan2` (within 2e-16), :func:`resloc.cl.kernels_trig.fast_atan2`."""
    ax = abs(x)
    ay = abs(y)
    steep = ay > ax
    low = min(ax, ay)
    high = max(ax, ay)
    # one division: (low - high) / (low + high) is (t - 1) / (t + 1) for t = low / high
    reduced = low > _TAN_PI_8 * high
    t = (low - high if reduced else low) / (low + high if reduced else high)
    base = _PI_4 if reduced else 0.0
    s = t * t
    s2 = s * s
    s4 = s2 * s2
    p01 = _C0 + _C1 * s
    p23 = _C2 + _C3 * s
    p45 = _C4 + _C5 * s
    p67 = _C6 + _C7 * s
    p89 = _C8 + _C9 * s
    p = (p01 + p23 * s2) + (p45 + p67 * s2) * s4 + (p89 + _C10 * s2) * (s4 * s4)
    a = base + (t + t * s * p)
    a = _PI_2 - a if steep else a
    a = _PI - a if x < 0.0 else a
    return math.copysign(a, y)


@_jit_inline
def _sincos_reduced(r):
    """Taylor polynomials of sine and cosine for ``|r| <= pi/4`` (those of
    :func:`~resloc.cl.kernels_trig.small_angle_sincos`)."""
    q = r * r
    sin_r = r + r * q * (
        -1.0 / 6.0
        + q
        * (
            1.0 / 120.0
            + q
            * (
                -1.0 / 5040.0
                + q
                * (
                    1.0 / 362880.0
                    + q * (-1.0 / 39916800.0 + q * (1.0 / 6227020800.0 - q / 1307674368000.0))
                )
            )
        )
    )
    cos_r = 1.0 + q * (
        -0.5
        + q
        * (
            1.0 / 24.0
            + q
            * (
                -1.0 / 720.0
                + q
                * (
                    1.0 / 40320.0
                    + q
                    * (
                        -1.0 / 3628800.0
                        + q
                        * (1.0 / 479001600.0 + q * (-1.0 / 87178291200.0 + q / 20922789888000.0))
                    )
                )
            )
        )
    )
    return sin_r, cos_r


@_jit_inline
def sincos_lanes(a):
    """``(sin a, cos a)`` for ``|a| <= SINCOS_LANES_MAX``, without branches.
    Twin: :func:`math.sin`, :func:`math.cos`."""
    n = math.floor(a * _TWO_OVER_PI + 0.5)
    r = (a - n * _PIO2_HI) - n * _PIO2_LO
    sin_r, cos_r = _sincos_reduced(r)
    quadrant = n - 4.0 * math.floor(n * 0.25)  # n mod 4 in {0, 1, 2, 3}
    odd = (quadrant == 1.0) | (quadrant == 3.0)
    s = cos_r if odd else sin_r
    c = sin_r if odd else cos_r
    s = -s if quadrant >= 2.0 else s
    c = -c if (quadrant == 1.0) | (quadrant == 2.0) else c
    return s, c


@_jit_inline
def small_sincos_lanes(a):
    """``(sin a, cos a)`` for ``|a| <= pi/4`` (the caller checks), without branches.
    Twin: :func:`resloc.cl.kernels_trig.small_angle_sincos` (same value, bit for bit)."""
    return _sincos_reduced(a)


@_jit_inline
def wrap_lanes(a):
    """``wrap(a)`` for ``-3 pi <= a < 3 pi``, without branches.
    Twin: :func:`resloc.cl.kernels_math.wrap` (same value, bit for bit, in that range)."""
    t = a + _PI
    t = t - _TWO_PI if t >= _TWO_PI else t
    t = t + _TWO_PI if t < 0.0 else t
    return t - _PI
