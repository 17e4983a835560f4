"""A two-argument arctangent for the compiled kernels, about 4x cheaper than libm's.

numba compiles ``math.atan2`` to a call of the C library's scalar ``atan2`` (measured here
18-26 ns a call; numpy's vectorized ``arctan2`` costs 1.6 ns an element, but a link's
points depend on the robot's running estimate, so they cannot be evaluated for all links
before the sequential loop). :func:`fast_atan2` is a branch-light polynomial evaluation that
numba inlines into the loop:

* reduce to ``t = min(|x|, |y|) / max(|x|, |y|)`` in ``[0, 1]``, then to
  ``|t| <= tan(pi/8)`` by ``atan(t) = pi/4 + atan((t - 1) / (t + 1))``;
* ``atan(t) = t + t s p(s)``, ``s = t^2``, with ``p`` the degree-10 least-squares fit of
  ``(atan(t) - t) / (t s)`` on Chebyshev nodes of ``[0, tan(pi/8)^2]``
  (:data:`ATAN_COEFFICIENTS`, fitted to the exact series; within 1 ulp of ``atan`` there);
* undo the reductions (``pi/2 - a``, ``pi - a``, the sign of ``y``).

Within 2e-16 (absolute) of ``math.atan2`` over the plane (tested); non-finite input and
``(0, 0)`` go to ``math.atan2`` itself, so the special values are libm's.

:func:`small_angle_sincos` gives the sine and cosine of the small angles the kernels turn
by (a point's heading offset ``(L xi)_theta``, a step's ``omega dt``) from their Taylor
polynomials (degree 15 and 16, truncation error below 5e-17 for ``|a| <= pi/4``), one
polynomial pair instead of two libm calls; larger angles go to libm. A heading
``th = x_theta + a`` then has ``sin th = sin x_theta cos a + cos x_theta sin a`` (and
likewise ``cos th``) from the robot's one pair of libm calls.
"""

from __future__ import annotations

import math

from resloc.cl.backend import HAVE_NUMBA

if HAVE_NUMBA:  # the optional extra ``fast``
    import numba

    _jit_inline = numba.njit(cache=True, nogil=True, inline="always")
else:  # pragma: no cover - exercised only where numba is absent

    def _jit_inline(func):
        return func


__all__ = ["ATAN_COEFFICIENTS", "SMALL_ANGLE", "fast_atan2", "small_angle_sincos"]

#: ``p(s)`` of ``atan(t) = t + t s p(s)`` on ``s in [0, tan(pi/8)^2]``, lowest degree first.
ATAN_COEFFICIENTS = (
    -0.3333333333333336,
    0.1999999999999579,
    -0.14285714284703172,
    0.11111111017643607,
    -0.09090904660612112,
    0.07692184870449958,
    -0.06664532629893895,
    0.05858316272731624,
    -0.050862557599685006,
    0.03925328532687664,
    -0.01920165985495579,
)
_C0, _C1, _C2, _C3, _C4, _C5, _C6, _C7, _C8, _C9, _C10 = ATAN_COEFFICIENTS
_TAN_PI_8 = 0.41421356237309503
#: :func:`small_angle_sincos` evaluates its polynomials up to this ``|a|``.
SMALL_ANGLE = math.pi / 4
_PI = math.pi
_PI_2 = math.pi / 2.0
_PI_4 = math.pi / 4.0


@_jit_inline
def fast_atan2(y, x):
    """``atan2(y, x)`` in ``[-pi, pi]``. Twin: :func:`math.atan2` / :func:`numpy.arctan2`."""
    ax = abs(x)
    ay = abs(y)
    if not (ax < math.inf and ay < math.inf) or (ax == 0.0 and ay == 0.0):
        return math.atan2(y, x)  # NaN, inf, (0, 0): libm's special values
    steep = ay > ax
    t = ax / ay if steep else ay / ax
    base = 0.0
    if t > _TAN_PI_8:
        t = (t - 1.0) / (t + 1.0)
        base = _PI_4
    s = t * t
    s2 = s * s
    s4 = s2 * s2
    # Estrin's scheme: shorter dependency chains than Horner's for the same operations.
    p01 = _C0 + _C1 * s
    p23 = _C2 + _C3 * s
    p45 = _C4 + _C5 * s
    p67 = _C6 + _C7 * s
    p89 = _C8 + _C9 * s
    p = (p01 + p23 * s2) + (p45 + p67 * s2) * s4 + (p89 + _C10 * s2) * (s4 * s4)
    a = base + (t + t * s * p)
    if steep:
        a = _PI_2 - a
    if x < 0.0:
        a = _PI - a
    return -a if y < 0.0 or (y == 0.0 and math.copysign(1.0, y) < 0.0) else a


@_jit_inline
def small_angle_sincos(a):
    """``(sin a, cos a)``; polynomials for ``|a| <= SMALL_ANGLE``, libm beyond.
    Twin: :func:`math.sin`, :func:`math.cos`."""
    if not abs(a) <= SMALL_ANGLE:
        return math.sin(a), math.cos(a)
    q = a * a
    sin_a = a + a * q * (
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
    cos_a = 1.0 + q * (
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
    return sin_a, cos_a
