"""Compiled twin of split covariance intersection (``split_ci`` fusion).

Each covariance is kept as ``P = P_dep + P_ind``; only the dependent parts are inflated by
the CI weight (:func:`resloc.cl.fusion.fused_update` with ``split_ci``). The link loop
(:mod:`resloc.cl.kernels_links`) and the rounds inline :func:`split_ci_update` for a fused
link, which calls :func:`_split_ci_link`: the independent parts (robot i's, from
:class:`~resloc.cl.kernels_fusion.KernelFusion`'s working copy of ``memory.independent``,
and j's transmitted one, ``LinkBatch.P_nb_ind``) clipped to their covariances, the weight
and the inflated update shared with ``ci`` (:mod:`resloc.cl.kernels_ci_weight`,
:mod:`resloc.cl.kernels_ci_update`), then robot
i's new independent part. The once-per-step
parts: the prediction of the independent parts is compiled too
(:func:`resloc.cl.kernels_fusion_step.compiled_independent_predict`); a delivered
sender's part turned dependent stays the strategy's one numpy assignment.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`_clip_independent`      :func:`resloc.cl.fusion.clip_independent` (one matrix)
:func:`split_ci_update`        :func:`resloc.cl.fusion.fused_update` (``split_ci``)
:func:`_split_ci_link`         the same, from the fields of the fusion it reads
:func:`_zero_delivered`        ``SplitCIFusion.finish``'s ``independent[j[delivered]] = 0``
=============================  ==========================================================
"""

from __future__ import annotations

import numpy as np

from resloc.cl.backend import backend
from resloc.cl.kernels_ci_update import inflated_update
from resloc.cl.kernels_ci_weight import reduce_i, reduce_j, weight_of
from resloc.cl.kernels_joint_links import scaled_unit_minus_is_pd
from resloc.cl.kernels_math import chol3, jit, jit_inline, stamp_with_pieces

__all__ = ["compiled_independent_finish", "sandwich3", "split_ci_update"]


@jit_inline
def _clip_independent(P, P_ind, out, L, Linv, M, jitter):
    """``P_ind`` shrunk so that ``0 <= P_ind <= P``, into ``out`` (``L``, ``Linv``, ``M``:
    scratch). False when ``P`` has no Cholesky factor.
    Twin: :func:`resloc.cl.fusion.clip_independent` (one matrix).

    First the certificate ``0 < P_ind < P`` by Sylvester's criterion on ``sym(P_ind)`` and
    ``sym(P - P_ind)``: by congruence the same as ``0 < L^-1 P_ind L^-T < I``, so no
    eigenvalue to clip and ``P`` positive definite; ``sym(P_ind)`` is the reference's result
    up to its round-off (its ``1 / lambda_max`` within an ulp of 1), without the Cholesky
    factor, ``L^-1`` and the sandwich (98.7% of the clips of the paper's scenario)."""
    i00 = P_ind[0, 0]
    i11 = P_ind[1, 1]
    i22 = P_ind[2, 2]
    i01 = 0.5 * (P_ind[0, 1] + P_ind[1, 0])
    i02 = 0.5 * (P_ind[0, 2] + P_ind[2, 0])
    i12 = 0.5 * (P_ind[1, 2] + P_ind[2, 1])
    if _is_pd6(i00, i01, i02, i11, i12, i22) and _is_pd6(
        P[0, 0] - i00,
        0.5 * (P[0, 1] + P[1, 0]) - i01,
        0.5 * (P[0, 2] + P[2, 0]) - i02,
        P[1, 1] - i11,
        0.5 * (P[1, 2] + P[2, 1]) - i12,
        P[2, 2] - i22,
    ):
        out[0, 0] = i00
        out[1, 1] = i11
        out[2, 2] = i22
        out[0, 1] = out[1, 0] = i01
        out[0, 2] = out[2, 0] = i02
        out[1, 2] = out[2, 1] = i12
        return True
    if not chol3(P, L, jitter):
        return False
    for col in range(3):  # L^-1 by forward substitution of I (twin: forward_substitution)
        for r in range(3):
            acc = 1.0 if r == col else 0.0
            for c in range(r):
                acc -= L[r, c] * Linv[c, col]
            Linv[r, col] = acc / L[r, r]
    sandwich3(Linv, P_ind, out, M)  # out = Linv P_ind Linv^T, then M = sym(out)
    for a in range(3):
        for b in range(3):
            M[a, b] = 0.5 * (out[a, b] + out[b, a])
    if _is_pd_sym(M) and scaled_unit_minus_is_pd(M, 1.0):
        # 0 < M < I certified (Sylvester's criterion): no eigenvalue above 1, none below 0
        for a in range(3):
            for b in range(a, 3):
                v = 0.5 * (P_ind[a, b] + P_ind[b, a])
                out[a, b] = v
                out[b, a] = v
        return True
    lam = np.linalg.eigvalsh(M)
    low = lam[0]
    top = lam[2]
    scale = 1.0 / max(top, 1e-300) if top > 1.0 else 1.0
    for a in range(3):
        for b in range(3):
            out[a, b] = P_ind[a, b] * scale
    if low < 0.0:  # project the independent part itself onto the PSD cone
        for a in range(3):
            for b in range(3):
                M[a, b] = 0.5 * (out[a, b] + out[b, a])
        vals, V = np.linalg.eigh(M)
        for a in range(3):
            for b in range(3):
                s = 0.0
                for k in range(3):
                    s += V[a, k] * max(vals[k], 0.0) * V[b, k]
                out[a, b] = s
    for a in range(3):
        for b in range(a + 1, 3):
            m = 0.5 * (out[a, b] + out[b, a])
            out[a, b] = m
            out[b, a] = m
    return True


