"""Compiled twins of the fusion methods that change the update itself: ``ci``.

Covariance intersection (:func:`resloc.cl.fusion.fused_update` with ``ci``) uses the joint
bound ``blockdiag(P_i / w, P_j / (1 - w))``: the weight ``w`` of each link minimises the
linearized posterior size (:func:`resloc.cl.fusion.ci_weights`: a grid, one parabolic
refinement, kept only where it helps, and ``w = 1``, "ignore j", when no weight beats the
prior), then the filter's own moments are extended by the inflations through the
range/bearing Jacobians at the means. The CL link loop (:mod:`resloc.cl.kernels_links`)
calls :func:`ci_update` in place of the plain Kalman update for a fused link;
:class:`KernelFusion` carries the method's code and constants, chosen from the strategy
(:attr:`FusionStrategy.kernel_code <resloc.cl.fusion_methods.FusionStrategy.kernel_code>`).

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`_ci_cost`               ``resloc.cl.fusion._posterior_cost`` (``ci``: no
                               independent parts)
:func:`_ci_weight`             :func:`resloc.cl.fusion.ci_weights`
:func:`ci_update`              :func:`resloc.cl.fusion.fused_update` (``ci``)
=============================  ==========================================================
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from resloc.cl.fusion import CI_GRID, CICriterion
from resloc.cl.kernels_math import chol2, jit_inline, solve2, wrap

__all__ = ["CI", "KERNEL_UPDATES", "NAIVE_UPDATE", "KernelFusion", "kernel_fusion"]

#: Codes of the link update in the kernel.
NAIVE_UPDATE = 0  # the filter's Kalman update (naive and gauge fusion)
CI = 1  # covariance intersection
#: A strategy's ``kernel_update`` -> its code.
KERNEL_UPDATES = {"kalman": NAIVE_UPDATE, "ci": CI}


class KernelFusion(NamedTuple):
    """The fusion method as the link loop takes it."""

    code: int  # NAIVE_UPDATE or CI
    det: bool  # CI weight by the posterior determinant (else its trace)
    grid: np.ndarray  # (G,) candidate CI weights


_GRID = np.ascontiguousarray(CI_GRID, dtype=float)


def kernel_fusion(code: int, criterion: CICriterion) -> KernelFusion:
    """The kernel form of a fusion method with update ``code`` and CI ``criterion``."""
    return KernelFusion(int(code), CICriterion(criterion) is CICriterion.DET, _GRID)


@jit_inline
def _ci_cost(w, det, tr_i, det_i, a00, a01, a10, a11, b00, b01, b10, b11, g00, g01, g10, g11, R):
    """Linearized posterior ``trace`` (or ``det``) of ``P_i`` under the CI joint bound with
    weight ``w`` from the link's 2 x 2 reductions: ``a = H_i P_i H_i^T``, ``b = H_j P_j
    H_j^T``, ``g = C^T C`` with ``C = P_i H_i^T`` (``tr_i``, ``det_i``: of ``P_i``).
    Twin: ``resloc.cl.fusion._posterior_cost`` without independent parts."""
    u = 1.0 / w
    v = 1.0 / (1.0 - w)
    sj00 = b00 * v + R[0, 0]
    sj01 = b01 * v + R[0, 1]
    sj10 = b10 * v + R[1, 0]
    sj11 = b11 * v + R[1, 1]
    s00 = a00 * u + sj00
    s01 = a01 * u + sj01
    s10 = a10 * u + sj10
    s11 = a11 * u + sj11
    det_s = s00 * s11 - s01 * s10
    if det:
        return det_i * u * u * u * (sj00 * sj11 - sj01 * sj10) / det_s
    q00 = g00 * u * u
    q01 = g01 * u * u
    q10 = g10 * u * u
    q11 = g11 * u * u
    tr_gsinv = (q00 * s11 + q11 * s00 - q01 * s10 - q10 * s01) / det_s
    return tr_i / w - tr_gsinv


@jit_inline
def _ci_weight(Pi, Pj, Hi, Hj, R, det, grid):
    """The CI weight of one link (1.0: no weight makes the posterior smaller than the prior).
    Twin: :func:`resloc.cl.fusion.ci_weights`."""
    # C = P_i H_i^T (3 x 2), reduced to a = H_i C and g = C^T C
    a00 = a01 = a10 = a11 = 0.0
    g00 = g01 = g10 = g11 = 0.0
    for r in range(3):
        c0 = 0.0
        c1 = 0.0
        for k in range(3):
            c0 += Pi[r, k] * Hi[0, k]
            c1 += Pi[r, k] * Hi[1, k]
        a00 += Hi[0, r] * c0
        a01 += Hi[0, r] * c1
        a10 += Hi[1, r] * c0
        a11 += Hi[1, r] * c1
        g00 += c0 * c0
        g01 += c0 * c1
        g10 += c1 * c0
        g11 += c1 * c1
    b00 = b01 = b10 = b11 = 0.0  # b = (H_j P_j) H_j^T
    for k in range(3):
        t0 = 0.0
        t1 = 0.0
        for c in range(3):
            t0 += Hj[0, c] * Pj[c, k]
            t1 += Hj[1, c] * Pj[c, k]
        b00 += t0 * Hj[0, k]
        b01 += t0 * Hj[1, k]
        b10 += t1 * Hj[0, k]
        b11 += t1 * Hj[1, k]
    tr_i = Pi[0, 0] + Pi[1, 1] + Pi[2, 2]
    det_i = (
        Pi[0, 0] * (Pi[1, 1] * Pi[2, 2] - Pi[1, 2] * Pi[2, 1])
        - Pi[0, 1] * (Pi[1, 0] * Pi[2, 2] - Pi[1, 2] * Pi[2, 0])
        + Pi[0, 2] * (Pi[1, 0] * Pi[2, 1] - Pi[1, 1] * Pi[2, 0])
    )
    n = grid.shape[0]
    best = np.inf
    k = 0
    for t in range(n):
        cost = _ci_cost(
            grid[t], det, tr_i, det_i, a00, a01, a10, a11, b00, b01, b10, b11,
            g00, g01, g10, g11, R,
        )  # fmt: skip
        if cost < best or (t == 0 and not cost >= best):
            best = cost
            k = t
    kc = min(max(k, 1), n - 2)
    c0 = _ci_cost(grid[kc - 1], det, tr_i, det_i, a00, a01, a10, a11, b00, b01, b10, b11,
                  g00, g01, g10, g11, R)  # fmt: skip
    c1 = _ci_cost(grid[kc], det, tr_i, det_i, a00, a01, a10, a11, b00, b01, b10, b11,
                  g00, g01, g10, g11, R)  # fmt: skip
    c2 = _ci_cost(grid[kc + 1], det, tr_i, det_i, a00, a01, a10, a11, b00, b01, b10, b11,
                  g00, g01, g10, g11, R)  # fmt: skip
    h = grid[1] - grid[0]
    denom = c0 - 2.0 * c1 + c2
    shift = 0.5 * h * (c0 - c2) / denom if denom > 0.0 else 0.0
    if k == kc:
        shift = min(max(shift, -h), h)
        w = min(max(grid[kc] + shift, grid[0]), grid[n - 1])
    else:
        w = grid[k]
    refined = _ci_cost(w, det, tr_i, det_i, a00, a01, a10, a11, b00, b01, b10, b11,
                       g00, g01, g10, g11, R)  # fmt: skip
    if refined <= best:
        best = refined
    else:
        w = grid[k]
    prior = det_i if det else tr_i
    return w if best < prior else 1.0


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
    w = _ci_weight(Pi, Pj, Hi, Hj, R, fusion[1], fusion[2])
    if w >= 1.0:  # j adds nothing: the prior is kept
        for a in range(3):
            for b in range(3):
                Pn[a, b] = Pi[a, b]
        return True
    fi = 1.0 / w - 1.0
    fj = 1.0 / (1.0 - w) - 1.0
    # A = sym(P_i + D_i), D_i = f_i P_i; extra_j = H_j D_j H_j^T; H_i D_i H_i^T
    for a in range(3):
        for b in range(3):
            A3[a, b] = 0.5 * ((Pi[a, b] + Pi[a, b] * fi) + (Pi[b, a] + Pi[b, a] * fi))
    e00 = e01 = e10 = e11 = 0.0
    d00 = d01 = d10 = d11 = 0.0
    for k in range(3):
        t0 = 0.0
        t1 = 0.0
        u0 = 0.0
        u1 = 0.0
        for c in range(3):
            t0 += Hj[0, c] * (Pj[c, k] * fj)
            t1 += Hj[1, c] * (Pj[c, k] * fj)
            u0 += Hi[0, c] * (Pi[c, k] * fi)
            u1 += Hi[1, c] * (Pi[c, k] * fi)
        e00 += t0 * Hj[0, k]
        e01 += t0 * Hj[1, k]
        e10 += t1 * Hj[0, k]
        e11 += t1 * Hj[1, k]
        d00 += u0 * Hi[0, k]
        d01 += u0 * Hi[1, k]
        d10 += u1 * Hi[0, k]
        d11 += u1 * Hi[1, k]
    s00 = S00 + d00 + e00
    s11 = S11 + d11 + e11
    s01 = 0.5 * ((S01 + d01 + e01) + (S01 + d10 + e10))
    l00, l10, l11 = chol2(s00, s01, s11, jitter)
    if l00 == 0.0:
        return False
    for a in range(3):  # P^xz + D_i H_i^T, then K by the Cholesky factor of S
        p0 = 0.0
        p1 = 0.0
        for c in range(3):
            p0 += (Pi[a, c] * fi) * Hi[0, c]
            p1 += (Pi[a, c] * fi) * Hi[1, c]
        k0, k1 = solve2(l00, l10, l11, Pxz[a, 0] + p0, Pxz[a, 1] + p1)
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
