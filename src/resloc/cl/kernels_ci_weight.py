"""Compiled covariance-intersection weight (``ci`` and ``split_ci`` fusion): the weight
``w`` of each link that minimises the linearized posterior size under the joint bound
``blockdiag(P_i / w, P_j / (1 - w))`` (:func:`resloc.cl.fusion.ci_weights`: a grid, one
parabolic refinement, kept only where it helps, and ``w = 1``, "ignore j", when no weight
beats the prior), from the link's 2 x 2 reductions, which the update
(:mod:`resloc.cl.kernels_ci_update`, :mod:`resloc.cl.kernels_split`) reuses.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`ci_cost`               ``resloc.cl.fusion._posterior_cost``
:func:`grid_costs`            ``resloc.cl.fusion._posterior_cost`` on the grid
:func:`first_best`           ``np.argmin`` of the grid's costs
:func:`_search_weight`         :func:`resloc.cl.fusion.ci_weights` after the reductions
:func:`weight_of`             :func:`resloc.cl.fusion.ci_weights` from the reductions
=============================  ==========================================================

The candidate weights come as the kernels take them, ``(3, G)`` (the weights ``w``,
``1 / w`` and ``1 / (1 - w)``: ``resloc.cl.kernels_fusion._GRID``, in
:class:`~resloc.cl.kernels_fusion.KernelFusion`).
"""

from __future__ import annotations

import numpy as np

from resloc.cl.kernels_math import entries3, jit_inline, jit_lanes

__all__ = [
    "ci_cost",
    "det3_scaled_entries",
    "first_best",
    "gram",
    "grid_costs",
    "reduce_i",
    "reduce_j",
    "weight_of",
]


@jit_inline
def ci_cost(u, v, det, split, tr_i, det_i, a, ai, b, bi, g, gdi, gii, Dp, Ip, tr_ip, R):
    """Linearized posterior ``trace`` (or ``det``) of ``P_i`` under the CI joint bound with
    weight ``w`` given as ``u = 1 / w`` and ``v = 1 / (1 - w)`` (the grid's are computed
    once, ``kernels_fusion._GRID``: one division per evaluation is left, that of ``S^-1``) from the
    link's 2 x 2 reductions (4-tuples ``(m00, m01, m10, m11)``):
    ``a = H_i D_i H_i^T``, ``b = H_j D_j H_j^T``, ``g = C^T C`` with ``C = D_i H_i^T``
    (``D``: the covariances, or their dependent parts with ``split``), and with ``split``
    the independent parts' ``ai = H_i I_i H_i^T``, ``bi = H_j I_j H_j^T + R``, ``gdi =
    C^T (I_i H_i^T)``, ``gii`` and the parts ``Dp``, ``Ip`` of ``P_i`` themselves (9-tuples
    by row; ``tr_ip``: trace of ``Ip``; ``tr_i``: trace of ``Dp``, ``det_i``: its
    determinant, used without ``split``; ``R``: a 4-tuple). Tuples of scalars, no arrays:
    each array an inlined call receives costs a reference-count update, and the weight's
    search calls this 34 times a link (33 of them in :func:`grid_costs`).
    Twin: ``resloc.cl.fusion._posterior_cost``."""
    if split:
        sj00 = b[0] * v + bi[0]
        sj01 = b[1] * v + bi[1]
        sj10 = b[2] * v + bi[2]
        sj11 = b[3] * v + bi[3]
        s00 = a[0] * u + ai[0] + sj00
        s01 = a[1] * u + ai[1] + sj01
        s10 = a[2] * u + ai[2] + sj10
        s11 = a[3] * u + ai[3] + sj11
    else:
        sj00 = b[0] * v + R[0]
        sj01 = b[1] * v + R[1]
        sj10 = b[2] * v + R[2]
        sj11 = b[3] * v + R[3]
        s00 = a[0] * u + sj00
        s01 = a[1] * u + sj01
        s10 = a[2] * u + sj10
        s11 = a[3] * u + sj11
    det_s = s00 * s11 - s01 * s10
    if det:
        if split:  # det(D_i / w + I_i)
            return det3_scaled_entries(Dp, u, Ip) * (sj00 * sj11 - sj01 * sj10) / det_s
        return det_i * u * u * u * (sj00 * sj11 - sj01 * sj10) / det_s
    if split:
        q00 = g[0] * u * u + (gdi[0] + gdi[0]) * u + gii[0]
        q01 = g[1] * u * u + (gdi[1] + gdi[2]) * u + gii[1]
        q10 = g[2] * u * u + (gdi[2] + gdi[1]) * u + gii[2]
        q11 = g[3] * u * u + (gdi[3] + gdi[3]) * u + gii[3]
        tr_a = tr_i * u + tr_ip
    else:
        q00 = g[0] * u * u
        q01 = g[1] * u * u
        q10 = g[2] * u * u
        q11 = g[3] * u * u
        tr_a = tr_i * u
    tr_gsinv = (q00 * s11 + q11 * s00 - q01 * s10 - q10 * s01) / det_s
    return tr_a - tr_gsinv


