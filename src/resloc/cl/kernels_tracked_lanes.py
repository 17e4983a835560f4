"""``tracked``'s lane stages in the joints' rounds (:mod:`resloc.cl.kernels_joint_rounds`):
the blocks of every lane and their 6 x 6 joint (:func:`tracked_cross_lanes`) and the record
of every fused lane (:func:`tracked_record_lanes`), the arithmetic over lanes in loops that
compile to SIMD, on arrays of :data:`~resloc.cl.kernels_joint_lanes.LANE_STRIDE` columns.
Each is the scalar pieces' (:mod:`resloc.cl.kernels_joint_links`,
:mod:`resloc.cl.kernels_joint_records`) to the bit and names them.
"""

from __future__ import annotations

import math

from resloc.cl import kernels_joint_links as _kernels_joint_links
from resloc.cl import kernels_round_cached as _kernels_round_cached
from resloc.cl.kernels_joint_lanes import LANE_STRIDE
from resloc.cl.kernels_joint_records import update_m_sigma_rows
from resloc.cl.kernels_lanes import CHUNK
from resloc.cl.kernels_math import jit_lanes, stamp_with_pieces, store_covariance
from resloc.cl.kernels_round_cached import padded_lanes
from resloc.models.measurement import MIN_RANGE

_jit = jit_lanes

__all__ = [
    "RECORD_INPUT_ROWS",
    "RECORD_OUTPUT_ROWS",
    "tracked_cross_lanes",
    "tracked_record_lanes",
]


@_jit
def tracked_cross_lanes(joint, lane_e, lane_first, obs, n, now, blocks, J):
    """``tracked``'s blocks of every lane: robot i's covariance now (``Sigma_ii``
    symmetrized at its first link, then ``now[i]``, kept there), ``C_ij`` from i's rows of
    ``M Sigma`` and ``Sigma_jj``, gathered into ``blocks: (27, LANE_STRIDE)``, then the
    lower triangle of their symmetrized joint into ``J: (21, LANE_STRIDE)`` in a loop over
    lanes that compiles to SIMD (:func:`_joint_of_lanes`). Twin, to the bit:
    :func:`~resloc.cl.kernels_joint_links.tracked_cross` and ``_joint_into_lane`` of
    :mod:`resloc.cl.kernels_joint_rounds`, lane by lane."""
    N = joint[1]
    nbr = joint[2]
    sigma = joint[3]
    rows = joint[14]
    for c in range(n):
        e = lane_e[c]
        i = obs[c]
        j = nbr[e]
        t = i // N
        if e == lane_first[c]:  # Sigma_ii at i's first link
            c0 = 3 * (i % N)
            for a in range(3):
                for b in range(3):
                    now[i, a, b] = 0.5 * (sigma[t, c0 + a, c0 + b] + sigma[t, c0 + b, c0 + a])
        cj = 3 * (j % N)
        tj = j // N
        for a in range(3):
            for b in range(3):
                blocks[3 * a + b, c] = now[i, a, b]
                blocks[9 + 3 * a + b, c] = rows[i, a, cj + b]
                blocks[18 + 3 * a + b, c] = sigma[tj, cj + a, cj + b]
    _joint_of_lanes(padded_lanes(n, CHUNK), blocks, J)  # (lanes from n: never read)


