"""The per-link pieces of ``tracked`` and ``factorized`` fusion in the CL link loop
(:func:`resloc.cl.kernels_links.correct_links`): the blocks of the correlated joint and the
moments under it (the record of an update: :mod:`resloc.cl.kernels_joint_records`). The
state they work on and its hand-over to the numpy bookkeeping are in
:mod:`resloc.cl.kernels_joint` (table of twins there).
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl.backend import HAVE_NUMBA
from resloc.cl.kernels_gauge import range_bearing_jacobians_into
from resloc.cl.kernels_math import chol3, jit_inline, wrap

__all__ = [
    "CROSS_CAP",
    "FACTORIZED",
    "JOINT_FORM",
    "NO_JOINT",
    "TRACKED",
    "chol6",
    "correlated_linearized_moments",
    "correlated_offsets",
    "factorized_cross",
    "joint6",
    "joint_cross",
    "joint_form",
    "scaled_unit_minus_is_pd",
    "tracked_cross",
]

#: Codes of the cross-covariance bookkeeping.
NO_JOINT = 0
TRACKED = 1
FACTORIZED = 2

#: The link loops' ``beyond`` switch (:func:`resloc.cl.kernels_rounds.beyond_paper`) for
#: ``tracked`` and ``factorized``: the int 1, equal to the other options' ``True`` but typed
#: ``int64`` by numba, so that the loops compile a form of their own for the correlated
#: joint. Its per-link pieces (this module) are inlined into that form only: called, each
#: piece cost a reference count per array it was passed, about 0.2 us a link; inlined into
#: the form every option shares, their code slowed the other options' loop (measured:
#: ``cached`` 1.17x, the options' form of the paper's method 1.3x).
JOINT_FORM = 1


def joint_form(beyond) -> bool:
    """Whether the loops' switch ``beyond`` is :data:`JOINT_FORM` (an int, not a bool):
    the form that runs the correlated joint. Compiled, a constant of the switch's type."""
    return type(beyond) is int


if HAVE_NUMBA:  # the optional extra ``fast``
    from numba.core import types as _types
    from numba.extending import overload as _overload

    @_overload(joint_form)
    def _joint_form_of_type(beyond):
        on = isinstance(beyond, _types.Integer)  # a bool is types.Boolean, not an Integer

        def constant(beyond):
            return on

        return constant


#: ``valid_cross``'s default cap on the correlation's singular values.
CROSS_CAP = 1.0 - 1e-6
_CAP = CROSS_CAP


@jit_inline
def _add_mul(X, Y, out):
    """``out += X Y`` of 3 x 3 matrices."""
    for a in range(3):
        for b in range(3):
            out[a, b] += X[a, 0] * Y[0, b] + X[a, 1] * Y[1, b] + X[a, 2] * Y[2, b]


@jit_inline
def _add_mul_t(X, Y, out):
    """``out += X Y^T`` of 3 x 3 matrices."""
    for a in range(3):
        for b in range(3):
            out[a, b] += X[a, 0] * Y[b, 0] + X[a, 1] * Y[b, 1] + X[a, 2] * Y[b, 2]


@jit_inline
def _solve_lower_into(L, X, out):
    """``out = L^-1 X`` for lower-triangular 3 x 3 ``L`` (forward substitution)."""
    for b in range(3):
        y0 = X[0, b] / L[0, 0]
        y1 = (X[1, b] - L[1, 0] * y0) / L[1, 1]
        y2 = (X[2, b] - L[2, 0] * y0 - L[2, 1] * y1) / L[2, 2]
        out[0, b] = y0
        out[1, b] = y1
        out[2, b] = y2


@jit_inline
def _valid_cross(Pi, Pj, C, Li, Lj, X, T3, jitter):
    """Shrink ``C`` in place so that ``[[P_i, C], [C^T, P_j]]`` stays valid (``Li``, ``Lj``,
    ``X``, ``T3``: scratch). False when a covariance has no Cholesky factor.
    Twin: :func:`resloc.cl.factorized.valid_cross`."""
    if not chol3(Pi, Li, jitter) or not chol3(Pj, Lj, jitter):
        return False
    for a in range(3):  # T3 = C^T, X = Lj^-1 C^T
        for b in range(3):
            T3[a, b] = C[b, a]
    _solve_lower_into(Lj, T3, X)
    for a in range(3):
        for b in range(3):
            T3[a, b] = X[b, a]
    _solve_lower_into(Li, T3, X)  # the correlation L_i^-1 C L_j^-T
    frob = 0.0
    for a in range(3):
        for b in range(3):
            frob += X[a, b] * X[a, b]
    if math.sqrt(frob) <= _CAP:  # sigma_max <= Frobenius norm: nothing to shrink
        return True
    for a in range(3):  # X^T X: its largest eigenvalue is sigma_max^2
        for b in range(3):
            T3[a, b] = X[0, a] * X[0, b] + X[1, a] * X[1, b] + X[2, a] * X[2, b]
    if scaled_unit_minus_is_pd(T3, _CAP * _CAP):  # sigma_max < cap certified
        return True
    smax = math.sqrt(max(np.linalg.eigvalsh(T3)[2], 0.0))
    if smax > _CAP:
        scale = _CAP / max(smax, 1e-300)
        for a in range(3):
            for b in range(3):
                C[a, b] = C[a, b] * scale
    return True


