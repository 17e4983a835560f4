"""The record of an update of ``tracked`` and ``factorized`` fusion in the CL link loops
(:func:`resloc.cl.kernels_links.correct_links`, the joints' rounds of
:mod:`resloc.cl.kernels_joint_rounds`): what an update does to the joint's working copies
(:class:`~resloc.cl.kernels_joint.KernelJoint`), and ``tracked``'s covariance after it.
The blocks and moments the update used are :mod:`resloc.cl.kernels_joint_links`'.
"""

from __future__ import annotations

from resloc.cl.kernels_gauge import range_bearing_jacobians_into
from resloc.cl.kernels_joint_links import TRACKED
from resloc.cl.kernels_math import jit_inline

__all__ = [
    "factorized_record",
    "joint_record",
    "left_multiply_row",
    "tracked_record",
    "update_m_sigma_rows",
]


@jit_inline
def _tracked_update(G, K, R, Bij, e, work, J6, Pn, T1):
    """Robot i's covariance after an update with gain ``K`` and ``G = I - K H_i``:
    ``[G, D] [[P_i, C_ij], [C_ij^T, P_j]] [G, D]^T + K R K^T`` with ``D = -K H_j`` (the
    link's ``Bij[e]``) and the blocks of :func:`joint_cross` (``work[0:3]``), symmetrized,
    into ``Pn`` and ``work[4]`` (``T1``, ``J6[1, :3, :3]``: scratch). Twin:
    ``JointCovariance.current`` after ``update`` (``M_i Sigma M_i^T + N_i`` with the
    updated ``M_i``, ``N_i``; the same quantity)."""
    for a in range(3):  # T1 = G P_i + D C^T, T2 = G C + D P_j
        for b in range(3):
            T1[a, b] = (
                G[a, 0] * work[0, 0, b] + G[a, 1] * work[0, 1, b] + G[a, 2] * work[0, 2, b]
            ) + (
                Bij[e, a, 0] * work[1, b, 0]
                + Bij[e, a, 1] * work[1, b, 1]
                + Bij[e, a, 2] * work[1, b, 2]
            )
            J6[1, a, b] = (
                G[a, 0] * work[1, 0, b] + G[a, 1] * work[1, 1, b] + G[a, 2] * work[1, 2, b]
            ) + (
                Bij[e, a, 0] * work[2, 0, b]
                + Bij[e, a, 1] * work[2, 1, b]
                + Bij[e, a, 2] * work[2, 2, b]
            )
    for a in range(3):
        t0 = K[a, 0] * R[0, 0] + K[a, 1] * R[1, 0]
        t1 = K[a, 0] * R[0, 1] + K[a, 1] * R[1, 1]
        for b in range(3):
            Pn[a, b] = (
                (T1[a, 0] * G[b, 0] + T1[a, 1] * G[b, 1] + T1[a, 2] * G[b, 2])
                + (
                    J6[1, a, 0] * Bij[e, b, 0]
                    + J6[1, a, 1] * Bij[e, b, 1]
                    + J6[1, a, 2] * Bij[e, b, 2]
                )
                + (t0 * K[b, 0] + t1 * K[b, 1])
            )
    for a in range(3):
        for b in range(a, 3):
            m = 0.5 * (Pn[a, b] + Pn[b, a])
            Pn[a, b] = m
            Pn[b, a] = m
            work[4, a, b] = m
            work[4, b, a] = m


@jit_inline
def left_multiply_row(G, M, r, T3):
    """``M[r] <- G M[r]`` of 3 x 3 matrices in place (``T3``: scratch; no view of ``M``)."""
    for a in range(3):
        for b in range(3):
            T3[a, b] = G[a, 0] * M[r, 0, b] + G[a, 1] * M[r, 1, b] + G[a, 2] * M[r, 2, b]
    for a in range(3):
        for b in range(3):
            M[r, a, b] = T3[a, b]


@jit_inline
def joint_record(joint, e, first, fused, i, xi0, xi1, xj0, xj1, K, R, Hi, Hj, G, T3, Pn):
    """Record link ``e``'s update of robot ``i`` (gain ``K``) linearized at i's estimate
    before the update and j's transmitted one; ``tracked`` writes robot i's covariance after
    the update into ``Pn``. Twin: ``JointCovariance.update`` /
    ``FactorizedCovariance.update`` (:func:`tracked_record`, :func:`factorized_record`)."""
    if joint[0] == TRACKED:
        tracked_record(joint, e, first, fused, i, xi0, xi1, xj0, xj1, K, R, Hi, Hj, G, T3, Pn)
    else:
        factorized_record(joint, e, i, xi0, xi1, xj0, xj1, K, Hi, Hj, G, T3)


@jit_inline
def _gain_map(joint, i, xi0, xi1, xj0, xj1, K, Hi, Hj, G, T3):
    """The Jacobians, ``G = I - K H_i`` and robot i's ``A_i <- G A_i``."""
    range_bearing_jacobians_into(xi0, xi1, xj0, xj1, Hi, Hj)
    for a in range(3):  # G = I - K H_i
        for b in range(3):
            G[a, b] = (1.0 if a == b else 0.0) - (K[a, 0] * Hi[0, b] + K[a, 1] * Hi[1, b])
    left_multiply_row(G, joint[5], i, T3)