@_jit
def _joint_of_lanes(n, blocks, J):
    """The lower triangle of ``sym([[P_i, C], [C^T, P_j]])`` of lanes ``0 .. n - 1`` from
    their blocks (``joint6``'s entries, ``chol6_lanes``' layout), through flat views."""
    bf = blocks.reshape(blocks.size)
    Jf = J.reshape(J.size)
    for c in range(n):
        pi00 = bf[c]
        pi01 = bf[1 * LANE_STRIDE + c]
        pi02 = bf[2 * LANE_STRIDE + c]
        pi10 = bf[3 * LANE_STRIDE + c]
        pi11 = bf[4 * LANE_STRIDE + c]
        pi12 = bf[5 * LANE_STRIDE + c]
        pi20 = bf[6 * LANE_STRIDE + c]
        pi21 = bf[7 * LANE_STRIDE + c]
        pi22 = bf[8 * LANE_STRIDE + c]
        pj00 = bf[18 * LANE_STRIDE + c]
        pj01 = bf[19 * LANE_STRIDE + c]
        pj02 = bf[20 * LANE_STRIDE + c]
        pj10 = bf[21 * LANE_STRIDE + c]
        pj11 = bf[22 * LANE_STRIDE + c]
        pj12 = bf[23 * LANE_STRIDE + c]
        pj20 = bf[24 * LANE_STRIDE + c]
        pj21 = bf[25 * LANE_STRIDE + c]
        pj22 = bf[26 * LANE_STRIDE + c]
        Jf[c] = 0.5 * (pi00 + pi00)
        Jf[1 * LANE_STRIDE + c] = 0.5 * (pi10 + pi01)
        Jf[2 * LANE_STRIDE + c] = 0.5 * (pi11 + pi11)
        Jf[3 * LANE_STRIDE + c] = 0.5 * (pi20 + pi02)
        Jf[4 * LANE_STRIDE + c] = 0.5 * (pi21 + pi12)
        Jf[5 * LANE_STRIDE + c] = 0.5 * (pi22 + pi22)
        Jf[6 * LANE_STRIDE + c] = bf[9 * LANE_STRIDE + c]  # C[0, 0]
        Jf[7 * LANE_STRIDE + c] = bf[12 * LANE_STRIDE + c]  # C[1, 0]
        Jf[8 * LANE_STRIDE + c] = bf[15 * LANE_STRIDE + c]  # C[2, 0]
        Jf[9 * LANE_STRIDE + c] = 0.5 * (pj00 + pj00)
        Jf[10 * LANE_STRIDE + c] = bf[10 * LANE_STRIDE + c]  # C[0, 1]
        Jf[11 * LANE_STRIDE + c] = bf[13 * LANE_STRIDE + c]  # C[1, 1]
        Jf[12 * LANE_STRIDE + c] = bf[16 * LANE_STRIDE + c]  # C[2, 1]
        Jf[13 * LANE_STRIDE + c] = 0.5 * (pj10 + pj01)
        Jf[14 * LANE_STRIDE + c] = 0.5 * (pj11 + pj11)
        Jf[15 * LANE_STRIDE + c] = bf[11 * LANE_STRIDE + c]  # C[0, 2]
        Jf[16 * LANE_STRIDE + c] = bf[14 * LANE_STRIDE + c]  # C[1, 2]
        Jf[17 * LANE_STRIDE + c] = bf[17 * LANE_STRIDE + c]  # C[2, 2]
        Jf[18 * LANE_STRIDE + c] = 0.5 * (pj20 + pj02)
        Jf[19 * LANE_STRIDE + c] = 0.5 * (pj21 + pj12)
        Jf[20 * LANE_STRIDE + c] = 0.5 * (pj22 + pj22)


#: The squared range below which the Jacobians take the minimum range (as
#: ``range_bearing_jacobians_into``'s).
_MIN_R2 = MIN_RANGE**2

#: Rows of :func:`tracked_record_lanes`' gathered inputs: the gain ``K`` (by row), i's and
#: j's positions, the link's blocks ``P_i``, ``C_ij``, ``P_j``, robot i's ``A_i`` and noise.
RECORD_INPUT_ROWS = 55
#: Rows of its results: ``G = I - K H_i``, ``G A_i``, ``B_ij = -K H_j``, the noise after
#: the update and robot i's covariance after it (9 each, by row).
RECORD_OUTPUT_ROWS = 45