@jit_inline
def _det3_scaled(D, u, I3):
    """``det(D u + I3)`` of 3 x 3 matrices."""
    return det3_scaled_entries(entries3(D), u, entries3(I3))


@jit_inline
def det3_scaled_entries(D, u, I3):
    """``det(D u + I3)`` of 3 x 3 matrices given as 9-tuples by row."""
    m00 = D[0] * u + I3[0]
    m01 = D[1] * u + I3[1]
    m02 = D[2] * u + I3[2]
    m10 = D[3] * u + I3[3]
    m11 = D[4] * u + I3[4]
    m12 = D[5] * u + I3[5]
    m20 = D[6] * u + I3[6]
    m21 = D[7] * u + I3[7]
    m22 = D[8] * u + I3[8]
    return (
        m00 * (m11 * m22 - m12 * m21)
        - m01 * (m10 * m22 - m12 * m20)
        + m02 * (m10 * m21 - m11 * m20)
    )


@jit_inline
def _row_times_ht(D, r, H):
    """Row ``r`` of ``D H^T`` (3 x 3 times 3 x 2) as a 2-tuple."""
    return (
        D[r, 0] * H[0, 0] + D[r, 1] * H[0, 1] + D[r, 2] * H[0, 2],
        D[r, 0] * H[1, 0] + D[r, 1] * H[1, 1] + D[r, 2] * H[1, 2],
    )


@jit_inline
def reduce_i(D, Hi):
    """``a = H_i D H_i^T`` (a 4-tuple) and the rows of ``C = D H_i^T`` (a 6-tuple
    ``(c00, c01, c10, c11, c20, c21)``)."""
    c00, c01 = _row_times_ht(D, 0, Hi)
    c10, c11 = _row_times_ht(D, 1, Hi)
    c20, c21 = _row_times_ht(D, 2, Hi)
    a00 = Hi[0, 0] * c00 + Hi[0, 1] * c10 + Hi[0, 2] * c20
    a01 = Hi[0, 0] * c01 + Hi[0, 1] * c11 + Hi[0, 2] * c21
    a10 = Hi[1, 0] * c00 + Hi[1, 1] * c10 + Hi[1, 2] * c20
    a11 = Hi[1, 0] * c01 + Hi[1, 1] * c11 + Hi[1, 2] * c21
    return (a00, a01, a10, a11), (c00, c01, c10, c11, c20, c21)


@jit_inline
def reduce_j(D, Hj):
    """``H_j D H_j^T`` as a 4-tuple."""
    b00 = b01 = b10 = b11 = 0.0
    for k in range(3):
        t0 = 0.0
        t1 = 0.0
        for c in range(3):
            t0 += Hj[0, c] * D[c, k]
            t1 += Hj[1, c] * D[c, k]
        b00 += t0 * Hj[0, k]
        b01 += t0 * Hj[1, k]
        b10 += t1 * Hj[0, k]
        b11 += t1 * Hj[1, k]
    return (b00, b01, b10, b11)


@jit_inline
def gram(c, d):
    """``c^T d`` of two 3 x 2 matrices (6-tuples of rows, :func:`reduce_i`) as a 4-tuple."""
    g00 = c[0] * d[0] + c[2] * d[2] + c[4] * d[4]
    g01 = c[0] * d[1] + c[2] * d[3] + c[4] * d[5]
    g10 = c[1] * d[0] + c[3] * d[2] + c[5] * d[4]
    g11 = c[1] * d[1] + c[3] * d[3] + c[5] * d[5]
    return (g00, g01, g10, g11)


@jit_lanes
def grid_costs(grid, det, split, tr_i, det_i, a, ai, b, bi, g, gdi, gii, Dp, Ip, tr_ip, R, cost):
    """The cost (:func:`ci_cost`) at every candidate weight of ``grid: (3, G)`` (rows ``w``,
    ``1 / w``, ``1 / (1 - w)``, ``kernels_fusion._GRID``) into ``cost: (G,)``.
    A loop of its own, free of branches and compiled with IEEE division (``jit_lanes``),
    so that LLVM evaluates several weights per SIMD instruction; the same arithmetic per
    weight as one evaluation, so the same costs to the bit."""
    for t in range(grid.shape[1]):
        cost[t] = ci_cost(
            grid[1, t],
            grid[2, t],
            det,
            split,
            tr_i,
            det_i,
            a,
            ai,
            b,
            bi,
            g,
            gdi,
            gii,
            Dp,
            Ip,
            tr_ip,
            R,
        )