@jit_inline
def scaled_unit_minus_is_pd(M, c):
    """Sylvester's criterion on ``c I - M`` (symmetric 3 x 3 ``M``): every eigenvalue of
    ``M`` below ``c``."""
    n00 = c - M[0, 0]  # N = c I - M
    n11 = c - M[1, 1]
    n22 = c - M[2, 2]
    n01 = -M[0, 1]
    n02 = -M[0, 2]
    n12 = -M[1, 2]
    m2 = n00 * n11 - n01 * n01
    det = (
        n00 * (n11 * n22 - n12 * n12)
        - n01 * (n01 * n22 - n12 * n02)
        + n02 * (n01 * n12 - n11 * n02)
    )
    return n00 > 0.0 and m2 > 0.0 and det > 0.0


@jit_inline
def joint_cross(joint, e, first, fused, i, Pi, Pj, jitter):
    """The blocks of the correlated joint for link ``e`` of robot ``i``: the observer's
    covariance into ``work[0]``, ``C_ij`` into ``work[1]`` and j's covariance into
    ``work[2]`` (:func:`tracked_cross`, :func:`factorized_cross`). False when a covariance
    has no Cholesky factor."""
    if joint[0] == TRACKED:
        return tracked_cross(joint, e, first, fused, i)
    return factorized_cross(joint, e, i, Pi, Pj, jitter)


@jit_inline
def tracked_cross(joint, e, first, fused, i):
    """:func:`joint_cross` of ``tracked``: the blocks from the joint (robot i's covariance
    now in ``work[4]``: ``Sigma_ii`` at its first link; ``C_ij = M_i Sigma[:, j]``, the
    block of i's rows of ``M Sigma`` that the records keep, ``joint[14]``). Indexes the
    arrays and takes no view of them (a view costs a reference count, and this runs per
    link); a loop over lanes calls it, not :func:`joint_cross`, whose ``factorized``
    branch's views made the loop 7x slower (measured: 230 ns a lane, 30 ns alone).
    ``fused`` is not read (the rows hold the earlier fused links already)."""
    N = joint[1]
    nbr = joint[2]
    j = nbr[e]
    work = joint[11]
    sigma = joint[3]
    rows = joint[14]
    t = i // N
    if e == first:  # robot i's covariance now (work[4]): Sigma_ii at its first link
        c0 = 3 * (i % N)
        for a in range(3):
            for b in range(3):
                work[4, a, b] = 0.5 * (sigma[t, c0 + a, c0 + b] + sigma[t, c0 + b, c0 + a])
    c0 = 3 * (j % N)
    for a in range(3):
        for b in range(3):
            work[0, a, b] = work[4, a, b]
            work[1, a, b] = rows[i, a, c0 + b]
    t = j // N
    for a in range(3):
        for b in range(3):
            work[2, a, b] = sigma[t, c0 + a, c0 + b]
    return True


@jit_inline
def factorized_cross(joint, e, i, Pi, Pj, jitter):
    """:func:`joint_cross` of ``factorized``: ``Pi``, the factors' product shrunk to a
    valid joint (:func:`_valid_cross`), ``Pj``."""
    N = joint[1]
    j = joint[2][e]
    work = joint[11]
    Pm = work[0]
    C = work[1]
    Pr = work[2]
    T3 = work[3]
    L6 = joint[12][1]
    sig = joint[7]
    sig_pred = joint[8]
    A = joint[5]
    li = i % N
    lj = j % N
    for a in range(3):  # robot i's factor now: A_i sigma_ij (the deferred products)
        for b in range(3):
            T3[a, b] = (
                A[i, a, 0] * sig[i, lj, 0, b]
                + A[i, a, 1] * sig[i, lj, 1, b]
                + (A[i, a, 2] * sig[i, lj, 2, b])
            )
    for a in range(3):
        for b in range(3):
            Pm[a, b] = Pi[a, b]
            Pr[a, b] = Pj[a, b]
            C[a, b] = (
                T3[a, 0] * sig_pred[j, li, b, 0]
                + T3[a, 1] * sig_pred[j, li, b, 1]
                + T3[a, 2] * sig_pred[j, li, b, 2]
            )
    return _valid_cross(Pm, Pr, C, L6[:3, :3], L6[3:, 3:], L6[:3, 3:], T3, jitter)


