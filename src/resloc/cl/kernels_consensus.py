"""Compiled twin of one step of the distributed ``lambda2`` estimator (cl.connectivity).

:meth:`DistributedLambda2.step <resloc.cl.connectivity.DistributedLambda2.step>` builds the
step's Metropolis mixer and runs a few exchange rounds, about a hundred small numpy
operations per step for a team of 17; :func:`compiled_lambda2_step` does the same in one
compiled call (numba, the optional extra ``fast``) when the backend is ``numba``, and counts
it in ``DistributedLambda2.compiled_steps``. The edges and weights are those of
:class:`~resloc.cl.connectivity.MetropolisMixer` (distinct directed edges ``a <- b`` in
ascending ``a n + b``, no self-loops), summed in the same order.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`_metropolis_graph`      :class:`~resloc.cl.connectivity.MetropolisMixer`
                               (``__init__``, :func:`~resloc.cl.connectivity.metropolis_weights`)
:func:`_lambda2_rounds`        the rounds of ``DistributedLambda2.step`` (``laplacian``,
                               ``mix``, the trackers, the Fiedler update, the estimate)
=============================  ==========================================================
"""

from __future__ import annotations

import numpy as np

from resloc.cl import kernels_math as _kernels_math
from resloc.cl.backend import backend
from resloc.cl.kernels_math import jit, stamp_with_pieces

__all__ = ["compiled_lambda2_step"]


def compiled_lambda2_step(estimator, i: np.ndarray, j: np.ndarray) -> np.ndarray | None:
    """:meth:`DistributedLambda2.step <resloc.cl.connectivity.DistributedLambda2.step>`
    compiled: updates ``estimator`` in place and returns its estimates ``(n,)``, or None
    (nothing changed) when the backend is not ``numba``.

    Parameters
    ----------
    estimator : DistributedLambda2
    i, j : ndarray of int, shape (E,)
        Communication edges (each undirected edge once or in both directions).
    """
    if backend() != "numba":
        return None
    n = estimator.n
    a, b, deg, w, w_self = _metropolis_graph(
        np.ascontiguousarray(i, dtype=np.int64), np.ascontiguousarray(j, dtype=np.int64), n
    )
    y = np.array(estimator.y, dtype=float, copy=True)
    first = estimator.s is None
    s = np.zeros((n, 3)) if first else np.array(estimator.s, dtype=float, order="C", copy=True)
    phi = np.zeros((n, 3)) if first else np.array(estimator.phi, dtype=float, order="C")
    estimate = np.zeros(n)
    _lambda2_rounds(
        a, b, deg, w, w_self, y, s, phi, estimate, estimator.n_max, estimator.rounds,
        estimator.leak, first,
    )  # fmt: skip
    estimator.y, estimator.s, estimator.phi, estimator.estimate = y, s, phi, estimate
    estimator.count_messages(a)
    estimator.compiled_steps += 1
    return estimate.copy()


@jit
def _metropolis_graph(i, j, n):
    """Distinct directed edges ``a <- b`` (both directions of every edge, sorted by ``a n +
    b``, no self-loops), degrees, Metropolis weights ``1 / (1 + max(deg_a, deg_b))`` and the
    self weights ``1 - sum_b W_ab``. Twin: :class:`resloc.cl.connectivity.MetropolisMixer`."""
    E = i.shape[0]
    key = np.empty(2 * E, np.int64)
    for e in range(E):
        key[e] = i[e] * n + j[e]
        key[E + e] = j[e] * n + i[e]
    key = np.unique(key)
    count = 0
    for k in range(key.shape[0]):
        if key[k] // n != key[k] % n:
            count += 1
    a = np.empty(count, np.int64)
    b = np.empty(count, np.int64)
    count = 0
    for k in range(key.shape[0]):
        if key[k] // n != key[k] % n:
            a[count] = key[k] // n
            b[count] = key[k] % n
            count += 1
    deg = np.zeros(n)
    for e in range(count):
        deg[a[e]] += 1.0
    w = np.empty(count)
    total = np.zeros(n)
    for e in range(count):
        w[e] = 1.0 / (1.0 + max(deg[a[e]], deg[b[e]]))
        total[a[e]] += w[e]
    w_self = np.empty(n)
    for v in range(n):
        w_self[v] = 1.0 - total[v]
    return a, b, deg, w, w_self


@jit
def _lambda2_rounds(a, b, deg, w, w_self, y, s, phi, estimate, n_max, rounds, leak, first):
    """``rounds`` exchange rounds of the distributed ``lambda2`` estimator in place on ``y:
    (n,)``, the trackers ``s: (n, 3)``, the last signals ``phi: (n, 3)``; writes each robot's
    estimate. Twin: the rounds of :meth:`resloc.cl.connectivity.DistributedLambda2.step`."""
    n = y.shape[0]
    Ly = np.empty(n)
    mixed = np.empty((n, 3))
    acc = np.empty(3)

    def laplacian(out):  # (L y)_v = deg_v y_v - sum_{b in N_v} y_b
        for v in range(n):
            out[v] = 0.0
        for e in range(a.shape[0]):
            out[a[e]] += y[b[e]]
        for v in range(n):
            out[v] = deg[v] * y[v] - out[v]

    if first:
        laplacian(Ly)
        for v in range(n):
            phi[v, 0] = y[v]
            phi[v, 1] = y[v] * y[v]
            phi[v, 2] = y[v] * Ly[v]
            for c in range(3):
                s[v, c] = phi[v, c]
    for _ in range(rounds):
        laplacian(Ly)
        # W s: self weight times own state plus the weighted neighbours' states
        e = 0
        for v in range(n):
            for c in range(3):
                acc[c] = 0.0
            while e < a.shape[0] and a[e] == v:
                for c in range(3):
                    acc[c] += w[e] * s[b[e], c]
                e += 1
            for c in range(3):
                mixed[v, c] = w_self[v] * s[v, c] + acc[c]
        for v in range(n):
            p0 = y[v]
            p1 = y[v] * y[v]
            p2 = y[v] * Ly[v]
            s0 = mixed[v, 0] + p0 - phi[v, 0] + leak * (p0 - s[v, 0])
            s1 = mixed[v, 1] + p1 - phi[v, 1] + leak * (p1 - s[v, 1])
            s2 = mixed[v, 2] + p2 - phi[v, 2] + leak * (p2 - s[v, 2])
            s[v, 0] = s0
            s[v, 1] = s1
            s[v, 2] = s2
            phi[v, 0] = p0
            phi[v, 1] = p1
            phi[v, 2] = p2
            k1 = n_max[v]
            k3 = 2.0 * n_max[v]
            eps = 0.05 / n_max[v]
            y[v] = y[v] - eps * (k1 * s0 + 1.0 * Ly[v] + k3 * (s1 - 1.0) * y[v])
            var = s1 - s0 * s0
            est = s2 / var if var > 1e-12 else 0.0
            if not np.isfinite(est):
                est = 0.0
            elif est < 0.0:
                est = 0.0
            elif est > n_max[v]:
                est = n_max[v]
            estimate[v] = est if deg[v] > 0 else 0.0


stamp_with_pieces(_lambda2_rounds, _kernels_math)
