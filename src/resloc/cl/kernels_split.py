"""Compiled twin of split covariance intersection (``split_ci`` fusion).

Each covariance is kept as ``P = P_dep + P_ind``; only the dependent parts are inflated by
the CI weight (:func:`resloc.cl.fusion.fused_update` with ``split_ci``). The link loop
(:mod:`resloc.cl.kernels_links`) calls :func:`split_ci_update` for a fused link: the
independent parts (robot i's, from :class:`~resloc.cl.kernels_fusion.KernelFusion`'s
working copy of ``memory.independent``, and j's transmitted one, ``LinkBatch.P_nb_ind``)
clipped to their covariances, the weight and the inflated update shared with ``ci``
(:mod:`resloc.cl.kernels_fusion`), then robot i's new independent part. The once-per-step
parts: the prediction of the independent parts is compiled too
(:func:`resloc.cl.kernels_fusion_step.compiled_propagate_independent`); a delivered
sender's part turned dependent stays the strategy's one numpy assignment.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`_clip_independent`      :func:`resloc.cl.fusion.clip_independent` (one matrix)
:func:`split_ci_update`        :func:`resloc.cl.fusion.fused_update` (``split_ci``)
=============================  ==========================================================
"""

from __future__ import annotations

import numpy as np

from resloc.cl.kernels_fusion import ci_posterior, ci_weight
from resloc.cl.kernels_joint_links import scaled_unit_minus_is_pd
from resloc.cl.kernels_math import chol3, jit, jit_inline, stamp_with_pieces

__all__ = ["sandwich3", "split_ci_update"]


@jit_inline
def _clip_independent(P, P_ind, out, L, Linv, M, jitter):
    """``P_ind`` shrunk so that ``0 <= P_ind <= P``, into ``out`` (``L``, ``Linv``, ``M``:
    scratch). False when ``P`` has no Cholesky factor.
    Twin: :func:`resloc.cl.fusion.clip_independent` (one matrix)."""
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


@jit
def split_ci_update(
    x, e, i, xi0, xi1, xi2, Pi, Pj, nu0, nu1, S00, S01, S11, Pxz, linearized, Hi, Hj,
    re00, re01, re11, R, fusion, jitter, K, A3, T3, Pn,
):  # fmt: skip
    """Split covariance intersection of robot ``i`` from link ``e``: as :func:`ci_update`
    with only the dependent parts inflated, then robot i's independent part (in
    ``fusion.independent``) updated, ``(I - K H) I_i (I - K H)^T + K R K^T`` clipped to the
    posterior, with ``H`` the Jacobian (EKF) or the statistical linearization ``(A^-1
    P^xz)^T``. j's transmitted independent part is ``fusion.P_nb_ind[e]``. False when a
    covariance has no Cholesky factor. Twin: :func:`resloc.cl.fusion.fused_update`
    (``split_ci``)."""
    independent = fusion[4]
    work = fusion[6]
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
    if not _clip_independent(Pj, fusion[5][e], Ij, L, Linv, M, jitter):
        return False
    for a in range(3):
        for b in range(3):
            Di[a, b] = Pi[a, b] - Ii[a, b]
            Dj[a, b] = Pj[a, b] - Ij[a, b]
    w = ci_weight(Di, Dj, Ii, Ij, True, Hi, Hj, R, fusion[1], fusion[2], fusion[7])
    if w >= 1.0:  # j adds nothing: the prior (and its clipped independent part) is kept
        for a in range(3):
            for b in range(3):
                Pn[a, b] = Pi[a, b]
                M[a, b] = 0.5 * (Ii[a, b] + Ii[b, a])
        return _clip_independent(Pi, M, independent[i], L, Linv, Q, jitter)
    if not ci_posterior(
        x, i, xi0, xi1, xi2, Pi, Di, Dj, w, nu0, nu1, S00, S01, S11, Pxz, linearized, Hi, Hj,
        re00, re01, re11, R, jitter, K, A3, T3, Pn,
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


# split_ci_update inlines kernels_fusion's weight and posterior and kernels_joint_links'
# bound check, and links kernels_math's chol3: its cache must go stale with them.
stamp_with_pieces(split_ci_update)
