"""The witness stage's notes in SIMD lanes (:mod:`resloc.cl.kernels_witness_notes`)."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.cl import kernels
from resloc.cl.detection_witness import witness_notes

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")


def _links(rng, n: int = 7, E: int = 300):
    """``E`` links of ``n`` observers sorted by observer, with the cases the lanes leave to
    libm: headings beyond the polynomials' range and a nan one, a neighbour at its
    observer's position (``r = 0``), one whose squared distance overflows."""
    li = np.sort(rng.integers(0, n, E))
    x = np.c_[rng.normal(0.0, 3.0, (n, 2)), rng.uniform(-np.pi, np.pi, n)]
    x[1, 2] = 70.0  # beyond SINCOS_LANES_MAX
    x[2, 2] = -3.0e9  # far beyond: the polynomials' reduction is not exact there
    x[3, 2] = np.nan
    A = rng.normal(0.0, 0.05, (n, 3, 3))
    P = A @ np.swapaxes(A, -1, -2) + 1e-6 * np.eye(3)
    z = np.c_[rng.uniform(0.1, 3.0, E), rng.uniform(-np.pi, np.pi, E)]
    x_nb = x[li] + np.c_[rng.normal(size=(E, 2)), np.zeros(E)]
    first = np.searchsorted(li, [0, 4, 5])  # (observers 0, 4, 5: finite headings)
    x_nb[first[0], :2] = x[li[first[0]], :2]  # r = 0
    x_nb[first[1], 0] = 3.0e154  # (3e154)^2 overflows: hypot's distance
    z[first[2]] = np.nan  # a reading that is no number
    return li, x, P, z, x_nb


def test_the_notes_in_lanes_equal_the_spec_and_note_at():
    """Every link's note by the lanes (libm only out of the polynomials' range, for nan
    and where the squares overflow) equals the numpy spec to 1e-9 (nan where it is nan)
    and the libm kernel (``notes_of``, ``note_at`` per row) to 1e-12; the broadcasts read
    by index give the same bits as per link."""
    from resloc.cl.kernels_witness_notes import NOTE_ROWS, notes_of, sent_notes

    rng = np.random.default_rng(12)
    li, x, P, z, x_nb = _links(rng)
    R = np.array([[0.01**2, 1e-6], [1e-6, 0.02**2]])
    lengthen = np.exp(0.5 * (R[1, 1] + P[:, 2, 2]))
    notes = np.full((NOTE_ROWS, len(li)), -1.0)
    sent_notes(z, x, P, x_nb, np.zeros(0, np.int64), li, R, lengthen, notes)
    assert sent_notes.signatures  # (compiled, not the Python function)
    u0, Q0 = witness_notes(z, x[li], P[li], x_nb, R)
    got = np.c_[notes[0], notes[1], notes[2], notes[3], notes[4]]
    spec = np.c_[u0[:, 0], u0[:, 1], Q0[:, 0, 0], Q0[:, 0, 1], Q0[:, 1, 1]]
    assert np.isnan(spec).any(axis=1).sum() >= 2  # (the nan heading's rows, the nan reading)
    np.testing.assert_allclose(got, spec, rtol=1e-9, atol=1e-15)
    u1 = np.empty((len(li), 2))
    Q1 = np.empty((len(li), 2, 2))
    notes_of(z, x[li], P[li], x_nb, R, u1, Q1)
    libm = np.c_[u1[:, 0], u1[:, 1], Q1[:, 0, 0], Q1[:, 0, 1], Q1[:, 1, 1]]
    finite = np.isfinite(libm)
    np.testing.assert_array_equal(np.isfinite(got), finite)
    np.testing.assert_allclose(got, libm, rtol=1e-12, atol=1e-15)  # (u cancels: not ulps)
    # the broadcasts by index (the batch's rows, shuffled and repeated): the same bits
    order = rng.permutation(len(li))
    x_src = np.concatenate([x_nb[order], x_nb[order[:5]] + 1.0])
    rows = np.empty(len(li), np.int64)
    rows[order] = np.arange(len(li))
    by_row = np.full_like(notes, -1.0)
    sent_notes(z, x, P, x_src, rows, li, R, lengthen, by_row)
    np.testing.assert_array_equal(by_row, notes)
