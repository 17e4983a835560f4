"""The rows of the lanes' array of the fused lanes' SIMD updates (split CI's,
:mod:`resloc.cl.kernels_split_lanes`, and ``ci``'s, :mod:`resloc.cl.kernels_ci_lanes`):
lane ``k`` in column ``k`` of rows :data:`LANE_STRIDE` apart, flattened (``f[row * S +
k]``); ``ci`` uses the rows without the independent parts. With the lane's tuples in and
out of them."""

from __future__ import annotations

from resloc.cl.kernels_joint_lanes import LANE_STRIDE
from resloc.cl.kernels_math import jit_inline

S = LANE_STRIDE
# The rows of the lanes' array (lane k in column k). Gathered: P_i (times the recovery's
# inflation), P_j, i's independent part as stored, j's transmitted one (9 rows each, by
# row), x_i, x_j's position, P^xz (by row), S (00, 01, 11), the innovation, the lane.
R_PI = 0
R_PJ = 9
R_II = 18
R_IJ = 27
R_X = 36
R_XR = 39
R_PXZ = 41
R_S = 47
R_NU = 50
R_LANE = 52
# The weight's inputs (_weight_inputs_lanes): the 2 x 2 reductions a, ai, b, bi, g, gdi,
# gii (4 rows each), tr(D_i), tr(I_i), the prior's cost, both clips certified (1.0), the
# dependent and independent parts of P_i (9 rows each, for the determinant's cost).
R_A = 53
R_AI = 57
R_B = 61
R_BI = 65
R_G = 69
R_GDI = 73
R_GII = 77
R_TR = 81
R_TRP = 82
R_PRIOR = 83
R_OKA = 84
R_DP = 85
R_IP = 94
# The weight (weight_lanes): the best cost and its index on the grid, the weight.
R_BEST = 103
R_KBEST = 104
R_W = 105
# The update (_update_lanes): x_i's new estimate (its heading not wrapped), the posterior
# symmetrized (9), i's new independent part (00, 01, 02, 11, 12, 22), certified (1.0), the
# posterior positive definite by :func:`~resloc.cl.kernels_math.is_pd3`'s test (1.0).
R_XN = 106
R_PN = 109
R_IN = 118
R_OK = 124
R_PD = 125
# det(P_i) as weight_of computes it (ci only; 0.0 for split CI, whose cost does not read it)
R_DET = 126
# The grid's costs, lane after lane (lane k's G costs from R_COST * S + k * G on).
R_COST = 127
#: The rows of :func:`~resloc.cl.kernels_split_lanes.split_lane_scratch` before the grid's
#: costs (G rows more).
SPLIT_LANE_ROWS = R_COST
#: The fused lanes are padded to whole blocks of this many (copies of the first).
FUSED_BLOCK = 8


@jit_inline
def row9(f, row, k):
    """Rows ``row .. row + 8`` of lane ``k`` as a 9-tuple (a 3 x 3 matrix by row)."""
    return (
        f[row * S + k], f[(row + 1) * S + k], f[(row + 2) * S + k], f[(row + 3) * S + k],
        f[(row + 4) * S + k], f[(row + 5) * S + k], f[(row + 6) * S + k],
        f[(row + 7) * S + k], f[(row + 8) * S + k],
    )  # fmt: skip


@jit_inline
def row4(f, row, k):
    return (f[row * S + k], f[(row + 1) * S + k], f[(row + 2) * S + k], f[(row + 3) * S + k])


@jit_inline
def put4(f, row, k, v):
    """A 4-tuple ``v`` into rows ``row .. row + 3`` of lane ``k``."""
    f[row * S + k] = v[0]
    f[(row + 1) * S + k] = v[1]
    f[(row + 2) * S + k] = v[2]
    f[(row + 3) * S + k] = v[3]


@jit_inline
def put9(f, row, k, v):
    """A 9-tuple ``v`` into rows ``row .. row + 8`` of lane ``k``."""
    put4(f, row, k, (v[0], v[1], v[2], v[3]))
    put4(f, row + 4, k, (v[4], v[5], v[6], v[7]))
    f[(row + 8) * S + k] = v[8]


@jit_inline
def gather_lane(f, m, i, r, g, c, P, P_ref, xi, xr, pxz, moments, R, update):
    """Round lane ``c``'s inputs both updates read into column ``m``: ``P_i`` times the
    recovery's inflation ``g``, ``P_j`` (robot ``r``'s reference), ``x_i``, ``x_j``'s
    position, ``P^xz``, ``S`` (the moments plus ``R``, symmetrized), the innovation and the
    round lane itself."""
    for a in range(3):
        for b in range(3):
            f[(R_PI + 3 * a + b) * S + m] = P[i, a, b] * g  # g = 1: P_i itself
            f[(R_PJ + 3 * a + b) * S + m] = P_ref[r, a, b]
    for a in range(3):
        f[(R_X + a) * S + m] = xi[a, c]
    f[R_XR * S + m] = xr[0, c]
    f[(R_XR + 1) * S + m] = xr[1, c]
    for a in range(6):
        f[(R_PXZ + a) * S + m] = pxz[a, c]
    f[R_S * S + m] = moments[2, c] + R[0, 0]
    f[(R_S + 1) * S + m] = 0.5 * ((moments[3, c] + R[0, 1]) + (moments[3, c] + R[1, 0]))
    f[(R_S + 2) * S + m] = moments[4, c] + R[1, 1]
    f[R_NU * S + m] = update[0, c]
    f[(R_NU + 1) * S + m] = update[1, c]
    f[R_LANE * S + m] = c


@jit_inline
def pad_lanes(f, m):
    """The gathered rows of ``m`` lanes padded to a whole :data:`FUSED_BLOCK` with copies of
    lane 0 (never read); the padded count."""
    m2 = min((m + FUSED_BLOCK - 1) // FUSED_BLOCK * FUSED_BLOCK, S)
    for row in range(R_LANE + 1):
        for k in range(m, m2):
            f[row * S + k] = f[row * S]
    return m2