@jit_inline
def _is_pd6(m00, m01, m02, m11, m12, m22):
    """Sylvester's criterion on the symmetric 3 x 3 matrix of upper entries ``m``."""
    m2 = m00 * m11 - m01 * m01
    det = (
        m00 * (m11 * m22 - m12 * m12)
        - m01 * (m01 * m22 - m12 * m02)
        + m02 * (m01 * m12 - m11 * m02)
    )
    return m00 > 0.0 and m2 > 0.0 and det > 0.0


@jit_inline
def _is_pd_sym(M):
    """Sylvester's criterion on a symmetric 3 x 3 ``M``."""
    m2 = M[0, 0] * M[1, 1] - M[0, 1] * M[0, 1]
    det = (
        M[0, 0] * (M[1, 1] * M[2, 2] - M[1, 2] * M[1, 2])
        - M[0, 1] * (M[0, 1] * M[2, 2] - M[1, 2] * M[0, 2])
        + M[0, 2] * (M[0, 1] * M[1, 2] - M[1, 1] * M[0, 2])
    )
    return M[0, 0] > 0.0 and m2 > 0.0 and det > 0.0


@jit_inline
def sandwich3(A, B, out, T):
    """``out = A B A^T`` of 3 x 3 matrices as ``(A B) A^T`` (``T``: scratch)."""
    for a in range(3):
        for b in range(3):
            T[a, b] = A[a, 0] * B[0, b] + A[a, 1] * B[1, b] + A[a, 2] * B[2, b]
    for a in range(3):
        for b in range(3):
            out[a, b] = T[a, 0] * A[b, 0] + T[a, 1] * A[b, 1] + T[a, 2] * A[b, 2]


