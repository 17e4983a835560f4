"""The witness stage's notes, compiled (twins of
:func:`~resloc.cl.detection_witness.witness_notes`).

:func:`note_at` computes a link's note with libm's ``cos``, ``sin`` and ``hypot``, the
numpy spec's products one for one (:func:`notes_of`: rows of arrays; :func:`fast_notes`:
``step_notes`` with the numba backend). Those three calls a link are about half of the
notes' cost in a step (numba here has no vector math library): the step's pass
(:func:`~resloc.cl.kernels_witness_step.witness_pass`) computes every link's note with
:func:`sent_notes` instead, with :func:`~resloc.cl.kernels_lanes.sincos_lanes`
(branch-free polynomials, within 2e-16 of libm for ``|a| <= SINCOS_LANES_MAX``; libm beyond
it and for a nan, as the redundancy pre-pass's fixes do) and the distance as the square
root of the sum of squares (within an ulp of ``hypot``; ``hypot`` where that is not
finite), then ``note_at``'s operations one for one, branch-free (``r > 0`` a select), in
loops LLVM compiles to SIMD. The notes are those of ``note_at`` to a few ulps, not to the
bit.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`notes_of`               :func:`~resloc.cl.detection_witness.witness_notes` (the
                               same products)
:func:`sent_notes`             :func:`~resloc.cl.detection_witness.witness_notes` (to a
                               few ulps)
=============================  ==========================================================
"""

from __future__ import annotations

import math

import numpy as np

from resloc.cl import kernels_lanes as _kernels_lanes
from resloc.cl.backend import backend
from resloc.cl.kernels_lanes import SINCOS_LANES_MAX, sincos_lanes
from resloc.cl.kernels_math import jit_inline, jit_lanes, stamp_with_pieces
from resloc.cl.kernels_witness import WITNESS_RUNS

__all__ = ["NOTE_ROWS", "fast_notes", "note_at", "notes_of", "sent_notes"]


@jit_lanes
def notes_of(z, x_obs, P_obs, x_nb, R, u, Q):
    """Each row's note ``u (E, 2)`` and its covariance ``Q (E, 2, 2)``, written in place,
    from the readings ``z (E, 2)``, the observers' estimates ``x_obs (E, 3)``, ``P_obs
    (E, 3, 3)`` and the neighbours' broadcasts ``x_nb (E, 3)``. Twin:
    :func:`~resloc.cl.detection_witness.witness_notes` (the same products)."""
    for e in range(z.shape[0]):
        lengthen = math.exp(0.5 * (R[1, 1] + P_obs[e, 2, 2]))
        note_at(z, e, x_obs, e, P_obs, x_nb, R, u, Q, e, lengthen)


