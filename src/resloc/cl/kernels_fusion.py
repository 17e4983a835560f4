"""Compiled twins of the fusion methods that change the update itself: ``ci`` and the
weights and inflated update ``split_ci`` shares (:mod:`resloc.cl.kernels_split`), and the
fusion method as the link loop takes it (:class:`KernelFusion`).

Covariance intersection (:func:`resloc.cl.fusion.fused_update` with ``ci``) uses the joint
bound ``blockdiag(P_i / w, P_j / (1 - w))``: the weight ``w`` of each link minimises the
linearized posterior size (:func:`resloc.cl.fusion.ci_weights`: a grid, one parabolic
refinement, kept only where it helps, and ``w = 1``, "ignore j", when no weight beats the
prior), then the filter's own moments are extended by the inflations through the
range/bearing Jacobians at the means (split CI: of the dependent parts only). The CL link
loop (:mod:`resloc.cl.kernels_links`) calls :func:`ci_update` in place of the plain Kalman
update for a fused link. :func:`fusion_state` builds the :class:`KernelFusion` of the
strategy's :attr:`~resloc.cl.fusion_methods.FusionStrategy.kernel_update`: its code, its
constants and working copies of the state it updates per link (split CI's independent
parts; the cross-covariance bookkeeping of ``tracked`` and ``factorized``,
:mod:`resloc.cl.kernels_joint`); :func:`fusion_commit` hands them back.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`ci_cost`               ``resloc.cl.fusion._posterior_cost``
:func:`grid_costs`            ``resloc.cl.fusion._posterior_cost`` on the grid
:func:`first_best`           ``np.argmin`` of the grid's costs
:func:`_search_weight`         :func:`resloc.cl.fusion.ci_weights` after the reductions
:func:`weight_of`             :func:`resloc.cl.fusion.ci_weights` from the reductions
:func:`ci_update`              :func:`resloc.cl.fusion.fused_update` (``ci``)
:func:`inflated_update`       :func:`resloc.cl.fusion.fused_update` after the weights
=============================  ==========================================================

``ci_update`` computes the 2 x 2 reductions of ``P_i`` and ``P_j`` once and uses them for
the weight and, times the inflation factors, for the update.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from resloc.cl.fusion import CI_GRID, CICriterion
from resloc.cl.kernels_joint import (
    FACTORIZED,
    TRACKED,
    KernelJoint,
    joint_commit,
    joint_state,
    kernel_scratch,
    no_joint,
)
from resloc.cl.kernels_math import chol2, jit, jit_inline, jit_lanes, solve2, wrap

__all__ = [
    "CI",
    "FACTORIZED_UPDATE",
    "KERNEL_UPDATES",
    "NAIVE_UPDATE",
    "SPLIT_CI",
    "TRACKED_UPDATE",
    "KernelFusion",
    "fusion_commit",
    "fusion_state",
    "kernel_fusion",
]

#: Codes of the link update in the kernel.
NAIVE_UPDATE = 0  # the filter's Kalman update (naive and gauge fusion)
CI = 1  # covariance intersection
SPLIT_CI = 2  # split covariance intersection
TRACKED_UPDATE = 3  # Kalman update under the tracked joint (resloc.cl.kernels_joint)
FACTORIZED_UPDATE = 4  # Kalman update under the factorized joint (resloc.cl.kernels_joint)
#: A strategy's ``kernel_update`` -> its code.
KERNEL_UPDATES = {
    "kalman": NAIVE_UPDATE,
    "ci": CI,
    "split_ci": SPLIT_CI,
    "tracked": TRACKED_UPDATE,
    "factorized": FACTORIZED_UPDATE,
}
_JOINT_CODES = {TRACKED_UPDATE: TRACKED, FACTORIZED_UPDATE: FACTORIZED}


class KernelFusion(NamedTuple):
    """The fusion method as the link loop takes it: its code, constants and the working
    copies of the state it updates per link (empty arrays when it keeps none)."""

    code: int  # a KERNEL_UPDATES code
    det: bool  # CI weight by the posterior determinant (else its trace)
    grid: np.ndarray  # (3, G) candidate CI weights w, 1 / w, 1 / (1 - w)
    joint: KernelJoint  # tracked / factorized: the cross-covariance bookkeeping
    independent: np.ndarray  # (B, 3, 3) split CI: the robots' independent parts
    P_nb_ind: np.ndarray  # (E, 3, 3) split CI: the transmitted independent parts
    work: np.ndarray  # (8, 3, 3) split CI: scratch
    costs: np.ndarray  # (G,) ci, split CI: scratch, the cost at each candidate weight


#: The candidate weights as the kernels take them, ``(3, G)``: the weights ``w``, ``1 / w``
#: and ``1 / (1 - w)`` (the same divisions as the reference's, done once, not per link).
_GRID = np.ascontiguousarray(np.stack([CI_GRID, 1.0 / CI_GRID, 1.0 / (1.0 - CI_GRID)]), dtype=float)
_NONE3 = np.zeros((0, 3, 3))


def kernel_fusion(code: int, criterion: CICriterion, E: int = 0) -> KernelFusion:
    """The kernel form of a fusion method with update ``code`` and CI ``criterion`` that
    keeps no per-link state."""
    return KernelFusion(
        int(code), CICriterion(criterion) is CICriterion.DET, _GRID, no_joint(E), _NONE3,
        _NONE3, np.zeros((8, 3, 3)), np.empty(_GRID.shape[1]),
    )  # fmt: skip


def fusion_state(update: str, criterion: CICriterion, memory, links, E: int):
    """The kernel form of the fusion method whose strategy declares ``kernel_update =
    update``, with working copies of its state in ``memory`` for the ``E`` links of
    ``links``; None when the kernel cannot reproduce the reference (then the reference
    raises its explanatory error, or records exactly)."""
    code = KERNEL_UPDATES[update]
    if code == SPLIT_CI:
        return _split_state(criterion, memory, links, E)
    if code in _JOINT_CODES:  # (built at once: kernel_fusion's then _replace cost ~1 us)
        joint = joint_state(_JOINT_CODES[code], memory, links.i, links.j)
        if joint is None:
            return None
        if criterion is not CICriterion.TRACE and criterion is not CICriterion.DET:
            criterion = CICriterion(criterion)
        scratch = kernel_scratch(memory.joint)  # (the joint's: no allocation a step)
        return KernelFusion(
            code, criterion is CICriterion.DET, _GRID, joint, _NONE3, _NONE3, scratch[2],
            scratch[3],
        )  # fmt: skip
    return kernel_fusion(code, criterion, E)


def _split_state(criterion: CICriterion, memory, links, E: int) -> KernelFusion | None:
    """:func:`fusion_state` of split CI: a working copy of ``memory.independent`` and the
    transmitted parts; None when a shape does not fit (the kernel does not check indices).
    Built at once, not as :func:`kernel_fusion`'s then ``_replace``; the copy and the
    observers' bound in one compiled call (:func:`_split_working_copy`), the criterion
    compared, not converted, when it is already a :class:`CICriterion` (measured,
    ``timeit``, 17 robots: 6.0 -> 2.7 -> ~1.3 us a step)."""
    independent = None if memory is None else memory.independent
    P_nb_ind = links.P_nb_ind
    if independent is None or P_nb_ind is None:
        return None
    if type(independent) is not np.ndarray or independent.dtype != _FLOAT:
        independent = np.array(independent, dtype=float)  # (the run's own is float64)
    if independent.shape[1:] != (3, 3) or np.shape(P_nb_ind) != (E, 3, 3):
        return None
    working = _split_working_copy(independent, np.asarray(links.i))
    if working.shape[0] == 0:  # an observer outside memory.independent
        return None
    if criterion is not CICriterion.TRACE and criterion is not CICriterion.DET:
        criterion = CICriterion(criterion)
    return KernelFusion(
        SPLIT_CI, criterion is CICriterion.DET, _GRID, no_joint(E), working,
        np.ascontiguousarray(P_nb_ind, dtype=float), np.zeros((8, 3, 3)),
        np.empty(_GRID.shape[1]),
    )  # fmt: skip


_FLOAT = np.dtype(float)


@jit
def _split_working_copy(independent, i):
    """A C-contiguous copy of ``independent: (B, 3, 3)`` when every observer ``i: (E,)`` is
    below ``B``, else an empty ``(0, 3, 3)`` array (the working copy of
    :func:`_split_state`; ``i``'s negative entries are refused before, by the link loop's
    checks)."""
    B = independent.shape[0]
    for e in range(i.shape[0]):
        if i[e] >= B:
            return np.empty((0, 3, 3))
    out = np.empty((B, 3, 3))
    out[:, :, :] = independent
    return out


def fusion_commit(fusion: KernelFusion, memory, i: np.ndarray, fused: np.ndarray) -> None:
    """Hand the kernel's records of a correction to the method's state in ``memory``
    (``i``: the links' observers, (E,) int64, ``fused``: (E,) bool, the kernel's own)."""
    code = fusion[0]  # (by position: a NamedTuple's field by name is a property call)
    if code == SPLIT_CI:
        memory.independent = fusion.independent
    elif code in _JOINT_CODES:
        joint_commit(fusion[3], memory, i, fused)


@jit_inline
def ci_cost(u, v, det, split, tr_i, det_i, a, ai, b, bi, g, gdi, gii, Dp, Ip, tr_ip, R):
    """Linearized posterior ``trace`` (or ``det``) of ``P_i`` under the CI joint bound with
    weight ``w`` given as ``u = 1 / w`` and ``v = 1 / (1 - w)`` (the grid's are computed
    once, :data:`_GRID`: one division per evaluation is left, that of ``S^-1``) from the
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
def _entries(M):
    """The nine entries of a 3 x 3 matrix by row, as a tuple."""
    return (
        M[0, 0], M[0, 1], M[0, 2], M[1, 0], M[1, 1], M[1, 2], M[2, 0], M[2, 1], M[2, 2],
    )  # fmt: skip