@jit_inline
def tracked_record(joint, e, first, fused, i, xi0, xi1, xj0, xj1, K, R, Hi, Hj, G, T3, Pn):
    """:func:`joint_record` of ``tracked``: the blocks of ``M_i``, the noise, i's rows of
    ``M Sigma`` (the cross of its later links, :func:`update_m_sigma_rows`), then ``P_i`` into
    ``Pn``. The gain ``G`` is kept (``joint[13][e]``); its products with robot i's earlier
    fused ``B_ij`` (``M_i <- G M_i`` on their blocks; no record reads them) are left to the
    commit (:func:`~resloc.cl.kernels_tracked_step.apply_later_gains`: two products a link,
    not a walk over every earlier link of the robot per record; ``first`` and ``fused``,
    which that walk read, are the shared call's). Indexes the arrays, takes no view of them
    (a view costs a reference count, and this runs per link)."""
    Bij = joint[6]
    noise = joint[4]
    gains = joint[13]
    _gain_map(joint, i, xi0, xi1, xj0, xj1, K, Hi, Hj, G, T3)
    for a in range(3):
        for b in range(3):
            Bij[e, a, b] = -(K[a, 0] * Hj[0, b] + K[a, 1] * Hj[1, b])
            gains[e, a, b] = G[a, b]
    for a in range(3):  # N_i <- G N_i G^T + K R K^T
        for b in range(3):
            T3[a, b] = (
                G[a, 0] * noise[i, 0, b] + G[a, 1] * noise[i, 1, b] + G[a, 2] * noise[i, 2, b]
            )
    for a in range(3):
        t0 = K[a, 0] * R[0, 0] + K[a, 1] * R[1, 0]
        t1 = K[a, 0] * R[0, 1] + K[a, 1] * R[1, 1]
        for b in range(3):
            s = 0.0
            for c in range(3):
                s += T3[a, c] * G[b, c]
            Pn[a, b] = s + (t0 * K[b, 0] + t1 * K[b, 1])
    for a in range(3):
        for b in range(3):
            noise[i, a, b] = Pn[a, b]
    N = joint[1]
    update_m_sigma_rows(joint[14], joint[3], i, i // N, 3 * (joint[2][e] % N), G, Bij, e)
    _tracked_update(G, K, R, Bij, e, joint[11], joint[12], Pn, T3)


@jit_inline
def update_m_sigma_rows(rows, sigma, i, t, cj, G, Bij, e):
    """Robot i's rows of ``M Sigma`` after the update: ``rows[i] <- G rows[i] + B_ij
    Sigma[j's rows]`` (``B_ij = Bij[e]``, ``Sigma``: team ``t``'s joint as the step began,
    j's rows from ``cj``), column by column in place. The gain and ``B_ij`` in scalars
    first: stores into ``rows`` would otherwise reload them (LLVM cannot prove the arrays
    apart), and the loop over the 3N columns compiles to SIMD. ``B_ij = -K H_j`` as the
    record wrote it has a zero third column (``H_j``'s is zero): j's third row of
    ``Sigma`` is not read (for finite entries the same sums: the terms left out are zeros;
    the rows are ``M Sigma`` over ``M``'s non-zero blocks already), a sixth of the
    products."""
    g00 = G[0, 0]
    g01 = G[0, 1]
    g02 = G[0, 2]
    g10 = G[1, 0]
    g11 = G[1, 1]
    g12 = G[1, 2]
    g20 = G[2, 0]
    g21 = G[2, 1]
    g22 = G[2, 2]
    b00 = Bij[e, 0, 0]
    b01 = Bij[e, 0, 1]
    b10 = Bij[e, 1, 0]
    b11 = Bij[e, 1, 1]
    b20 = Bij[e, 2, 0]
    b21 = Bij[e, 2, 1]
    for q in range(rows.shape[2]):
        w0 = rows[i, 0, q]
        w1 = rows[i, 1, q]
        w2 = rows[i, 2, q]
        s0 = sigma[t, cj, q]
        s1 = sigma[t, cj + 1, q]
        rows[i, 0, q] = (g00 * w0 + g01 * w1 + g02 * w2) + (b00 * s0 + b01 * s1)
        rows[i, 1, q] = (g10 * w0 + g11 * w1 + g12 * w2) + (b10 * s0 + b11 * s1)
        rows[i, 2, q] = (g20 * w0 + g21 * w1 + g22 * w2) + (b20 * s0 + b21 * s1)


@jit_inline
def factorized_record(joint, e, i, xi0, xi1, xj0, xj1, K, Hi, Hj, G, T3):
    """:func:`joint_record` of ``factorized``: the factors and B's products with G are
    deferred to the commit (:func:`resloc.cl.kernels_joint.joint_commit`): records ``G``
    and ``-K H_j``."""
    N = joint[1]
    j = joint[2][e]
    Bij = joint[6]
    gains = joint[13]
    _gain_map(joint, i, xi0, xi1, xj0, xj1, K, Hi, Hj, G, T3)
    for a in range(3):
        for b in range(3):
            gains[e, a, b] = G[a, b]
            Bij[e, a, b] = -(K[a, 0] * Hj[0, b] + K[a, 1] * Hj[1, b])
    joint[10][i, j % N] = True