@jit_inline
def note_at(z, e, x, o, P, x_nb, R, u, Q, q, lengthen):
    """Row ``e``'s note into ``u[q]``, ``Q[q]``: the reading ``z[e]``, the neighbour's
    broadcast ``x_nb[e]``, the observer's estimate ``x[o]``, ``P[o]`` (:func:`notes_of`);
    ``lengthen``: ``exp((R[1, 1] + P[o, 2, 2]) / 2)``, the observer's (computed once per
    observer by the step's pass). Scalars and whole arrays with indices: a view per row
    costs more than the note."""
    a = x[o, 2] + z[e, 1]
    r_mean = z[e, 0] * lengthen
    ca = math.cos(a)
    sa = math.sin(a)
    u[q, 0] = x_nb[e, 0] - (x[o, 0] + r_mean * ca)
    u[q, 1] = x_nb[e, 1] - (x[o, 1] + r_mean * sa)
    rel0 = x_nb[e, 0] - x[o, 0]
    rel1 = x_nb[e, 1] - x[o, 1]
    r = math.hypot(rel0, rel1)
    if r > 0.0:
        c = rel0 / r
        s = rel1 / r
    else:
        c = ca
        s = sa
        r = z[e, 0]
    # J_x = [[1, 0, -r s], [0, 1, r c]], J_z = [[c, -r s], [s, r c]]: every product of
    # J_x P J_x^T + J_z R J_z^T kept, zeros included (a non-finite P propagates as in numpy)
    j2, k2 = -r * s, r * c
    A = (
        P[o, 0, 0] + 0.0 * P[o, 1, 0] + j2 * P[o, 2, 0],
        P[o, 0, 1] + 0.0 * P[o, 1, 1] + j2 * P[o, 2, 1],
        P[o, 0, 2] + 0.0 * P[o, 1, 2] + j2 * P[o, 2, 2],
    )
    B = (
        0.0 * P[o, 0, 0] + P[o, 1, 0] + k2 * P[o, 2, 0],
        0.0 * P[o, 0, 1] + P[o, 1, 1] + k2 * P[o, 2, 1],
        0.0 * P[o, 0, 2] + P[o, 1, 2] + k2 * P[o, 2, 2],
    )
    Ra = (c * R[0, 0] + j2 * R[1, 0], c * R[0, 1] + j2 * R[1, 1])
    Rb = (s * R[0, 0] + k2 * R[1, 0], s * R[0, 1] + k2 * R[1, 1])
    Q00 = (A[0] + 0.0 * A[1] + A[2] * j2) + (Ra[0] * c + Ra[1] * j2)
    Q01 = (0.0 * A[0] + A[1] + A[2] * k2) + (Ra[0] * s + Ra[1] * k2)
    Q10 = (B[0] + 0.0 * B[1] + B[2] * j2) + (Rb[0] * c + Rb[1] * j2)
    Q11 = (0.0 * B[0] + B[1] + B[2] * k2) + (Rb[0] * s + Rb[1] * k2)
    off = 0.5 * (Q01 + Q10)
    Q[q, 0, 0] = Q00
    Q[q, 0, 1] = off
    Q[q, 1, 0] = off
    Q[q, 1, 1] = Q11


