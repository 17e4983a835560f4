"""Compiled twin of the ``gauge`` fusion method's per-link bookkeeping (:mod:`resloc.cl.gauge`).

``gauge`` fuses like the paper (same moments, same Kalman update: the CL kernel's), and
records every update's linear map for the team's gauge covariance ``G``:
``A_i <- (I - K H_i) A_i``, ``N_i <- (I - K H_i) N_i (I - K H_i)^T + K R K^T`` and, per fused
link, ``B_ij = -K H_j`` left-multiplied by robot i's later gains of the step
(:meth:`GaugeCovariance.update <resloc.cl.gauge.GaugeCovariance.update>`). The CL kernel
(:mod:`resloc.cl.kernels`) does that in its link loop (:func:`gauge_record`) on the step's
``A`` and ``N``; :func:`gauge_commit` then hands them, and the fused links' ``B_ij``
in the reference's order, to the :class:`~resloc.cl.gauge.GaugeCovariance`, whose
``finish`` (the leak, the addition to ``G``) follows. The consensus exchanges are once per
step, vectorized, outside the correction.

The once-per-step parts (prediction, finish, reported covariances) are compiled in
:mod:`resloc.cl.kernels_gauge_step`. A compiled step allocates no bookkeeping array: the
step's ``L``, ``A``, ``N``, ``D`` and the fused links' records live in
:class:`GaugeBuffers`, allocated once per batch (measured at 17 robots, the per-step Python
and allocations around the kernels cost more than the kernels themselves:
``docs/performance.md``).

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`range_bearing_jacobians_into`  :func:`resloc.models.measurement.range_bearing_jacobians`
:func:`gauge_record`          :meth:`resloc.cl.gauge.GaugeCovariance.update` (with
                               :func:`resloc.cl.tracking.update_map`)
:func:`_fused_in_round_order`  the order of ``GaugeCovariance.update``'s records
=============================  ==========================================================
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from resloc.cl.gauge import GaugeCovariance
from resloc.cl.kernels_math import jit, jit_inline
from resloc.models.measurement import MIN_RANGE

__all__ = [
    "NO_LINKS",
    "GaugeBuffers",
    "KernelGauge",
    "buffers_of",
    "gauge_commit",
    "gauge_state",
    "gauge_undo",
    "no_gauge",
]

_MIN_R2 = MIN_RANGE**2


class KernelGauge(NamedTuple):
    """The gauge bookkeeping as the kernel takes it (empty arrays when the method is not
    ``gauge``)."""

    on: bool
    A: np.ndarray  # (B, 3, 3) product of each robot's I - K H_i this step
    noise: np.ndarray  # (B, 3, 3) its propagated measurement noise
    Bij: np.ndarray  # (E, 3, 3) per fused link, -K H_j times i's later gains


_NO_GAUGE = KernelGauge(False, np.zeros((0, 3, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3, 3)))
#: The records of a step with no fused link yet (``obs``/``nbr``, ``Bij``; never written).
NO_LINKS = (np.zeros(0, dtype=np.int64), np.zeros((0, 3, 3)))
_IDENTITY3 = np.eye(3)


def no_gauge(E: int) -> KernelGauge:
    """Nothing to record (every method but ``gauge``; the kernel reads none of its arrays)."""
    del E
    return _NO_GAUGE


class GaugeBuffers:
    """The arrays the compiled twins keep a :class:`~resloc.cl.gauge.GaugeCovariance`'s
    step in, allocated once per batch size (a step then creates no array of its own).

    ``work`` (4, B, 3, 3) holds the step's fit ``L``, the products ``A``, the propagated
    noise ``N`` and the predicted ``D``, which the compiled prediction hands to the
    bookkeeping as views (``joint.L``, ``joint.A``, ``joint.noise``, ``joint.D_pred``);
    ``rows`` (capacity, 3, 3) receives the kernel's ``B_ij`` in row order, and ``obs``,
    ``nbr``, ``Bij`` the fused links in the reference's order (:func:`gauge_commit`).
    """

    def __init__(self, B: int) -> None:
        self.work = np.zeros((4, B, 3, 3))
        self.L, self.A, self.noise, self.D_pred = self.work
        self._grow(0)

    def __getstate__(self) -> dict:
        # The step's arrays are views of ``work``: a pickle would copy them apart.
        state = dict(self.__dict__)
        for name in ("L", "A", "noise", "D_pred"):
            del state[name]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.L, self.A, self.noise, self.D_pred = self.work

    def _grow(self, E: int) -> None:
        capacity = max(E, 64)
        self.rows = np.empty((capacity, 3, 3))
        self.obs = np.empty(capacity, dtype=np.int64)
        self.nbr = np.empty(capacity, dtype=np.int64)
        self.Bij = np.empty((capacity, 3, 3))

    def links(self, E: int) -> np.ndarray:
        """The kernel's ``B_ij`` rows for ``E`` links, shape (E, 3, 3) (uninitialised: the
        kernel writes the row of every link it fuses and reads no other)."""
        if len(self.rows) < E:
            self._grow(E)
        return self.rows[:E]


def buffers_of(joint: GaugeCovariance) -> GaugeBuffers:
    """``joint``'s :class:`GaugeBuffers`, made on first use (and for a new batch size)."""
    buffers = joint.kernel_buffers
    if buffers is None or buffers.work.shape[1] != joint.B:
        buffers = joint.kernel_buffers = GaugeBuffers(joint.B)
    return buffers