@jit_inline
def first_best(cost, n):
    """``(cost[k], k)``: the first smallest of ``cost[:n]`` as the scalar search finds it
    (``best = cost[0]``, then ``cost[t] < best`` replaces it: a NaN first cost stays the
    best, a later NaN never becomes it). Four interleaved searches (``t = 1, 5, ...``,
    ``t = 2, 6, ...``, ...) merged by value then index: the same ``k``, in a quarter of
    the scalar search's chain of dependent compares (measured with the grid's inverses,
    ``kernels_fusion._GRID``: a ``ci`` link's weight 119 -> 108 ns)."""
    b0 = b1 = b2 = b3 = np.inf
    k0 = k1 = k2 = k3 = -1
    t = 1
    while t + 3 < n:
        c = cost[t]
        if c < b0:
            b0 = c
            k0 = t
        c = cost[t + 1]
        if c < b1:
            b1 = c
            k1 = t + 1
        c = cost[t + 2]
        if c < b2:
            b2 = c
            k2 = t + 2
        c = cost[t + 3]
        if c < b3:
            b3 = c
            k3 = t + 3
        t += 4
    while t < n:  # the rest, in index order, by the first search
        c = cost[t]
        if c < b0:
            b0 = c
            k0 = t
        t += 1
    best = cost[0]
    k = 0
    if best == best:  # (not NaN)
        for m, q in ((b0, k0), (b1, k1), (b2, k2), (b3, k3)):
            if q >= 0 and (m < best or (m == best and q < k)):
                best = m
                k = q
    return best, k


@jit_lanes
def _search_weight(grid, det, split, tr_i, det_i, a, ai, b, bi, g, gdi, gii, Dp, Ip, tr_ip, R,
                   prior, cost):  # fmt: skip
    """The weight minimising the cost (arguments of :func:`ci_cost`, ``grid`` of
    :func:`grid_costs`; ``prior``: the cost
    of ``w = 1``, the prior kept; ``cost: (G,)``: scratch): the first best of the grid
    (:func:`grid_costs`), refined by the parabola through it and its neighbours (the first
    or last three points when it is at an end) where that helps; 1.0 when no weight beats
    the prior. A call of its own, not inlined: the link loops' bodies stay small, and the
    grid's loop is vectorized (measured: the weight of a ``ci`` link about 2.3x faster
    than by the inlined scalar search that kept the best as it went)."""
    n = grid.shape[1]
    grid_costs(grid, det, split, tr_i, det_i, a, ai, b, bi, g, gdi, gii, Dp, Ip, tr_ip, R, cost)
    best, k = first_best(cost, n)
    kc = min(max(k, 1), n - 2)
    c0 = cost[kc - 1]
    c1 = cost[kc]
    c2 = cost[kc + 1]
    h = grid[0, 1] - grid[0, 0]
    denom = c0 - 2.0 * c1 + c2
    shift = 0.5 * h * (c0 - c2) / denom if denom > 0.0 else 0.0
    if k == kc:
        shift = min(max(shift, -h), h)
        w = min(max(grid[0, kc] + shift, grid[0, 0]), grid[0, n - 1])
    else:
        w = grid[0, k]
    refined = ci_cost(
        1.0 / w, 1.0 / (1.0 - w), det, split, tr_i, det_i, a, ai, b, bi, g, gdi, gii, Dp, Ip,
        tr_ip, R,
    )  # fmt: skip
    if refined <= best:
        best = refined
    else:
        w = grid[0, k]
    return w if best < prior else 1.0


@jit_inline
def weight_of(a, cd, b, Di, Ii, Ij, split, Hi, Hj, R, det, grid, cost):
    """The CI weight of one link (1.0: no weight makes the posterior smaller than the prior)
    from the reductions ``a = H_i D_i H_i^T``, ``cd = D_i H_i^T``
    (:func:`reduce_i`) and ``b = H_j D_j H_j^T`` (:func:`reduce_j`), which
    :func:`ci_update` reuses for the update."""
    g = gram(cd, cd)
    zero = (0.0, 0.0, 0.0, 0.0)
    ai = zero
    bi = zero
    gdi = zero
    gii = zero
    if split:
        ai, ci = reduce_i(Ii, Hi)
        gdi = gram(cd, ci)
        gii = gram(ci, ci)
        bj = reduce_j(Ij, Hj)
        bi = (bj[0] + R[0, 0], bj[1] + R[0, 1], bj[2] + R[1, 0], bj[3] + R[1, 1])
    tr_i = Di[0, 0] + Di[1, 1] + Di[2, 2]
    det_i = (
        Di[0, 0] * (Di[1, 1] * Di[2, 2] - Di[1, 2] * Di[2, 1])
        - Di[0, 1] * (Di[1, 0] * Di[2, 2] - Di[1, 2] * Di[2, 0])
        + Di[0, 2] * (Di[1, 0] * Di[2, 1] - Di[1, 1] * Di[2, 0])
    )
    tr_ip = Ii[0, 0] + Ii[1, 1] + Ii[2, 2]
    if split:  # the prior P_i = D_i + I_i
        if det:
            prior = _det3_scaled(Di, 1.0, Ii)
        else:
            prior = tr_i + tr_ip
    else:
        prior = det_i if det else tr_i
    # the matrices as tuples of scalars for the evaluations of the cost (see ci_cost)
    return _search_weight(
        grid, det, split, tr_i, det_i, a, ai, b, bi, g, gdi, gii, entries3(Di), entries3(Ii),
        tr_ip, (R[0, 0], R[0, 1], R[1, 0], R[1, 1]), prior, cost,
    )  # fmt: skip