@_jit
def tracked_record_lanes(
    joint, P, lane_e, obs, n, xi, xr, update, decision, R, flags, now, blocks, lanes, rin,
    rout, G, Pn, T3,
):  # fmt: skip
    """``tracked``'s record of every fused lane of a round (``decision[3, c] == 1``) with
    the arithmetic over lanes: the fused lanes' inputs gathered into ``rin:
    (RECORD_INPUT_ROWS, LANE_STRIDE)`` (lanes up to the padded count copies of the first,
    never read), then the Jacobians, ``G``, ``G A_i``, ``B_ij``, the noise and i's
    covariance after the update in one branch-free loop over lanes that compiles to SIMD
    (:func:`_record_of_lanes`, into ``rout: (RECORD_OUTPUT_ROWS, LANE_STRIDE)``), then per
    fused lane what the loop cannot do: the results into the joint's working copies, ``G``
    into the link's gain (``joint[13]``), i's rows of ``M Sigma`` left-multiplied by ``G``
    (:func:`~resloc.cl.kernels_joint_records.update_m_sigma_rows`), ``P[i]`` (repaired
    where not positive definite, ``flags[4]``) and ``now[i]``. ``lanes: (CHUNK,)``, ``G``,
    ``Pn``, ``T3`` (3 x 3): scratch. Returns the number of fused lanes. The same operations
    in the same order as the scalar record it replaces (the ``tracked`` branch of
    :func:`resloc.cl.kernels_joint_rounds.joint_record_lanes`, ``tracked_record``): the
    same values to the bit. Neither multiplies i's earlier fused ``B`` rows by ``G``: the
    commit does (:func:`~resloc.cl.kernels_tracked_step.apply_later_gains`, two products a
    link; the walk over every earlier link of the robot per record cost ~5 us a step)."""
    noise = joint[4]
    A = joint[5]
    Bij = joint[6]
    gains = joint[13]
    nf = 0
    for c in range(n):
        if decision[3, c] == 1.0:
            lanes[nf] = c
            nf += 1
    if nf == 0:
        return 0
    n2 = padded_lanes(nf, CHUNK)
    for k in range(n2):
        c = lanes[k if k < nf else 0]
        i = obs[c]
        for a in range(3):
            rin[2 * a, k] = update[16 + 2 * a, c]
            rin[2 * a + 1, k] = update[17 + 2 * a, c]
        rin[6, k] = xi[0, c]
        rin[7, k] = xi[1, c]
        rin[8, k] = xr[0, c]
        rin[9, k] = xr[1, c]
        for r in range(27):
            rin[10 + r, k] = blocks[r, c]
        for a in range(3):
            for b in range(3):
                rin[37 + 3 * a + b, k] = A[i, a, b]
                rin[46 + 3 * a + b, k] = noise[i, a, b]
    _record_of_lanes(n2, rin, rout, R[0, 0], R[0, 1], R[1, 0], R[1, 1])
    N = joint[1]
    nbr = joint[2]
    sigma = joint[3]
    rows = joint[14]
    for k in range(nf):
        c = lanes[k]
        e = lane_e[c]
        i = obs[c]
        for a in range(3):
            for b in range(3):
                r = 3 * a + b
                G[a, b] = rout[r, k]
                A[i, a, b] = rout[9 + r, k]
                Bij[e, a, b] = rout[18 + r, k]
                gains[e, a, b] = rout[r, k]
                noise[i, a, b] = rout[27 + r, k]
                Pn[a, b] = rout[36 + r, k]
                now[i, a, b] = rout[36 + r, k]
        update_m_sigma_rows(rows, sigma, i, i // N, 3 * (nbr[e] % N), G, Bij, e)
        flags[4, e] = store_covariance(P, i, Pn, T3)
    return nf


@_jit
def _record_of_lanes(n, rin, rout, r00, r01, r10, r11):
    """The arithmetic of :func:`tracked_record_lanes` on lanes ``0 .. n - 1``, scalars
    only (``R`` as four), through flat views of the arrays (:data:`LANE_STRIDE` columns):
    ``range_bearing_jacobians_into``, ``G = I - K H_i``, ``G A_i``, ``B_ij = -K H_j``, ``G
    N_i G^T + K R K^T`` and ``_tracked_update`` (symmetrized) of
    :mod:`resloc.cl.kernels_joint_records`, each sum in their order."""
    f = rin.reshape(rin.size)
    o = rout.reshape(rout.size)
    for c in range(n):
        k00 = f[c]
        k01 = f[1 * LANE_STRIDE + c]
        k10 = f[2 * LANE_STRIDE + c]
        k11 = f[3 * LANE_STRIDE + c]
        k20 = f[4 * LANE_STRIDE + c]
        k21 = f[5 * LANE_STRIDE + c]
        xi0 = f[6 * LANE_STRIDE + c]
        xi1 = f[7 * LANE_STRIDE + c]
        xj0 = f[8 * LANE_STRIDE + c]
        xj1 = f[9 * LANE_STRIDE + c]
        p00 = f[10 * LANE_STRIDE + c]
        p01 = f[11 * LANE_STRIDE + c]
        p02 = f[12 * LANE_STRIDE + c]
        p10 = f[13 * LANE_STRIDE + c]
        p11 = f[14 * LANE_STRIDE + c]
        p12 = f[15 * LANE_STRIDE + c]
        p20 = f[16 * LANE_STRIDE + c]
        p21 = f[17 * LANE_STRIDE + c]
        p22 = f[18 * LANE_STRIDE + c]
        c00 = f[19 * LANE_STRIDE + c]
        c01 = f[20 * LANE_STRIDE + c]
        c02 = f[21 * LANE_STRIDE + c]
        c10 = f[22 * LANE_STRIDE + c]
        c11 = f[23 * LANE_STRIDE + c]
        c12 = f[24 * LANE_STRIDE + c]
        c20 = f[25 * LANE_STRIDE + c]
        c21 = f[26 * LANE_STRIDE + c]
        c22 = f[27 * LANE_STRIDE + c]
        q00 = f[28 * LANE_STRIDE + c]
        q01 = f[29 * LANE_STRIDE + c]
        q02 = f[30 * LANE_STRIDE + c]
        q10 = f[31 * LANE_STRIDE + c]
        q11 = f[32 * LANE_STRIDE + c]
        q12 = f[33 * LANE_STRIDE + c]
        q20 = f[34 * LANE_STRIDE + c]
        q21 = f[35 * LANE_STRIDE + c]
        q22 = f[36 * LANE_STRIDE + c]
        a00 = f[37 * LANE_STRIDE + c]
        a01 = f[38 * LANE_STRIDE + c]
        a02 = f[39 * LANE_STRIDE + c]
        a10 = f[40 * LANE_STRIDE + c]
        a11 = f[41 * LANE_STRIDE + c]
        a12 = f[42 * LANE_STRIDE + c]
        a20 = f[43 * LANE_STRIDE + c]
        a21 = f[44 * LANE_STRIDE + c]
        a22 = f[45 * LANE_STRIDE + c]
        n00 = f[46 * LANE_STRIDE + c]
        n01 = f[47 * LANE_STRIDE + c]
        n02 = f[48 * LANE_STRIDE + c]
        n10 = f[49 * LANE_STRIDE + c]
        n11 = f[50 * LANE_STRIDE + c]
        n12 = f[51 * LANE_STRIDE + c]
        n20 = f[52 * LANE_STRIDE + c]
        n21 = f[53 * LANE_STRIDE + c]
        n22 = f[54 * LANE_STRIDE + c]
        dx = xj0 - xi0
        dy = xj1 - xi1
        qq = dx * dx + dy * dy
        qq = _MIN_R2 if qq < _MIN_R2 else qq
        r = math.sqrt(qq)
        hj00 = dx / r
        hj01 = dy / r
        hj02 = 0.0
        hj10 = -dy / qq
        hj11 = dx / qq
        hj12 = 0.0
        hi00 = -hj00
        hi01 = -hj01
        hi02 = -hj02
        hi10 = -hj10
        hi11 = -hj11
        hi12 = -hj12
        hi12 = -1.0
        g00 = 1.0 - (k00 * hi00 + k01 * hi10)
        g01 = 0.0 - (k00 * hi01 + k01 * hi11)
        g02 = 0.0 - (k00 * hi02 + k01 * hi12)
        g10 = 0.0 - (k10 * hi00 + k11 * hi10)
        g11 = 1.0 - (k10 * hi01 + k11 * hi11)
        g12 = 0.0 - (k10 * hi02 + k11 * hi12)
        g20 = 0.0 - (k20 * hi00 + k21 * hi10)
        g21 = 0.0 - (k20 * hi01 + k21 * hi11)
        g22 = 1.0 - (k20 * hi02 + k21 * hi12)
        na00 = g00 * a00 + g01 * a10 + g02 * a20
        na01 = g00 * a01 + g01 * a11 + g02 * a21
        na02 = g00 * a02 + g01 * a12 + g02 * a22
        na10 = g10 * a00 + g11 * a10 + g12 * a20
        na11 = g10 * a01 + g11 * a11 + g12 * a21
        na12 = g10 * a02 + g11 * a12 + g12 * a22
        na20 = g20 * a00 + g21 * a10 + g22 * a20
        na21 = g20 * a01 + g21 * a11 + g22 * a21
        na22 = g20 * a02 + g21 * a12 + g22 * a22
        b00 = -(k00 * hj00 + k01 * hj10)
        b01 = -(k00 * hj01 + k01 * hj11)
        b02 = -(k00 * hj02 + k01 * hj12)
        b10 = -(k10 * hj00 + k11 * hj10)
        b11 = -(k10 * hj01 + k11 * hj11)
        b12 = -(k10 * hj02 + k11 * hj12)
        b20 = -(k20 * hj00 + k21 * hj10)
        b21 = -(k20 * hj01 + k21 * hj11)
        b22 = -(k20 * hj02 + k21 * hj12)
        t00 = g00 * n00 + g01 * n10 + g02 * n20
        t01 = g00 * n01 + g01 * n11 + g02 * n21
        t02 = g00 * n02 + g01 * n12 + g02 * n22
        t10 = g10 * n00 + g11 * n10 + g12 * n20
        t11 = g10 * n01 + g11 * n11 + g12 * n21
        t12 = g10 * n02 + g11 * n12 + g12 * n22
        t20 = g20 * n00 + g21 * n10 + g22 * n20
        t21 = g20 * n01 + g21 * n11 + g22 * n21
        t22 = g20 * n02 + g21 * n12 + g22 * n22
        u00 = k00 * r00 + k01 * r10
        u01 = k00 * r01 + k01 * r11
        u10 = k10 * r00 + k11 * r10
        u11 = k10 * r01 + k11 * r11
        u20 = k20 * r00 + k21 * r10
        u21 = k20 * r01 + k21 * r11
        nn00 = (((0.0 + t00 * g00) + t01 * g01) + t02 * g02) + (u00 * k00 + u01 * k01)
        nn01 = (((0.0 + t00 * g10) + t01 * g11) + t02 * g12) + (u00 * k10 + u01 * k11)
        nn02 = (((0.0 + t00 * g20) + t01 * g21) + t02 * g22) + (u00 * k20 + u01 * k21)
        nn10 = (((0.0 + t10 * g00) + t11 * g01) + t12 * g02) + (u10 * k00 + u11 * k01)
        nn11 = (((0.0 + t10 * g10) + t11 * g11) + t12 * g12) + (u10 * k10 + u11 * k11)
        nn12 = (((0.0 + t10 * g20) + t11 * g21) + t12 * g22) + (u10 * k20 + u11 * k21)
        nn20 = (((0.0 + t20 * g00) + t21 * g01) + t22 * g02) + (u20 * k00 + u21 * k01)
        nn21 = (((0.0 + t20 * g10) + t21 * g11) + t22 * g12) + (u20 * k10 + u21 * k11)
        nn22 = (((0.0 + t20 * g20) + t21 * g21) + t22 * g22) + (u20 * k20 + u21 * k21)
        v00 = (g00 * p00 + g01 * p10 + g02 * p20) + (b00 * c00 + b01 * c01 + b02 * c02)
        s00 = (g00 * c00 + g01 * c10 + g02 * c20) + (b00 * q00 + b01 * q10 + b02 * q20)
        v01 = (g00 * p01 + g01 * p11 + g02 * p21) + (b00 * c10 + b01 * c11 + b02 * c12)
        s01 = (g00 * c01 + g01 * c11 + g02 * c21) + (b00 * q01 + b01 * q11 + b02 * q21)
        v02 = (g00 * p02 + g01 * p12 + g02 * p22) + (b00 * c20 + b01 * c21 + b02 * c22)
        s02 = (g00 * c02 + g01 * c12 + g02 * c22) + (b00 * q02 + b01 * q12 + b02 * q22)
        v10 = (g10 * p00 + g11 * p10 + g12 * p20) + (b10 * c00 + b11 * c01 + b12 * c02)
        s10 = (g10 * c00 + g11 * c10 + g12 * c20) + (b10 * q00 + b11 * q10 + b12 * q20)
        v11 = (g10 * p01 + g11 * p11 + g12 * p21) + (b10 * c10 + b11 * c11 + b12 * c12)
        s11 = (g10 * c01 + g11 * c11 + g12 * c21) + (b10 * q01 + b11 * q11 + b12 * q21)
        v12 = (g10 * p02 + g11 * p12 + g12 * p22) + (b10 * c20 + b11 * c21 + b12 * c22)
        s12 = (g10 * c02 + g11 * c12 + g12 * c22) + (b10 * q02 + b11 * q12 + b12 * q22)
        v20 = (g20 * p00 + g21 * p10 + g22 * p20) + (b20 * c00 + b21 * c01 + b22 * c02)
        s20 = (g20 * c00 + g21 * c10 + g22 * c20) + (b20 * q00 + b21 * q10 + b22 * q20)
        v21 = (g20 * p01 + g21 * p11 + g22 * p21) + (b20 * c10 + b21 * c11 + b22 * c12)
        s21 = (g20 * c01 + g21 * c11 + g22 * c21) + (b20 * q01 + b21 * q11 + b22 * q21)
        v22 = (g20 * p02 + g21 * p12 + g22 * p22) + (b20 * c20 + b21 * c21 + b22 * c22)
        s22 = (g20 * c02 + g21 * c12 + g22 * c22) + (b20 * q02 + b21 * q12 + b22 * q22)
        m00 = ((v00 * g00 + v01 * g01 + v02 * g02) + (s00 * b00 + s01 * b01 + s02 * b02)) + (
            u00 * k00 + u01 * k01
        )
        m01 = ((v00 * g10 + v01 * g11 + v02 * g12) + (s00 * b10 + s01 * b11 + s02 * b12)) + (
            u00 * k10 + u01 * k11
        )
        m02 = ((v00 * g20 + v01 * g21 + v02 * g22) + (s00 * b20 + s01 * b21 + s02 * b22)) + (
            u00 * k20 + u01 * k21
        )
        m10 = ((v10 * g00 + v11 * g01 + v12 * g02) + (s10 * b00 + s11 * b01 + s12 * b02)) + (
            u10 * k00 + u11 * k01
        )
        m11 = ((v10 * g10 + v11 * g11 + v12 * g12) + (s10 * b10 + s11 * b11 + s12 * b12)) + (
            u10 * k10 + u11 * k11
        )
        m12 = ((v10 * g20 + v11 * g21 + v12 * g22) + (s10 * b20 + s11 * b21 + s12 * b22)) + (
            u10 * k20 + u11 * k21
        )
        m20 = ((v20 * g00 + v21 * g01 + v22 * g02) + (s20 * b00 + s21 * b01 + s22 * b02)) + (
            u20 * k00 + u21 * k01
        )
        m21 = ((v20 * g10 + v21 * g11 + v22 * g12) + (s20 * b10 + s21 * b11 + s22 * b12)) + (
            u20 * k10 + u21 * k11
        )
        m22 = ((v20 * g20 + v21 * g21 + v22 * g22) + (s20 * b20 + s21 * b21 + s22 * b22)) + (
            u20 * k20 + u21 * k21
        )
        o[c] = g00
        o[1 * LANE_STRIDE + c] = g01
        o[2 * LANE_STRIDE + c] = g02
        o[3 * LANE_STRIDE + c] = g10
        o[4 * LANE_STRIDE + c] = g11
        o[5 * LANE_STRIDE + c] = g12
        o[6 * LANE_STRIDE + c] = g20
        o[7 * LANE_STRIDE + c] = g21
        o[8 * LANE_STRIDE + c] = g22
        o[9 * LANE_STRIDE + c] = na00
        o[10 * LANE_STRIDE + c] = na01
        o[11 * LANE_STRIDE + c] = na02
        o[12 * LANE_STRIDE + c] = na10
        o[13 * LANE_STRIDE + c] = na11
        o[14 * LANE_STRIDE + c] = na12
        o[15 * LANE_STRIDE + c] = na20
        o[16 * LANE_STRIDE + c] = na21
        o[17 * LANE_STRIDE + c] = na22
        o[18 * LANE_STRIDE + c] = b00
        o[19 * LANE_STRIDE + c] = b01
        o[20 * LANE_STRIDE + c] = b02
        o[21 * LANE_STRIDE + c] = b10
        o[22 * LANE_STRIDE + c] = b11
        o[23 * LANE_STRIDE + c] = b12
        o[24 * LANE_STRIDE + c] = b20
        o[25 * LANE_STRIDE + c] = b21
        o[26 * LANE_STRIDE + c] = b22
        o[27 * LANE_STRIDE + c] = nn00
        o[28 * LANE_STRIDE + c] = nn01
        o[29 * LANE_STRIDE + c] = nn02
        o[30 * LANE_STRIDE + c] = nn10
        o[31 * LANE_STRIDE + c] = nn11
        o[32 * LANE_STRIDE + c] = nn12
        o[33 * LANE_STRIDE + c] = nn20
        o[34 * LANE_STRIDE + c] = nn21
        o[35 * LANE_STRIDE + c] = nn22
        o[36 * LANE_STRIDE + c] = 0.5 * (m00 + m00)
        o[37 * LANE_STRIDE + c] = 0.5 * (m01 + m10)
        o[38 * LANE_STRIDE + c] = 0.5 * (m02 + m20)
        o[39 * LANE_STRIDE + c] = 0.5 * (m01 + m10)
        o[40 * LANE_STRIDE + c] = 0.5 * (m11 + m11)
        o[41 * LANE_STRIDE + c] = 0.5 * (m12 + m21)
        o[42 * LANE_STRIDE + c] = 0.5 * (m02 + m20)
        o[43 * LANE_STRIDE + c] = 0.5 * (m12 + m21)
        o[44 * LANE_STRIDE + c] = 0.5 * (m22 + m22)


for _dispatcher in (tracked_cross_lanes, _joint_of_lanes, tracked_record_lanes, _record_of_lanes):
    stamp_with_pieces(_dispatcher, _kernels_joint_links, _kernels_round_cached)
