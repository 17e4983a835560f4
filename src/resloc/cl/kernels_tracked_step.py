"""``tracked``'s commit and end of step from the blocks of ``M``, compiled.

After a compiled correction the kernel holds ``M`` by its non-zero 3 x 3 blocks (robot b's
``A_b`` at its own column, each fused link's ``B_ij`` at j's: :class:`~resloc.cl.kernels_joint.
KernelJoint`) and each robot's rows of ``U = M Sigma`` (``rows``, the records'). The
reference's end of step is ``Sigma <- sym(M Sigma M^T + blockdiag(N))``
(:meth:`resloc.cl.tracking.JointCovariance.finish`). :func:`commit_tracked` applies the
gains the records deferred to the earlier ``B_ij`` (:func:`apply_later_gains`), hands the
blocks to the joint (:meth:`~resloc.cl.tracking.JointCovariance.set_blocks`: the dense ``M``
is built only if the reference reads it) and computes the end of step at once, while the
rows are still in the cache, from the blocks: ``M U^T`` over each robot's blocks, only the
lower triangle of the team's joint (the result is symmetric; its upper triangle is the
mirror), into :attr:`~resloc.cl.tracking.JointCovariance.end_of_step`, which the compiled
finish (:func:`resloc.cl.kernels_fusion_step.compiled_tracked_finish`) installs.

Not the reference's sums to the bit (it sums the dense products and averages the two
triangles): equal to 1e-9 (the tests check 1e-12 relative on random block-sparse maps), as
the project's rule for compiled twins asks. A non-finite entry in the rows leaves the end
of step to the dense path (``0 * inf`` is ``nan`` in the reference's dense product, which a
product over the non-zero blocks skips).

=============================  ======================================================
function                       numpy twin
=============================  ======================================================
:func:`commit_tracked`         the state ``JointCovariance.update`` leaves, then
                               ``JointCovariance.finish``'s new joint and diagonal
:func:`apply_later_gains`      ``JointCovariance.update``'s ``G M_i`` on the earlier
                               links' blocks of ``M_i``
=============================  ======================================================
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl.kernels_math import jit

__all__ = ["apply_later_gains", "commit_tracked", "installed_end_of_step", "take_spare_rows"]


def take_spare_rows(joint, sigma: np.ndarray) -> np.ndarray:
    """Each robot's rows of ``sigma`` (B, 3, 3N), a copy the kernel may update in place: the
    prediction's spare when it is a copy of this very ``sigma`` (taken: used once), else
    copied now. The compiled prediction keeps ``joint.spare_rows = (sigma, spare)``
    (:func:`resloc.cl.kernels_fusion_step.compiled_tracked_predict`: ``spare``, a copy of
    the new joint ``sigma`` it wrote while it had it in the cache, in the rows' shape,
    since ``M = I`` at a step's start)."""
    spare = joint.spare_rows
    if spare is not None:
        joint.spare_rows = None
        if spare[0] is sigma:
            return spare[1]
    T, n3 = sigma.shape[0], sigma.shape[1]
    return sigma.reshape(T * n3 // 3, 3, n3).copy()


def commit_tracked(state, joint, obs: np.ndarray, fused: np.ndarray) -> None:
    """Hand a compiled correction's records (``state``: the kernel's
    :class:`~resloc.cl.kernels_joint.KernelJoint`; ``obs``, ``fused``: the links' observers
    (E,) int64 and whether each fused, (E,) bool) to ``joint`` (a
    :class:`~resloc.cl.tracking.JointCovariance` as the step began: checked by
    ``joint_state``): the gains the records deferred applied to the earlier ``B_ij``, then
    the blocks, and the end of step computed from them (kept in ``joint.end_of_step`` for the
    compiled finish; left None where a row is not finite), in one compiled call."""
    # (the fields unpacked at once: a NamedTuple's field by name is a property call)
    _, N, nbr, _, noise, A, Bij, _, _, _, _, _, _, gains, rows = state
    sigma = np.empty(joint.sigma.shape)
    diagonal = np.empty(A.shape)
    count = _end_of_step(rows, A, Bij, obs, nbr, fused, noise, N, sigma, diagonal, gains)
    joint.set_blocks(A, Bij, obs, nbr, fused)
    joint.noise = noise
    joint.m_sigma = rows  # M Sigma as the records kept it (the dense path's first product)
    if count >= 0:
        joint.updates = count
        joint.end_of_step = (sigma, diagonal)
    else:
        joint.updates = int(np.count_nonzero(fused))


def installed_end_of_step(joint) -> np.ndarray | None:
    """The end of step :func:`commit_tracked` computed, installed as ``joint``'s joint and
    the step's bookkeeping started (the reference's ``finish``); returns the diagonal blocks
    (B, 3, 3), or None when there is none (then the caller computes it)."""
    done = joint.end_of_step
    if done is None:
        return None
    joint.sigma = done[0]
    joint.start_step()
    return done[1]


@jit
def _end_of_step(rows, A, Bij, obs, nbr, fused, noise, N, out, diagonal, gains):
    """``out[t] = sym(M_t U_t^T + blockdiag(noise))`` per team from ``rows = U`` (B, 3, 3N:
    each robot's rows of ``M Sigma``) and ``M``'s blocks (``A``: (B, 3, 3) at each robot's
    own column; ``Bij[e]`` at column ``nbr[e]`` of row ``obs[e]`` for each ``fused[e]``;
    blocks at the same place add up, as the reference's records do), the diagonal blocks
    into ``diagonal``. ``gains`` (E, 3, 3): each fused link's ``G``, whose products with
    the robot's earlier ``B_ij`` the records deferred (:func:`apply_later_gains`, applied
    first, into ``Bij``), or (0, 3, 3) where ``Bij`` holds them already. Returns the number
    of fused links, or -1 (``out`` and ``diagonal`` not valid) when an entry of ``rows`` is
    not finite.

    ``U^T`` per team first (a transposed copy: the block products then run over contiguous
    rows, SIMD); robot a's rows of the result, left of and in its diagonal block only (the
    lower triangle by blocks): ``A_a`` and each fused ``B_ad`` times three rows of ``U^T``;
    then the upper triangle mirrored and the diagonal blocks symmetrized with the noise.
    About half the flops of the product over all blocks (``kernels_fusion_step.
    _block_product``), no dense ``M``."""
    B = A.shape[0]
    n3 = 3 * N
    E = obs.shape[0]
    start = np.zeros(B + 1, np.int64)  # each robot's fused links, grouped (CSR)
    nf = 0
    for e in range(E):
        if fused[e]:
            start[obs[e] + 1] += 1
            nf += 1
    for b in range(B):
        start[b + 1] += start[b]
    fill = start[:B].copy()
    order = np.empty(nf, np.int64)
    for e in range(E):
        if fused[e]:
            order[fill[obs[e]]] = e
            fill[obs[e]] += 1
    if gains.shape[0]:
        _later_gains_by_robot(Bij, gains, start, order, B)
    UT = np.empty((n3, n3))
    for t in range(out.shape[0]):
        bad = 0  # (the rows' check in the copy: an integer sum, branch-free)
        for a in range(N):  # U^T of the team: UT[k, 3a + p] = rows[a, p, k]
            for k in range(n3):  # (three entries stored side by side per k)
                for p in range(3):
                    v = rows[t * N + a, p, k]
                    UT[k, 3 * a + p] = v
                    bad += 0 if abs(v) < math.inf else 1
        if bad:
            return -1
        res = out[t]
        for a in range(N):
            b = t * N + a
            r = 3 * a
            width = r + 3  # the columns left of robot a's diagonal block, and the block
            _add_block(A, b, UT, r, width, res, r, False)  # (A_a first: it sets the rows)
            for s in range(start[b], start[b + 1]):
                e = order[s]
                _add_block(Bij, e, UT, 3 * (nbr[e] % N), width, res, r, True)
        for a in range(N):  # the mirror, block by block (three entries side by side)
            for c in range(a):
                for j in range(3):
                    for i in range(3):
                        res[3 * c + j, 3 * a + i] = res[3 * a + i, 3 * c + j]
        for p in range(n3):  # the diagonal blocks symmetrized with the noise
            a = p // 3
            d = 3 * a
            for k in range(p - d + 1):
                q = d + k
                v = 0.5 * (res[p, q] + res[q, p])
                v += 0.5 * (noise[t * N + a, p - d, k] + noise[t * N + a, k, p - d])
                res[p, q] = v
                res[q, p] = v
                diagonal[t * N + a, p - d, k] = v
                diagonal[t * N + a, k, p - d] = v
    return nf


@jit
def apply_later_gains(Bij, gains, obs, fused):
    """Each fused link's ``B_ij`` (``Bij[e]``, (E, 3, 3)) left-multiplied by the gains
    ``G`` (``gains[e]``) of its robot's later fused links (``obs``, ``fused``: (E,) the
    links' observers, rows in the order the records ran): the reference's ``M_i <- G M_i``
    (``JointCovariance.update``) on the blocks of the earlier links, which the compiled
    records leave to the commit (they keep each fused link's ``G``; no record reads an
    earlier ``B_ij``). For a robot's fused links ``e_1 < ... < e_k``, from the last:
    ``B_(e_m) <- S B_(e_m)``, ``S <- S G_(e_m)`` (``S = I`` first): two products a link;
    the same matrices, summed in another order (1e-16 relative a product). A zero third
    column (``-K H_j``'s) stays zero."""
    B = 0
    for e in range(obs.shape[0]):
        B = max(B, obs[e] + 1)
    start = np.zeros(B + 1, np.int64)
    for e in range(obs.shape[0]):
        if fused[e]:
            start[obs[e] + 1] += 1
    for b in range(B):
        start[b + 1] += start[b]
    fill = start[:B].copy()
    order = np.empty(start[B], np.int64)
    for e in range(obs.shape[0]):
        if fused[e]:
            order[fill[obs[e]]] = e
            fill[obs[e]] += 1
    _later_gains_by_robot(Bij, gains, start, order, B)


@jit
def _later_gains_by_robot(Bij, gains, start, order, B):
    """:func:`apply_later_gains` on the fused links grouped by robot (``order[start[b]:
    start[b + 1]]``: robot b's, in the records' order)."""
    for b in range(B):
        last = start[b + 1] - 1
        if last <= start[b]:
            continue  # (no or one fused link: no later gain)
        e = order[last]
        s00, s01, s02 = gains[e, 0, 0], gains[e, 0, 1], gains[e, 0, 2]
        s10, s11, s12 = gains[e, 1, 0], gains[e, 1, 1], gains[e, 1, 2]
        s20, s21, s22 = gains[e, 2, 0], gains[e, 2, 1], gains[e, 2, 2]
        for m in range(last - 1, start[b] - 1, -1):
            e = order[m]
            b00, b01, b02 = Bij[e, 0, 0], Bij[e, 0, 1], Bij[e, 0, 2]
            b10, b11, b12 = Bij[e, 1, 0], Bij[e, 1, 1], Bij[e, 1, 2]
            b20, b21, b22 = Bij[e, 2, 0], Bij[e, 2, 1], Bij[e, 2, 2]
            Bij[e, 0, 0] = s00 * b00 + s01 * b10 + s02 * b20
            Bij[e, 0, 1] = s00 * b01 + s01 * b11 + s02 * b21
            Bij[e, 1, 0] = s10 * b00 + s11 * b10 + s12 * b20
            Bij[e, 1, 1] = s10 * b01 + s11 * b11 + s12 * b21
            Bij[e, 2, 0] = s20 * b00 + s21 * b10 + s22 * b20
            Bij[e, 2, 1] = s20 * b01 + s21 * b11 + s22 * b21
            if b02 != 0.0 or b12 != 0.0 or b22 != 0.0:  # (B_ij's third column: zero)
                Bij[e, 0, 2] = s00 * b02 + s01 * b12 + s02 * b22
                Bij[e, 1, 2] = s10 * b02 + s11 * b12 + s12 * b22
                Bij[e, 2, 2] = s20 * b02 + s21 * b12 + s22 * b22
            if m > start[b]:  # S <- S G_e
                g00, g01, g02 = gains[e, 0, 0], gains[e, 0, 1], gains[e, 0, 2]
                g10, g11, g12 = gains[e, 1, 0], gains[e, 1, 1], gains[e, 1, 2]
                g20, g21, g22 = gains[e, 2, 0], gains[e, 2, 1], gains[e, 2, 2]
                s00, s01, s02 = (
                    s00 * g00 + s01 * g10 + s02 * g20,
                    s00 * g01 + s01 * g11 + s02 * g21,
                    s00 * g02 + s01 * g12 + s02 * g22,
                )
                s10, s11, s12 = (
                    s10 * g00 + s11 * g10 + s12 * g20,
                    s10 * g01 + s11 * g11 + s12 * g21,
                    s10 * g02 + s11 * g12 + s12 * g22,
                )
                s20, s21, s22 = (
                    s20 * g00 + s21 * g10 + s22 * g20,
                    s20 * g01 + s21 * g11 + s22 * g21,
                    s20 * g02 + s21 * g12 + s22 * g22,
                )


@jit
def _add_block(M, m, UT, k, width, res, r, add):
    """``res[r:r + 3, :width] += M[m] UT[k:k + 3, :width]`` (``=`` without ``add``; the
    block's entries in scalars: the loop over columns compiles to SIMD)."""
    m00 = M[m, 0, 0]
    m01 = M[m, 0, 1]
    m02 = M[m, 0, 2]
    m10 = M[m, 1, 0]
    m11 = M[m, 1, 1]
    m12 = M[m, 1, 2]
    m20 = M[m, 2, 0]
    m21 = M[m, 2, 1]
    m22 = M[m, 2, 2]
    if add and m02 == 0.0 and m12 == 0.0 and m22 == 0.0:
        # a zero third column (every B_ij: -K H_j, H_j's third column is zero, times the
        # later gains): two rows of UT, a third fewer products (UT finite: the terms
        # skipped are zeros)
        for q in range(width):
            s0 = UT[k, q]
            s1 = UT[k + 1, q]
            res[r, q] += m00 * s0 + m01 * s1
            res[r + 1, q] += m10 * s0 + m11 * s1
            res[r + 2, q] += m20 * s0 + m21 * s1
        return
    if not add:
        for q in range(width):
            s0 = UT[k, q]
            s1 = UT[k + 1, q]
            s2 = UT[k + 2, q]
            res[r, q] = m00 * s0 + m01 * s1 + m02 * s2
            res[r + 1, q] = m10 * s0 + m11 * s1 + m12 * s2
            res[r + 2, q] = m20 * s0 + m21 * s1 + m22 * s2
        return
    for q in range(width):
        s0 = UT[k, q]
        s1 = UT[k + 1, q]
        s2 = UT[k + 2, q]
        res[r, q] += m00 * s0 + m01 * s1 + m02 * s2
        res[r + 1, q] += m10 * s0 + m11 * s1 + m12 * s2
        res[r + 2, q] += m20 * s0 + m21 * s1 + m22 * s2
