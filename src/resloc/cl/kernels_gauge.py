"""Compiled twin of the ``gauge`` fusion method's per-link bookkeeping (:mod:`resloc.cl.gauge`).

``gauge`` fuses like the paper (same moments, same Kalman update: the CL kernel's), and
records every update's linear map for the team's gauge covariance ``G``:
``A_i <- (I - K H_i) A_i``, ``N_i <- (I - K H_i) N_i (I - K H_i)^T + K R K^T`` and, per fused
link, ``B_ij = -K H_j`` left-multiplied by robot i's later gains of the step
(:meth:`GaugeCovariance.update <resloc.cl.gauge.GaugeCovariance.update>`). The CL kernel
(:mod:`resloc.cl.kernels`) does that in its link loop (:func:`gauge_record`) on copies of
the step's ``A`` and ``N``; :func:`gauge_commit` then hands them, and the fused links' ``B_ij``
in the reference's order, to the :class:`~resloc.cl.gauge.GaugeCovariance`, whose own
``finish`` (the leak, the addition to ``G``) runs as in the reference path. The prediction
and the consensus exchanges are once per step, vectorized, outside the correction.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`range_bearing_jacobians_into`  :func:`resloc.models.measurement.range_bearing_jacobians`
:func:`gauge_record`          :meth:`resloc.cl.gauge.GaugeCovariance.update` (with
                               :func:`resloc.cl.tracking.update_map`)
=============================  ==========================================================
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from resloc.cl.backend import HAVE_NUMBA
from resloc.cl.gauge import GaugeCovariance
from resloc.models.measurement import MIN_RANGE

if HAVE_NUMBA:  # the optional extra ``fast``
    import numba

    _jit_inline = numba.njit(cache=True, nogil=True, inline="always")
else:  # pragma: no cover - exercised only where numba is absent

    def _jit_inline(func):
        return func


__all__ = ["KernelGauge", "gauge_commit", "gauge_state", "no_gauge"]

_MIN_R2 = MIN_RANGE**2


class KernelGauge(NamedTuple):
    """The gauge bookkeeping as the kernel takes it (empty arrays when the method is not
    ``gauge``)."""

    on: bool
    A: np.ndarray  # (B, 3, 3) product of each robot's I - K H_i this step
    noise: np.ndarray  # (B, 3, 3) its propagated measurement noise
    Bij: np.ndarray  # (E, 3, 3) per fused link, -K H_j times i's later gains


def no_gauge(E: int) -> KernelGauge:
    """Nothing to record (every method but ``gauge``)."""
    del E
    return KernelGauge(False, np.zeros((0, 3, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3, 3)))


def gauge_state(joint, E: int) -> KernelGauge | None:
    """Working copies of the step's bookkeeping of ``joint`` for ``E`` links; None when the
    kernel cannot reproduce the reference (no bookkeeping, or updates already recorded this
    step by an earlier correction: their ``B_ij`` would have to see this call's gains)."""
    if not isinstance(joint, GaugeCovariance) or len(joint.obs):
        return None
    A = np.ascontiguousarray(joint.A, dtype=float).copy()
    noise = np.ascontiguousarray(joint.noise, dtype=float).copy()
    return KernelGauge(True, A, noise, np.zeros((E, 3, 3)))


def gauge_commit(joint: GaugeCovariance, state: KernelGauge, i, j, fused) -> None:
    """Hand the kernel's bookkeeping to ``joint`` as the reference leaves it: ``A``, ``N``,
    and the fused links' observers, neighbours and ``B_ij`` in the reference's order (round
    r holds every robot's r-th link)."""
    E = len(i)
    rank = np.arange(E) - np.searchsorted(i, i, side="left")
    rows = np.flatnonzero(fused)
    rows = rows[np.argsort(rank[rows], kind="stable")]
    joint.A = state.A
    joint.noise = state.noise
    joint.obs = np.asarray(i, dtype=np.int64)[rows]
    joint.nbr = np.asarray(j, dtype=np.int64)[rows]
    joint.Bij = state.Bij[rows]


# ---------------------------------------------------------------------------------------
# Per-link pieces, inlined into the CL loop of resloc.cl.kernels.
# ---------------------------------------------------------------------------------------
@_jit_inline
def range_bearing_jacobians_into(xi0, xi1, xj0, xj1, Hi, Hj):
    """Jacobians of eq. (3) with respect to ``x_i`` and ``x_j`` into ``Hi``, ``Hj`` (2 x 3).
    Twin: :func:`resloc.models.measurement.range_bearing_jacobians`."""
    dx = xj0 - xi0
    dy = xj1 - xi1
    q = dx * dx + dy * dy
    if q < _MIN_R2:
        q = _MIN_R2
    r = math.sqrt(q)
    Hj[0, 0] = dx / r
    Hj[0, 1] = dy / r
    Hj[0, 2] = 0.0
    Hj[1, 0] = -dy / q
    Hj[1, 1] = dx / q
    Hj[1, 2] = 0.0
    for a in range(2):
        for b in range(3):
            Hi[a, b] = -Hj[a, b]
    Hi[1, 2] = -1.0


@_jit_inline
def gauge_record(gauge, e, first, fused, i, xi0, xi1, xj0, xj1, K, R, Hi, Hj, G, T3):
    """Record link ``e``'s update of robot ``i`` (its links start at row ``first``; ``fused``:
    the flags of the rows so far) linearized at i's estimate before the update and j's
    transmitted one. Twin: :meth:`resloc.cl.gauge.GaugeCovariance.update`."""
    _on, A, noise, Bij = gauge
    range_bearing_jacobians_into(xi0, xi1, xj0, xj1, Hi, Hj)
    for a in range(3):  # G = I - K H_i
        for b in range(3):
            G[a, b] = (1.0 if a == b else 0.0) - (K[a, 0] * Hi[0, b] + K[a, 1] * Hi[1, b])
    for r in range(first, e):  # i's earlier B_ik this step see i's new gain
        if fused[r]:
            _left_multiply(G, Bij[r], T3)
    _left_multiply(G, A[i], T3)
    # N_i <- G N_i G^T + K R K^T
    _left_multiply(G, noise[i], T3)
    for a in range(3):
        t0 = K[a, 0] * R[0, 0] + K[a, 1] * R[1, 0]
        t1 = K[a, 0] * R[0, 1] + K[a, 1] * R[1, 1]
        for b in range(3):
            s = 0.0
            for c in range(3):
                s += noise[i, a, c] * G[b, c]
            T3[a, b] = s + (t0 * K[b, 0] + t1 * K[b, 1])
    for a in range(3):
        for b in range(3):
            noise[i, a, b] = T3[a, b]
            Bij[e, a, b] = -(K[a, 0] * Hj[0, b] + K[a, 1] * Hj[1, b])


@_jit_inline
def _left_multiply(G, M, T3):
    """``M <- G M`` of 3 x 3 matrices in place (``T3``: scratch)."""
    for a in range(3):
        for b in range(3):
            s = 0.0
            for c in range(3):
                s += G[a, c] * M[c, b]
            T3[a, b] = s
    for a in range(3):
        for b in range(3):
            M[a, b] = T3[a, b]
