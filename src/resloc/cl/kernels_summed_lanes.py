"""The summed update's moments in SIMD lanes (:func:`summed_moments_lanes`).

In the ``summed`` update (:mod:`resloc.cl.kernels_summed`) every link's moments (eq. 3)
come from the *predicted* estimates: no link waits for another, so the links need no
rounds at all. :func:`summed_moments_lanes` takes them ``CHUNK`` consecutive rows at a
time, one link a lane, through the vectorized stages of the link rounds
(:mod:`resloc.cl.kernels_link_stages`: the factors of ``P_i`` and ``P_j``, the sigma
points' range and bearing by branch-free polynomials, their moments), and stores each
row's ``z_hat``, ``S - R`` and ``P^xz``. :func:`~resloc.cl.kernels_summed.correct_summed`
then judges and fuses the rows from them, exactly as from its own scalar moments; a row
the lanes cannot take (a point at the robot's own position, a heading out of the
polynomials' range, a covariance that needs Cholesky jitter) is left to its scalar
moments (``done[e]`` False), so the lanes never fall back as a whole and keep no state.

Coverage: the sigma-point filters whose 6-D points have at most one non-zero entry (the
CKF and the UKF, as the rounds), from :data:`SUMMED_LANES_MIN_LINKS` links on.
"""

from __future__ import annotations

import numpy as np

from resloc.cl import kernels_lanes as _kernels_lanes
from resloc.cl import kernels_link_stages as _kernels_link_stages
from resloc.cl.kernels_lanes import CHUNK
from resloc.cl.kernels_link_stages import (
    chol_lanes,
    gather_lanes,
    load_covariances,
    moment_scratch,
    moments_lanes,
    point_axes,
    points_lanes,
)
from resloc.cl.kernels_math import jit_lanes, stamp_with_pieces

__all__ = ["SUMMED_LANES_MIN_LINKS", "summed_lanes_cover", "summed_moments_lanes"]

#: The lanes take the moments from this many links on (as the rounds,
#: :data:`resloc.cl.kernels_rounds.ROUNDS_MIN_LINKS`).
SUMMED_LANES_MIN_LINKS = 64


def summed_lanes_cover(filt) -> bool:
    """Whether :func:`summed_moments_lanes` computes the moments of the filter described by
    ``filt`` (:class:`~resloc.cl.backend.FilterKernelSpec` as a tuple)."""
    return not (filt[0] or np.any(filt[3] > 1))


@jit_lanes
def summed_moments_lanes(x, P, links, filt, zh, s, pxz_rows, done):
    """Every row's moments at the predicted estimates ``x: (B, 3)``, ``P: (B, 3, 3)`` (the
    link structure ``links`` and filter ``filt`` as
    :func:`~resloc.cl.kernels_links.correct_links` takes them; ``filt`` one
    :func:`summed_lanes_cover` accepts), ``CHUNK`` rows at a time: ``zh: (E, 2)`` the
    predicted measurement, ``s: (E, 3)`` the points' spread ``(s00, s01, s11)`` (``S``
    without ``R``), ``pxz_rows: (E, 3, 2)`` robot i's cross-covariance, and ``done: (E,)``
    False where the row needs the scalar moments (then its other outputs are unspecified).
    Twin: :func:`~resloc.cl.kernels_summed.link_moments` (the sigma points' moments of
    :func:`~resloc.cl.kernels_points.point_moments`)."""
    li, z, nb, x_ref, P_ref = links[0], links[1], links[4], links[7], links[8]
    nz_idx, nz_val, nz_cnt, Wm, Wc, circular = filt[1:]
    axis, value = point_axes(nz_idx, nz_val, nz_cnt)
    m = axis.shape[0]
    C = CHUNK
    (lane_e, obs, src, xi, xr, zl, sin_cos, Li, Lj, cov, ok_i, ok_j, bad, Z0, Z1, sums,
     moments, pxz, mean) = moment_scratch(C, m)  # fmt: skip
    E = li.shape[0]
    for start in range(0, E, C):
        n = min(C, E - start)
        for c in range(n):
            lane_e[c] = start + c
        gather_lanes(x, li, nb, x_ref, z, lane_e, n, obs, src, xi, xr, zl, sin_cos, bad)
        load_covariances(P, obs, n, cov)
        chol_lanes(cov, n, Li, ok_i)
        load_covariances(P_ref, src, n, cov)
        chol_lanes(cov, n, Lj, ok_j)
        for c in range(n):  # a factor that needs jitter: the row's scalar moments
            bad[c] += 0.0 if (ok_i[c] == 1.0) & (ok_j[c] == 1.0) else 1.0
        points_lanes(axis, value, Wm, n, xi, xr, sin_cos, Li, Lj, Z0, Z1, sums, bad)
        moments_lanes(axis, value, Wm, Wc, circular, n, Li, Z0, Z1, sums, moments, pxz, mean, bad)
        for c in range(n):
            e = start + c
            done[e] = bad[c] == 0.0
            zh[e, 0] = moments[0, c]
            zh[e, 1] = moments[1, c]
            s[e, 0] = moments[2, c]
            s[e, 1] = moments[3, c]
            s[e, 2] = moments[4, c]
            for a in range(3):
                pxz_rows[e, a, 0] = pxz[2 * a, c]
                pxz_rows[e, a, 1] = pxz[2 * a + 1, c]


stamp_with_pieces(summed_moments_lanes, _kernels_lanes, _kernels_link_stages)