@jit_inline
def split_ci_update(
    x, e, i, xi0, xi1, xi2, Pi, Pj, nu0, nu1, S00, S01, S11, Pxz, linearized, Hi, Hj,
    re00, re01, re11, R, fusion, jitter, K, A3, T3, Pn,
):  # fmt: skip
    """Split covariance intersection of robot ``i`` from link ``e``: as :func:`ci_update`
    with only the dependent parts inflated, then robot i's independent part (in
    ``fusion.independent``) updated, ``(I - K H) I_i (I - K H)^T + K R K^T`` clipped to the
    posterior, with ``H`` the Jacobian (EKF) or the statistical linearization ``(A^-1
    P^xz)^T``. j's transmitted independent part is ``fusion.P_nb_ind[e]``. False when a
    covariance has no Cholesky factor. Inlined into the link loops: it hands
    :func:`_split_ci_link` only the fields of ``fusion`` it reads (the whole tuple carries
    the joints' 14 arrays, each a reference count and an argument of the call).
    Twin: :func:`resloc.cl.fusion.fused_update` (``split_ci``)."""
    return _split_ci_link(
        x, e, i, (xi0, xi1, xi2), Pi, Pj, (nu0, nu1), (S00, S01, S11), Pxz, linearized, Hi,
        Hj, (re00, re01, re11), R, fusion[4], fusion[5], fusion[6], fusion[1], fusion[2],
        fusion[7], jitter, K, A3, T3, Pn,
    )  # fmt: skip


@jit
def _split_ci_link(
    x, e, i, xi, Pi, Pj, nu, S, Pxz, linearized, Hi, Hj, re, R, independent, P_nb_ind, work,
    det, grid, cost, jitter, K, A3, T3, Pn,
):  # fmt: skip
    """:func:`split_ci_update` with the fields of the fusion it reads (``xi``, ``nu``,
    ``S``, ``re``: tuples of the scalars of :func:`ci_update`). A call of its own, not
    inlined: compiled once for the row-order loop and the SIMD rounds. The weight's 2 x 2
    reductions of the dependent parts are computed once and reused, times the inflation
    factors, for the update (as :func:`ci_update` does)."""
    Ii = work[0]
    Ij = work[1]
    Di = work[2]
    Dj = work[3]
    L = work[4]
    Linv = work[5]
    M = work[6]
    Q = work[7]
    if not _clip_independent(Pi, independent[i], Ii, L, Linv, M, jitter):
        return False
    if not _clip_independent(Pj, P_nb_ind[e], Ij, L, Linv, M, jitter):
        return False
    for a in range(3):
        for b in range(3):
            Di[a, b] = Pi[a, b] - Ii[a, b]
            Dj[a, b] = Pj[a, b] - Ij[a, b]
    hdh, dh = reduce_i(Di, Hi)
    hdj = reduce_j(Dj, Hj)
    w = weight_of(hdh, dh, hdj, Di, Ii, Ij, True, Hi, Hj, R, det, grid, cost)
    if w >= 1.0:  # j adds nothing: the prior (and its clipped independent part) is kept
        for a in range(3):
            for b in range(3):
                Pn[a, b] = Pi[a, b]
                M[a, b] = 0.5 * (Ii[a, b] + Ii[b, a])
        return _clip_independent(Pi, M, independent[i], L, Linv, Q, jitter)
    fi = 1.0 / w - 1.0
    fj = 1.0 / (1.0 - w) - 1.0
    d = (hdh[0] * fi, hdh[1] * fi, hdh[2] * fi, hdh[3] * fi)
    ej = (hdj[0] * fj, hdj[1] * fj, hdj[2] * fj, hdj[3] * fj)
    c = (dh[0] * fi, dh[1] * fi, dh[2] * fi, dh[3] * fi, dh[4] * fi, dh[5] * fi)
    if not inflated_update(
        x, i, xi[0], xi[1], xi[2], Pi, Di, fi, d, ej, c, nu[0], nu[1], S[0], S[1], S[2], Pxz,
        linearized, Hi, re[0], re[1], re[2], jitter, K, A3, T3, Pn,
    ):  # fmt: skip
        return False
    # H_eff: the Jacobian (EKF) or the statistical linearization (A^-1 P^xz)^T, 2 x 3 in Dj
    if linearized:
        for a in range(2):
            for b in range(3):
                Dj[a, b] = Hi[a, b]
    else:
        if not chol3(A3, L, jitter):
            return False
        for col in range(2):  # solve_spd(A, P^xz): forward, then backward substitution
            y0 = Pxz[0, col] / L[0, 0]
            y1 = (Pxz[1, col] - L[1, 0] * y0) / L[1, 1]
            y2 = (Pxz[2, col] - L[2, 0] * y0 - L[2, 1] * y1) / L[2, 2]
            h2 = y2 / L[2, 2]
            h1 = (y1 - L[2, 1] * h2) / L[1, 1]
            h0 = (y0 - L[1, 0] * h1 - L[2, 0] * h2) / L[0, 0]
            Dj[col, 0] = h0
            Dj[col, 1] = h1
            Dj[col, 2] = h2
    for a in range(3):  # Di = I - K H_eff
        for b in range(3):
            Di[a, b] = (1.0 if a == b else 0.0) - (K[a, 0] * Dj[0, b] + K[a, 1] * Dj[1, b])
    sandwich3(Di, Ii, Ij, L)
    for a in range(3):  # + K R K^T, symmetrized; the posterior symmetrized into Q
        t0 = K[a, 0] * R[0, 0] + K[a, 1] * R[1, 0]
        t1 = K[a, 0] * R[0, 1] + K[a, 1] * R[1, 1]
        for b in range(3):
            Ij[a, b] += t0 * K[b, 0] + t1 * K[b, 1]
    for a in range(3):
        for b in range(3):
            M[a, b] = 0.5 * (Ij[a, b] + Ij[b, a])
            Q[a, b] = 0.5 * (Pn[a, b] + Pn[b, a])
    return _clip_independent(Q, M, independent[i], L, Linv, Di, jitter)


