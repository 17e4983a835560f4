"""The once-per-step parts of the ``gauge`` fusion method, compiled (:mod:`resloc.cl.gauge`).

The per-link records are the CL kernel's (:mod:`resloc.cl.kernels_gauge`); these are the
prediction, the end of the correction and the reported covariances, each the twin of a
method of :class:`~resloc.cl.gauge.GaugeCovariance`, used by the ``gauge`` strategy
(:mod:`resloc.cl.fusion_methods`) when the backend is numba and the bookkeeping is a
batch's with exact team sums (a robot process's ``local`` gauge and the ``consensus`` sums
stay numpy, except the reported covariances). Each returns None or False (nothing changed)
when it does not apply; the strategy then runs the reference. Imported on the strategy's
first call (it needs the compiled prediction's process noise,
:mod:`resloc.cl.kernels_predict`, which imports the link loop).

A step of the compiled path allocates no bookkeeping array: the step's ``L``, ``A``, ``N``
and ``D`` live in :class:`~resloc.cl.kernels_gauge.GaugeBuffers`, allocated once, and ``G``
is updated in place (measured at 17 robots, the Python and the allocations around these
kernels cost more than the kernels themselves: ``docs/performance.md``).

=================================  ======================================================
function                           numpy twin
=================================  ======================================================
:func:`compiled_gauge_predict`     :meth:`resloc.cl.gauge.GaugeCovariance.predict` (with
                                   :func:`resloc.models.motion.process_noise`)
:func:`compiled_gauge_finish`      :meth:`resloc.cl.gauge.GaugeCovariance.finish`
:func:`compiled_gauge_reported`    :meth:`resloc.cl.gauge.GaugeCovariance.reported`
=================================  ======================================================

(kernels: :func:`_predict_step`, :func:`_leak_and_add`, :func:`_reported_into`.)
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl import kernels_math as _kernels_math
from resloc.cl import kernels_predict as _kernels_predict
from resloc.cl.backend import backend
from resloc.cl.gauge import GaugeCovariance
from resloc.cl.kernels_gauge import NO_LINKS, buffers_of
from resloc.cl.kernels_math import chol3, jit, jit_inline, stamp_with_pieces
from resloc.cl.kernels_predict import noise_variances, odometry_process_noise
from resloc.linalg import JITTER_LEVELS

__all__ = ["compiled_gauge_finish", "compiled_gauge_predict", "compiled_gauge_reported"]

_JITTER = np.asarray(JITTER_LEVELS, dtype=float)


def _runs_compiled(joint) -> bool:
    """The compiled twins reproduce ``joint``: a batch with exact team sums."""
    return (
        backend() == "numba"
        and isinstance(joint, GaugeCovariance)
        and joint.rounds is None
        and not joint.local
    )


def _own_G(joint: GaugeCovariance) -> np.ndarray:
    """``joint.G`` as an array the twins may update in place (the compiled path's own:
    the reference path makes a new ``G`` at every addition)."""
    G = joint.G
    if not (G.dtype == np.float64 and G.flags.c_contiguous and G.flags.writeable):
        G = joint.G = np.array(G, dtype=float, order="C")
    return G


def compiled_gauge_predict(joint, x: np.ndarray, dt: float, params, P_pred: np.ndarray) -> bool:
    """:meth:`GaugeCovariance.predict <resloc.cl.gauge.GaugeCovariance.predict>` compiled,
    in one call: every robot's process noise ``Q_i`` at ``x`` (twin:
    :func:`resloc.models.motion.process_noise`), the fit ``L_i``, ``G += sum_i L_i Q_i
    L_i^T`` and the step's bookkeeping started (``A = I``, ``N = 0``, ``D = P_pred``, in
    :class:`GaugeBuffers`). Returns False (nothing changed) when the twin does not apply,
    the shapes are not the documented ones or a team's ``sum J^T J`` is not positive
    definite (the reference then raises).

    Shapes: ``x: (B, 3)`` (the estimates before the prediction), ``P_pred: (B, 3, 3)``.
    """
    if not _runs_compiled(joint):
        return False
    B = joint.B
    odometry_shape, odometry_var, floor_var = noise_variances(params, dt)
    if odometry_shape not in ((2,), (B, 2)) or floor_var.shape != (3,):
        return False
    if np.shape(x) != (B, 3) or np.shape(P_pred) != (B, 3, 3):
        return False
    buffers = buffers_of(joint)
    if not _predict_step(
        np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(P_pred, dtype=float),
        float(dt), odometry_var, floor_var, joint.N, _JITTER, _own_G(joint), buffers.work,
    ):  # fmt: skip
        return False
    joint.L, joint.A, joint.noise, joint.D_pred = (
        buffers.L,
        buffers.A,
        buffers.noise,
        buffers.D_pred,
    )
    joint.obs = joint.nbr = NO_LINKS[0]
    joint.Bij = NO_LINKS[1]
    joint.compiled_steps += 1
    return True


def compiled_gauge_finish(joint) -> bool:
    """:meth:`GaugeCovariance.finish <resloc.cl.gauge.GaugeCovariance.finish>` compiled:
    every robot's leak ``Delta_m = L_m (A_m - I) + sum_{i fused m} L_i B_im`` and ``G +=
    sum_m Delta_m D_m Delta_m^T + sum_i L_i N_i L_i^T``. False when it does not apply."""
    if not _runs_compiled(joint):
        return False
    buffers = buffers_of(joint)
    if (
        joint.L is buffers.L
        and joint.A is buffers.A
        and joint.noise is buffers.noise
        and joint.D_pred is buffers.D_pred
    ):
        work = buffers.work  # the compiled prediction's arrays: no copy
    else:  # a step the reference predicted
        work = np.stack([joint.L, joint.A, joint.noise, joint.D_pred]).astype(float)
    _leak_and_add(
        work, np.ascontiguousarray(joint.obs, dtype=np.int64),
        np.ascontiguousarray(joint.nbr, dtype=np.int64),
        np.ascontiguousarray(joint.Bij, dtype=float).reshape(-1, 3, 3), joint.N, _own_G(joint),
    )  # fmt: skip
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
    if joint.rounds is None:  # one G per team of N robots
        G, team_size = joint.G, joint.N
    else:  # every robot's own
        G, team_size = joint.robot_G(), 1
    _reported_into(x, P, np.ascontiguousarray(G, dtype=float), team_size, out)
    joint.compiled_reports += 1
    return out


@jit
def _reported_into(x, P, G, team_size, out):
    """``out_b = sym(P_b + J_b G_t J_b^T)`` with ``J_b = [[1, 0, -y_b], [0, 1, x_b], [0, 0,
    1]]`` (:func:`resloc.cl.gauge.gauge_jacobian`) and ``G_t`` the gauge covariance of robot
    ``b``'s team ``t = b // team_size``. Twin: ``GaugeCovariance.reported``."""
    J = np.zeros((3, 3))
    S = np.empty((3, 3))
    J[0, 0] = J[1, 1] = J[2, 2] = 1.0
    for b in range(x.shape[0]):
        J[0, 2] = -x[b, 1]
        J[1, 2] = x[b, 0]
        S[:, :] = P[b]
        _add_sandwich(J, G[b // team_size], S)
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
def _predict_step(x, P_pred, dt, odometry_var, floor_var, N, jitter, G, work):
    """The gauge's prediction for teams of ``N`` robots: per team ``t``, ``M = sum_l J_l^T
    J_l``, ``L_i = M^-1 J_i^T`` by a Cholesky solve (twin: ``GaugeCovariance._fit``,
    :func:`gauge_jacobian <resloc.cl.gauge.gauge_jacobian>`) and ``G[t] <- sym(G[t] + sum_i
    L_i Q_i L_i^T)`` with ``Q_i`` the process noise at ``x_i`` (twin:
    :func:`resloc.models.motion.process_noise`); then the step's bookkeeping started
    (twin: ``GaugeCovariance._start_step``). ``work`` (4, B, 3, 3) receives ``L``, ``A =
    I``, ``N = 0`` and ``D = P_pred``. Returns False (``G`` and the bookkeeping unchanged)
    when a team's ``M`` has no Cholesky factor."""
    L = work[0]
    per_robot_noise = odometry_var.shape[0] > 1
    M = np.zeros((3, 3))
    C = np.zeros((3, 3))
    Minv = np.zeros((3, 3))
    Q = np.zeros((3, 3))
    added = np.zeros((G.shape[0], 3, 3))
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
        for b in range(t * N, (t + 1) * N):
            px = x[b, 0]
            py = x[b, 1]
            for a in range(3):  # L_b = M^-1 J_b^T, J^T = [[1, 0, 0], [0, 1, 0], [-y, x, 1]]
                L[b, a, 0] = Minv[a, 0] - Minv[a, 2] * py
                L[b, a, 1] = Minv[a, 1] + Minv[a, 2] * px
                L[b, a, 2] = Minv[a, 2]
            r = b if per_robot_noise else 0
            odometry_process_noise(
                math.cos(x[b, 2]), math.sin(x[b, 2]), dt, odometry_var[r, 0],
                odometry_var[r, 1], floor_var, Q,
            )  # fmt: skip
            _add_sandwich(L[b], Q, added[t])
    for t in range(G.shape[0]):  # every team's fit exists: the additions apply
        _add_symmetrized(G[t], added[t])
    for b in range(x.shape[0]):
        for a in range(3):
            for c in range(3):
                work[1, b, a, c] = 1.0 if a == c else 0.0
                work[2, b, a, c] = 0.0
                work[3, b, a, c] = P_pred[b, a, c]
    return True


@jit
def _leak_and_add(work, obs, nbr, Bij, N, G):
    """Every robot's leak ``Delta_m = L_m (A_m - I) + sum_{links (i, m) fused} L_i B_im`` and
    per team ``G[t] <- sym(G[t] + sum_m Delta_m D_m Delta_m^T + sum_i L_i N_i L_i^T)``
    (``work``: the step's ``L``, ``A``, ``N``, ``D``, shape (4, B, 3, 3), as
    :class:`~resloc.cl.kernels_gauge.GaugeBuffers` holds them).
    Twin: :meth:`resloc.cl.gauge.GaugeCovariance.finish` and ``_close``."""
    L = work[0]
    A = work[1]
    noise = work[2]
    D = work[3]
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


stamp_with_pieces(_predict_step, _kernels_math, _kernels_predict)
stamp_with_pieces(_leak_and_add, _kernels_math)