@jit_inline
def _det3_scaled(D, u, I3):
    """``det(D u + I3)`` of 3 x 3 matrices."""
    return det3_scaled_entries(_entries(D), u, _entries(I3))


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
    ``1 / w``, ``1 / (1 - w)``, :data:`_GRID`) into ``cost: (G,)``.
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
    :data:`_GRID`: a ``ci`` link's weight 119 -> 108 ns)."""
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
        grid, det, split, tr_i, det_i, a, ai, b, bi, g, gdi, gii, _entries(Di), _entries(Ii),
        tr_ip, (R[0, 0], R[0, 1], R[1, 0], R[1, 1]), prior, cost,
    )  # fmt: skip


@jit_inline
def ci_update(
    x, i, xi0, xi1, xi2, Pi, Pj, nu0, nu1, S00, S01, S11, Pxz, linearized, Hi, Hj,
    re00, re01, re11, R, fusion, jitter, K, A3, T3, Pn,
):  # fmt: skip
    """Covariance-intersection update of robot ``i`` from one link: writes ``x[i]`` and the
    unsymmetrized posterior into ``Pn`` (the prior where the link brings nothing); ``Hi``,
    ``Hj``: the range/bearing Jacobians at the means, ``(S, Pxz)``: the filter's moments
    under ``blockdiag(P_i, P_j)``, ``re``: its ``R_eff`` (EKF). Returns False when the
    inflated ``S`` has no Cholesky factor. Twin: :func:`resloc.cl.fusion.fused_update`."""
    # the reductions once, for the weight and the update (D_i = P_i, D_j = P_j)
    hph, ph = reduce_i(Pi, Hi)
    hpj = reduce_j(Pj, Hj)
    w = weight_of(hph, ph, hpj, Pi, Pi, Pj, False, Hi, Hj, R, fusion[1], fusion[2], fusion[7])
    if w >= 1.0:  # j adds nothing: the prior is kept
        for a in range(3):
            for b in range(3):
                Pn[a, b] = Pi[a, b]
        return True
    fi = 1.0 / w - 1.0
    fj = 1.0 / (1.0 - w) - 1.0
    d = (hph[0] * fi, hph[1] * fi, hph[2] * fi, hph[3] * fi)
    e = (hpj[0] * fj, hpj[1] * fj, hpj[2] * fj, hpj[3] * fj)
    c = (ph[0] * fi, ph[1] * fi, ph[2] * fi, ph[3] * fi, ph[4] * fi, ph[5] * fi)
    return inflated_update(
        x, i, xi0, xi1, xi2, Pi, Pi, fi, d, e, c, nu0, nu1, S00, S01, S11, Pxz, linearized,
        Hi, re00, re01, re11, jitter, K, A3, T3, Pn,
    )  # fmt: skip