@jit_inline
def joint6(work, J6):
    """``J = sym([[P_i, C], [C^T, P_j]])`` from ``work`` into ``J6[0]``."""
    for a in range(3):
        for b in range(3):
            J6[0, a, b] = 0.5 * (work[0, a, b] + work[0, b, a])
            J6[0, 3 + a, 3 + b] = 0.5 * (work[2, a, b] + work[2, b, a])
            J6[0, a, 3 + b] = work[1, a, b]
            J6[0, 3 + b, a] = work[1, a, b]


@jit_inline
def chol6(J6, jitter):
    """Lower Cholesky factor of the 6 x 6 ``J6[0]`` into ``J6[1]`` with the escalating
    jitter of :func:`resloc.linalg.cholesky_jitter`. False if none succeeds."""
    n = 6
    scale = 0.0
    for c in range(n):
        for r in range(n):
            if not math.isfinite(J6[0, r, c]):
                return False
        scale += abs(J6[0, c, c])
    scale = max(scale / n, 1e-300)
    for level in jitter:
        eps = level * scale
        ok = True
        for c in range(n):
            s = J6[0, c, c] + eps
            for k in range(c):
                s -= J6[1, c, k] * J6[1, c, k]
            if not s > 0.0:
                ok = False
                break
            d = math.sqrt(s)
            J6[1, c, c] = d
            for r in range(c + 1, n):
                t = J6[0, r, c]
                for k in range(c):
                    t -= J6[1, r, k] * J6[1, c, k]
                J6[1, r, c] = t / d
            for r in range(c):
                J6[1, r, c] = 0.0
        if ok:
            return True
    return False


@jit_inline
def correlated_offsets(joint, nz_idx, nz_val, nz_cnt, off, jitter):
    """The filter's unit points times the Cholesky factor of the correlated joint
    (:func:`joint_cross`'s blocks) into ``off: (6, m)``. False when the joint has no
    Cholesky factor. Twin: :func:`resloc.cl.tracking.joint_moments` (its offsets)."""
    J6 = joint[12]
    joint6(joint[11], J6)
    if not chol6(J6, jitter):
        return False
    for k in range(off.shape[1]):
        for a in range(6):
            off[a, k] = 0.0
        for t in range(nz_cnt[k]):
            b = nz_idx[k, t]
            u = nz_val[k, t]
            for a in range(b, 6):  # L is lower triangular
                off[a, k] += J6[1, a, b] * u
    return True


@jit_inline
def correlated_linearized_moments(joint, xi0, xi1, xi2, xj0, xj1, R, Hi, Hj, Pxz):
    """First-order moments of eq. (3) under the correlated joint (:func:`joint_cross`'s
    blocks): ``S = H J H^T + R``, ``P^xz = J[:3] H^T`` with ``H = [H_i, H_j]`` at the means;
    fills ``Hi``, ``Hj``, ``Pxz``. Returns ``(zh0, zh1, S00, S01, S11)``.
    Twin: :func:`resloc.cl.tracking.joint_moments` (EKF)."""
    J6 = joint[12]  # the joint in J6[0], H J in the first rows of J6[1]
    joint6(joint[11], J6)
    dx = xj0 - xi0
    dy = xj1 - xi1
    range_bearing_jacobians_into(xi0, xi1, xj0, xj1, Hi, Hj)
    for a in range(2):
        for b in range(6):
            s = 0.0
            for c in range(3):
                s += Hi[a, c] * J6[0, c, b]
            for c in range(3):
                s += Hj[a, c] * J6[0, 3 + c, b]
            J6[1, a, b] = s
    q00 = 0.0
    q01 = 0.0
    q10 = 0.0
    q11 = 0.0
    for c in range(3):
        q00 += J6[1, 0, c] * Hi[0, c]
        q01 += J6[1, 0, c] * Hi[1, c]
        q10 += J6[1, 1, c] * Hi[0, c]
        q11 += J6[1, 1, c] * Hi[1, c]
    for c in range(3):
        q00 += J6[1, 0, 3 + c] * Hj[0, c]
        q01 += J6[1, 0, 3 + c] * Hj[1, c]
        q10 += J6[1, 1, 3 + c] * Hj[0, c]
        q11 += J6[1, 1, 3 + c] * Hj[1, c]
    for a in range(3):
        for b in range(2):
            s = 0.0
            for c in range(3):
                s += J6[0, a, c] * Hi[b, c]
            for c in range(3):
                s += J6[0, a, 3 + c] * Hj[b, c]
            Pxz[a, b] = s
    S00 = q00 + R[0, 0]
    S01 = 0.5 * ((q01 + R[0, 1]) + (q10 + R[1, 0]))
    S11 = q11 + R[1, 1]
    return math.hypot(dx, dy), wrap(math.atan2(dy, dx) - xi2), S00, S01, S11
