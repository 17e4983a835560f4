"""Compiled covariance-intersection update (``ci`` fusion) of one link: the weight
(:func:`resloc.cl.kernels_ci_weight.weight_of`), then the filter's own moments extended
by the inflations through the range/bearing Jacobians at the means
(:func:`inflated_update`, which split CI shares for its dependent parts,
:mod:`resloc.cl.kernels_split`). The CL link loop (:mod:`resloc.cl.kernels_links`) calls
:func:`ci_update` in place of the plain Kalman update for a fused link.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`ci_update`              :func:`resloc.cl.fusion.fused_update` (``ci``)
:func:`inflated_update`       :func:`resloc.cl.fusion.fused_update` after the weights
=============================  ==========================================================

``ci_update`` computes the 2 x 2 reductions of ``P_i`` and ``P_j`` once and uses them for
the weight and, times the inflation factors, for the update.
"""

from __future__ import annotations

from resloc.cl.kernels_ci_weight import reduce_i, reduce_j, weight_of
from resloc.cl.kernels_math import chol2, jit_inline, solve2, wrap

__all__ = ["ci_update", "inflated_update"]


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