def gauge_state(joint, E: int) -> KernelGauge | None:
    """The step's bookkeeping of ``joint`` as the kernel takes it, for ``E`` links; None
    when the kernel cannot reproduce the reference (no bookkeeping, or updates already
    recorded this step by an earlier correction: their ``B_ij`` would have to see this
    call's gains).

    With no update recorded, ``A`` is the identity and ``N`` zero: when they are the
    compiled prediction's arrays (:class:`GaugeBuffers`) the kernel works on them in place
    and :func:`gauge_undo` puts them back if the kernel fails; otherwise on copies."""
    if not isinstance(joint, GaugeCovariance) or len(joint.obs):
        return None
    buffers = buffers_of(joint)
    if joint.A is buffers.A and joint.noise is buffers.noise:
        return KernelGauge(True, buffers.A, buffers.noise, buffers.links(E))
    A = np.array(joint.A, dtype=float, order="C", copy=True)
    noise = np.array(joint.noise, dtype=float, order="C", copy=True)
    return KernelGauge(True, A, noise, buffers.links(E))


def gauge_undo(joint: GaugeCovariance, state: KernelGauge) -> None:
    """The kernel failed after :func:`gauge_state`: ``joint`` as it was (``A = I``,
    ``N = 0``: no update was recorded when the state was made)."""
    if state.A is joint.A:
        state.A[...] = _IDENTITY3
        state.noise[...] = 0.0


def gauge_commit(joint: GaugeCovariance, state: KernelGauge, i, j, fused) -> None:
    """Hand the kernel's bookkeeping to ``joint`` as the reference leaves it: ``A``, ``N``,
    and the fused links' observers, neighbours and ``B_ij`` in the reference's order (round
    r holds every robot's r-th link), gathered by one compiled call into
    :class:`GaugeBuffers` (``i``, ``j``: int64 (E,), rows sorted by observer; ``fused``:
    bool (E,))."""
    buffers = buffers_of(joint)
    count = _fused_in_round_order(i, j, fused, state.Bij, buffers.obs, buffers.nbr, buffers.Bij)
    joint.A = state.A
    joint.noise = state.noise
    joint.obs = buffers.obs[:count]
    joint.nbr = buffers.nbr[:count]
    joint.Bij = buffers.Bij[:count]


@jit
def _fused_in_round_order(i, j, fused, rows, obs, nbr, Bij):
    """The fused links ``(i[e], j[e], rows[e])`` into ``obs``, ``nbr``, ``Bij`` round by
    round (round ``r``: every robot's ``r``-th row, robots in row order), the order of the
    reference's updates; returns their number. Twin: the ``rank`` sort of the reference's
    rounds (:meth:`GaugeCovariance.update <resloc.cl.gauge.GaugeCovariance.update>` called
    once per round)."""
    E = i.shape[0]
    count = 0
    rank = 0
    more = E > 0
    while more:
        more = False
        e = 0
        while e < E:  # robot by robot: its row of this rank
            first = e
            while e < E and i[e] == i[first]:
                e += 1
            row = first + rank
            if row < e:
                more = more or row + 1 < e
                if fused[row]:
                    obs[count] = i[row]
                    nbr[count] = j[row]
                    for a in range(3):
                        for b in range(3):
                            Bij[count, a, b] = rows[row, a, b]
                    count += 1
        rank += 1
    return count


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