def compiled_independent_finish(independent, j, delivered) -> bool:
    """``independent[j[delivered]] = 0.0`` compiled (split CI's end of step: a delivered
    sender's part turned dependent; numpy's boolean then fancy index cost ~3.5 us a step of
    the paper's scenario). False, nothing written, when the backend is numpy, an input is
    not of the documented form (``(B, 3, 3)`` float64 C-contiguous, ``(E,)`` int64 and
    bool) or an index is outside ``0 .. B - 1``: then the numpy assignment (which wraps a
    negative index and raises for one out of range)."""
    if (  # (exact types, dtypes against dtype objects: not against np.float64, ~0.1 us each)
        backend() != "numba"
        or type(independent) is not np.ndarray
        or type(j) is not np.ndarray
        or type(delivered) is not np.ndarray
        or independent.dtype != _FLOAT
        or j.dtype != _INT
        or delivered.dtype != _BOOL
        or independent.shape[1:] != (3, 3)  # (and ndim 3)
        or j.ndim != 1
        or delivered.shape != j.shape
    ):
        return False
    flags = independent.flags
    if not (flags.c_contiguous and flags.writeable):
        return False
    return _zero_delivered(independent, j, delivered)


_FLOAT, _INT, _BOOL = np.dtype(np.float64), np.dtype(np.int64), np.dtype(np.bool_)


@jit
def _zero_delivered(independent, j, delivered):
    """Rows ``j[e]`` of ``independent`` zero for every ``delivered[e]``; False (nothing
    written) when one of them is outside ``0 .. B - 1``."""
    B = independent.shape[0]
    for e in range(j.shape[0]):
        if delivered[e] and not 0 <= j[e] < B:
            return False
    for e in range(j.shape[0]):
        if delivered[e]:
            b = j[e]
            for a in range(3):
                for c in range(3):
                    independent[b, a, c] = 0.0
    return True


# _split_ci_link inlines kernels_ci_weight's weight, kernels_ci_update's update and
# kernels_joint_links' bound
# check, and links kernels_math's chol3: its cache (and its inliner's) must go stale with them.
stamp_with_pieces(split_ci_update)
stamp_with_pieces(_split_ci_link)