@jit_inline
def inflated_update(
    x, i, xi0, xi1, xi2, Pi, Di, fi, d, e, c, nu0, nu1, S00, S01, S11, Pxz, linearized, Hi,
    re00, re01, re11, jitter, K, A3, T3, Pn,
):  # fmt: skip
    """The update with weight ``w < 1`` from the inflations' reductions, ``f_i = 1/w - 1``,
    ``d = H_i (f_i D_i) H_i^T``, ``e = H_j (f_j D_j) H_j^T`` (4-tuples ``00, 01, 10, 11``)
    and ``c``, the rows of ``f_i D_i H_i^T`` (a 6-tuple), with ``D`` the covariances
    (``ci``) or their dependent parts (split CI): :func:`ci_update` and
    :func:`resloc.cl.kernels_split.split_ci_update` pass their weight's reductions times
    ``f`` (the reference's products in another order: within an ulp; a ``ci`` link's update
    262 -> 217 ns with the weight's changes). Writes ``x[i]``, ``K``, the prior ``A3 =
    sym(P_i + f_i D_i)`` and the unsymmetrized posterior ``Pn``; False when the inflated
    ``S`` has no Cholesky factor. (At most 30 arguments: CPython passes more as ``*args``,
    which numba's inliner refuses.) Twin: :func:`resloc.cl.fusion.fused_update` (after the
    weights)."""
    d00, d01, d10, d11 = d
    e00, e01, e10, e11 = e
    c00, c01, c10, c11, c20, c21 = c
    # A = sym(P_i + f_i D_i)
    for a in range(3):
        for b in range(3):
            A3[a, b] = 0.5 * ((Pi[a, b] + Di[a, b] * fi) + (Pi[b, a] + Di[b, a] * fi))
    s00 = S00 + d00 + e00
    s11 = S11 + d11 + e11
    s01 = 0.5 * ((S01 + d01 + e01) + (S01 + d10 + e10))
    l00, l10, l11 = chol2(s00, s01, s11, jitter)
    if l00 == 0.0:
        return False
    Pxz[0, 0] += c00  # P^xz + f_i D_i H_i^T, then K by the Cholesky factor of S
    Pxz[0, 1] += c01
    Pxz[1, 0] += c10
    Pxz[1, 1] += c11
    Pxz[2, 0] += c20
    Pxz[2, 1] += c21
    for a in range(3):
        k0, k1 = solve2(l00, l10, l11, Pxz[a, 0], Pxz[a, 1])
        K[a, 0] = k0
        K[a, 1] = k1
    x[i, 0] = xi0 + (K[0, 0] * nu0 + K[0, 1] * nu1)
    x[i, 1] = xi1 + (K[1, 0] * nu0 + K[1, 1] * nu1)
    x[i, 2] = wrap(xi2 + (K[2, 0] * nu0 + K[2, 1] * nu1))
    if linearized:
        # Joseph form (I - K H_i) A (I - K H_i)^T + K (R_eff + extra_j) K^T
        r00 = re00 + e00
        r01 = re01 + e01
        r10 = re01 + e10
        r11 = re11 + e11
        for a in range(3):
            for b in range(3):
                T3[a, b] = (1.0 if a == b else 0.0) - (K[a, 0] * Hi[0, b] + K[a, 1] * Hi[1, b])
        for a in range(3):
            t0 = K[a, 0] * r00 + K[a, 1] * r10
            t1 = K[a, 0] * r01 + K[a, 1] * r11
            for b in range(3):
                s = 0.0
                for c in range(3):
                    m = 0.0
                    for d in range(3):
                        m += T3[a, d] * A3[d, c]
                    s += m * T3[b, c]
                Pn[a, b] = s + (t0 * K[b, 0] + t1 * K[b, 1])
    else:
        for a in range(3):  # A - K S K^T
            t0 = K[a, 0] * s00 + K[a, 1] * s01
            t1 = K[a, 0] * s01 + K[a, 1] * s11
            for b in range(3):
                Pn[a, b] = A3[a, b] - (t0 * K[b, 0] + t1 * K[b, 1])
    return True