def fast_notes(z, x_obs, P_obs, x_nb, R) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`notes_of` on the arrays as :func:`~resloc.cl.detection_witness.witness_notes`
    takes them: ``(u, Q)``, or None with the numpy backend or shapes it does not take."""
    if backend() != "numba":
        return None
    z, x_obs, P_obs, x_nb, R = (
        np.ascontiguousarray(a, dtype=float) for a in (z, x_obs, P_obs, x_nb, R)
    )
    E = len(z)
    if z.shape != (E, 2) or x_obs.shape != (E, 3) or P_obs.shape != (E, 3, 3):
        return None
    if x_nb.shape != (E, 3) or R.shape != (2, 2):
        return None
    u = np.empty((E, 2))
    Q = np.empty((E, 2, 2))
    notes_of(z, x_obs, P_obs, x_nb, R, u, Q)
    WITNESS_RUNS["notes"] += 1
    return u, Q


#: :func:`sent_notes`' rows: ``u`` (2), ``Q``'s entries ``Q00``, ``Q01 = Q10``, ``Q11``.
NOTE_ROWS = 5


@jit_lanes
def sent_notes(z, x, P, x_src, xrows, li, R, lengthen, notes):
    """Every link's note: link ``e`` (observer ``li[e]``, reading ``z[e]``, neighbour's
    broadcast ``x_src[xrows[e]]``, or ``x_src[e]`` when ``xrows`` is empty) at the
    observer's estimate ``x[li[e]]``, ``P[li[e]]``;
    ``lengthen[o] = exp((R[1, 1] + P[o, 2, 2]) / 2)``. Into ``notes: (NOTE_ROWS, E)``:
    ``u`` and ``Q`` (symmetric: its off-diagonal once), rows ``u0, u1, Q00, Q01, Q11``.
    Twin: :func:`note_at` (to a few ulps). The angles, their
    sines and cosines and the distances in arrays of their own: a loop over rows of one 2-d
    array does not compile to SIMD (measured: 3.0 against 0.55 us for 260 links)."""
    E = li.shape[0]
    by_row = xrows.shape[0] > 0
    out = notes.reshape(notes.size)
    angle = np.empty(E)
    cos_a = np.empty(E)
    sin_a = np.empty(E)
    dist = np.empty(E)
    for e in range(E):
        o = li[e]
        m = xrows[e] if by_row else e
        angle[e] = x[o, 2] + z[e, 1]
        rel0 = x_src[m, 0] - x[o, 0]
        rel1 = x_src[m, 1] - x[o, 1]
        dist[e] = math.sqrt(rel0 * rel0 + rel1 * rel1)
    for e in range(E):
        sn, cs = sincos_lanes(angle[e])
        cos_a[e] = cs
        sin_a[e] = sn
    for e in range(E):  # (the polynomials' range; nan; the squares' overflow, inf: hypot's)
        a = angle[e]
        if not abs(a) <= SINCOS_LANES_MAX:
            cos_a[e] = math.cos(a)
            sin_a[e] = math.sin(a)
        if not math.isfinite(dist[e]):
            o = li[e]
            m = xrows[e] if by_row else e
            dist[e] = math.hypot(x_src[m, 0] - x[o, 0], x_src[m, 1] - x[o, 1])
    R00, R01, R10, R11 = R[0, 0], R[0, 1], R[1, 0], R[1, 1]
    for e in range(E):
        o = li[e]
        m = xrows[e] if by_row else e
        ca = cos_a[e]
        sa = sin_a[e]
        r_mean = z[e, 0] * lengthen[o]
        out[e] = x_src[m, 0] - (x[o, 0] + r_mean * ca)
        out[E + e] = x_src[m, 1] - (x[o, 1] + r_mean * sa)
        rel0 = x_src[m, 0] - x[o, 0]
        rel1 = x_src[m, 1] - x[o, 1]
        r = dist[e]
        far = r > 0.0
        c = rel0 / r if far else ca
        s = rel1 / r if far else sa
        r = r if far else z[e, 0]
        # note_at's products, zeros included (a non-finite P propagates as in numpy)
        j2, k2 = -r * s, r * c
        A0 = P[o, 0, 0] + 0.0 * P[o, 1, 0] + j2 * P[o, 2, 0]
        A1 = P[o, 0, 1] + 0.0 * P[o, 1, 1] + j2 * P[o, 2, 1]
        A2 = P[o, 0, 2] + 0.0 * P[o, 1, 2] + j2 * P[o, 2, 2]
        B0 = 0.0 * P[o, 0, 0] + P[o, 1, 0] + k2 * P[o, 2, 0]
        B1 = 0.0 * P[o, 0, 1] + P[o, 1, 1] + k2 * P[o, 2, 1]
        B2 = 0.0 * P[o, 0, 2] + P[o, 1, 2] + k2 * P[o, 2, 2]
        Ra0 = c * R00 + j2 * R10
        Ra1 = c * R01 + j2 * R11
        Rb0 = s * R00 + k2 * R10
        Rb1 = s * R01 + k2 * R11
        Q00 = (A0 + 0.0 * A1 + A2 * j2) + (Ra0 * c + Ra1 * j2)
        Q01 = (0.0 * A0 + A1 + A2 * k2) + (Ra0 * s + Ra1 * k2)
        Q10 = (B0 + 0.0 * B1 + B2 * j2) + (Rb0 * c + Rb1 * j2)
        Q11 = (0.0 * B0 + B1 + B2 * k2) + (Rb0 * s + Rb1 * k2)
        out[2 * E + e] = Q00
        out[3 * E + e] = 0.5 * (Q01 + Q10)
        out[4 * E + e] = Q11


stamp_with_pieces(sent_notes, _kernels_lanes)  # (sincos_lanes: its own decorator)
