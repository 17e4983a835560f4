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

The once-per-step parts have compiled twins too (exact team sums in a batch, the runner's
case; a robot process's ``local`` gauge and the ``consensus`` sums stay numpy):
:func:`compiled_gauge_predict` (the fit ``L_i`` and ``G += sum L Q L^T``) and
:func:`compiled_gauge_finish` (the leak and ``G += sum Delta D Delta^T + L N L^T``), each
counted in ``GaugeCovariance.compiled_steps``.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`range_bearing_jacobians_into`  :func:`resloc.models.measurement.range_bearing_jacobians`
:func:`gauge_record`          :meth:`resloc.cl.gauge.GaugeCovariance.update` (with
                               :func:`resloc.cl.tracking.update_map`)
:func:`_fit_and_add`          ``GaugeCovariance._fit`` and ``_add`` in
                               :meth:`~resloc.cl.gauge.GaugeCovariance.predict`
:func:`_leak_and_add`         :meth:`resloc.cl.gauge.GaugeCovariance.finish` (``_close``)
:func:`_reported_into`        :meth:`resloc.cl.gauge.GaugeCovariance.reported`
=============================  ==========================================================
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from resloc.cl import kernels_math as _kernels_math
from resloc.cl.backend import backend
from resloc.cl.gauge import GaugeCovariance
from resloc.cl.kernels_math import chol3, jit, jit_inline, stamp_with_pieces
from resloc.linalg import JITTER_LEVELS
from resloc.models.measurement import MIN_RANGE

__all__ = [
    "KernelGauge",
    "compiled_gauge_finish",
    "compiled_gauge_predict",
    "gauge_commit",
    "gauge_state",
    "no_gauge",
]

_JITTER = np.asarray(JITTER_LEVELS, dtype=float)

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
@jit_inline
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


@jit_inline
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


@jit_inline
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


# ---------------------------------------------------------------------------------------
# The once-per-step parts (prediction and end of the correction), compiled.
# ---------------------------------------------------------------------------------------
def _runs_compiled(joint) -> bool:
    """The compiled twins reproduce ``joint``: a batch with exact team sums."""
    return (
        backend() == "numba"
        and isinstance(joint, GaugeCovariance)
        and joint.rounds is None
        and not joint.local
    )


def compiled_gauge_predict(joint, x: np.ndarray, Q: np.ndarray, P_pred: np.ndarray) -> bool:
    """:meth:`GaugeCovariance.predict <resloc.cl.gauge.GaugeCovariance.predict>` compiled:
    the fit ``L_i`` of every robot, ``G += sum_i L_i Q_i L_i^T``, the step's bookkeeping
    started. Returns False (nothing changed) when the twin does not apply or a team's
    ``sum J^T J`` is not positive definite (the reference then raises).

    Shapes: ``x: (B, 3)``, ``Q: (B, 3, 3)``, ``P_pred: (B, 3, 3)``.
    """
    if not _runs_compiled(joint):
        return False
    L = np.empty((joint.B, 3, 3))
    G = np.array(joint.G, dtype=float, order="C", copy=True)
    x = np.ascontiguousarray(x, dtype=float)
    Q = np.ascontiguousarray(Q, dtype=float)
    if not _fit_and_add(x, Q, joint.N, _JITTER, L, G):
        return False
    joint.G = G
    joint._start_step(L, P_pred)
    joint.compiled_steps += 1
    return True


def compiled_gauge_finish(joint) -> bool:
    """:meth:`GaugeCovariance.finish <resloc.cl.gauge.GaugeCovariance.finish>` compiled:
    every robot's leak ``Delta_m = L_m (A_m - I) + sum_{i fused m} L_i B_im`` and ``G +=
    sum_m Delta_m D_m Delta_m^T + sum_i L_i N_i L_i^T``. False when it does not apply."""
    if not _runs_compiled(joint):
        return False
    G = np.array(joint.G, dtype=float, order="C", copy=True)
    _leak_and_add(
        np.ascontiguousarray(joint.L), np.ascontiguousarray(joint.A),
        np.ascontiguousarray(joint.D_pred), np.ascontiguousarray(joint.noise),
        np.ascontiguousarray(joint.obs, dtype=np.int64),
        np.ascontiguousarray(joint.nbr, dtype=np.int64),
        np.ascontiguousarray(joint.Bij, dtype=float).reshape(-1, 3, 3), joint.N, G,
    )  # fmt: skip
    joint.G = G
    joint.compiled_steps += 1
    return True


def compiled_gauge_reported(joint, x: np.ndarray, P: np.ndarray) -> np.ndarray | None:
    """:meth:`GaugeCovariance.reported <resloc.cl.gauge.GaugeCovariance.reported>` compiled
    (``P_i + J_i G J_i^T``, symmetrized), or None when the numba backend is off."""
    if backend() != "numba" or not isinstance(joint, GaugeCovariance):
        return None
    x = np.ascontiguousarray(x, dtype=float)
    P = np.ascontiguousarray(P, dtype=float)
    out = np.empty_like(P)
    _reported_into(x, P, np.ascontiguousarray(joint.robot_G(), dtype=float), out)
    joint.compiled_reports += 1
    return out


@jit
def _reported_into(x, P, G, out):
    """``out_b = sym(P_b + J_b G_b J_b^T)`` with ``J_b = [[1, 0, -y_b], [0, 1, x_b], [0, 0,
    1]]`` (:func:`resloc.cl.gauge.gauge_jacobian`). Twin: ``GaugeCovariance.reported``."""
    J = np.zeros((3, 3))
    S = np.empty((3, 3))
    J[0, 0] = J[1, 1] = J[2, 2] = 1.0
    for b in range(x.shape[0]):
        J[0, 2] = -x[b, 1]
        J[1, 2] = x[b, 0]
        S[:, :] = P[b]
        _add_sandwich(J, G[b], S)
        for r in range(3):
            for c in range(3):
                out[b, r, c] = 0.5 * (S[r, c] + S[c, r])


@jit_inline
def _add_sandwich(L, M, S):
    """``S += L M L^T`` of 3 x 3 matrices."""
    for a in range(3):
        for b in range(3):
            s = 0.0
            for c in range(3):
                t = 0.0
                for d in range(3):
                    t += L[a, d] * M[d, c]
                s += t * L[b, c]
            S[a, b] += s


@jit_inline
def _add_symmetrized(G, S):
    """``G <- sym(G + S)`` (twin: ``GaugeCovariance._add`` with exact sums)."""
    for a in range(3):
        for b in range(3):
            S[a, b] += G[a, b]
    for a in range(3):
        for b in range(3):
            G[a, b] = 0.5 * (S[a, b] + S[b, a])


@jit
def _fit_and_add(x, Q, N, jitter, L, G):
    """Per team ``t`` of ``N`` robots: ``M = sum_l J_l^T J_l``, ``L_i = M^-1 J_i^T`` into
    ``L`` (B, 3, 3) by a Cholesky solve (twin: ``GaugeCovariance._fit``, :func:`gauge_jacobian
    <resloc.cl.gauge.gauge_jacobian>`), then ``G[t] <- sym(G[t] + sum_i L_i Q_i L_i^T)``.
    Returns False when a team's ``M`` has no Cholesky factor."""
    M = np.zeros((3, 3))
    C = np.zeros((3, 3))
    Minv = np.zeros((3, 3))
    S = np.zeros((3, 3))
    for t in range(G.shape[0]):
        for a in range(3):
            for b in range(3):
                M[a, b] = 0.0
        for b in range(t * N, (t + 1) * N):
            px = x[b, 0]
            py = x[b, 1]
            # J = [[1, 0, -y], [0, 1, x], [0, 0, 1]]: J^T J
            M[0, 0] += 1.0
            M[1, 1] += 1.0
            M[0, 2] += -py
            M[2, 0] += -py
            M[1, 2] += px
            M[2, 1] += px
            M[2, 2] += py * py + px * px + 1.0
        if not chol3(M, C, jitter):
            return False
        for col in range(3):  # M^-1 column by column: C C^T m = e_col
            y0 = (1.0 if col == 0 else 0.0) / C[0, 0]
            y1 = ((1.0 if col == 1 else 0.0) - C[1, 0] * y0) / C[1, 1]
            y2 = ((1.0 if col == 2 else 0.0) - C[2, 0] * y0 - C[2, 1] * y1) / C[2, 2]
            m2 = y2 / C[2, 2]
            m1 = (y1 - C[2, 1] * m2) / C[1, 1]
            m0 = (y0 - C[1, 0] * m1 - C[2, 0] * m2) / C[0, 0]
            Minv[0, col] = m0
            Minv[1, col] = m1
            Minv[2, col] = m2
        for a in range(3):
            for b in range(3):
                S[a, b] = 0.0
        for b in range(t * N, (t + 1) * N):
            px = x[b, 0]
            py = x[b, 1]
            for a in range(3):  # L_b = M^-1 J_b^T, J^T = [[1, 0, 0], [0, 1, 0], [-y, x, 1]]
                L[b, a, 0] = Minv[a, 0] - Minv[a, 2] * py
                L[b, a, 1] = Minv[a, 1] + Minv[a, 2] * px
                L[b, a, 2] = Minv[a, 2]
            _add_sandwich(L[b], Q[b], S)
        _add_symmetrized(G[t], S)
    return True


@jit
def _leak_and_add(L, A, D, noise, obs, nbr, Bij, N, G):
    """Every robot's leak ``Delta_m = L_m (A_m - I) + sum_{links (i, m) fused} L_i B_im`` and
    per team ``G[t] <- sym(G[t] + sum_m Delta_m D_m Delta_m^T + sum_i L_i N_i L_i^T)``.
    Twin: :meth:`resloc.cl.gauge.GaugeCovariance.finish` and ``_close``."""
    B = L.shape[0]
    leak = np.zeros((B, 3, 3))
    for b in range(B):
        for a in range(3):
            for c in range(3):
                s = 0.0
                for d in range(3):
                    s += L[b, a, d] * (A[b, d, c] - (1.0 if d == c else 0.0))
                leak[b, a, c] = s
    for r in range(obs.shape[0]):
        i = obs[r]
        m = nbr[r]
        for a in range(3):
            for c in range(3):
                s = 0.0
                for d in range(3):
                    s += L[i, a, d] * Bij[r, d, c]
                leak[m, a, c] += s
    S = np.zeros((3, 3))
    for t in range(G.shape[0]):
        for a in range(3):
            for b in range(3):
                S[a, b] = 0.0
        for b in range(t * N, (t + 1) * N):
            _add_sandwich(leak[b], D[b], S)
            _add_sandwich(L[b], noise[b], S)
        _add_symmetrized(G[t], S)


stamp_with_pieces(_fit_and_add, _kernels_math)
stamp_with_pieces(_leak_and_add, _kernels_math)
