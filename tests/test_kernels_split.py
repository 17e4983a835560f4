"""Split CI's compiled clip of an independent part (``resloc.cl.kernels_split``): the
certificate ``0 < P_ind < P`` that skips the Cholesky factor and the eigenvalues."""

from __future__ import annotations

import numpy as np

from resloc.cl.fusion import clip_independent
from resloc.linalg import JITTER_LEVELS


def _random_spd(rng, n: int) -> np.ndarray:
    A = rng.normal(size=(n, 3, 3)) * rng.uniform(0.05, 2.0, (n, 1, 1))
    return A @ np.swapaxes(A, -1, -2) + 1e-3 * np.eye(3)


def test_clip_certifies_parts_inside_the_covariance_without_factorizing() -> None:
    """Parts with ``0 < P_ind < P`` are kept (symmetrized) by the certificate alone: the
    factor's scratch is never written (the certificate ran); parts above ``P``, equal to
    it, zero or indefinite go to the factor and the eigenvalues. Both like the reference."""
    from resloc.cl.kernels_split import _clip_independent

    rng = np.random.default_rng(12)
    P = _random_spd(rng, 200)
    inside = P * rng.uniform(0.05, 0.95, (200, 1, 1))
    outside = np.concatenate([P[:50] * 1.3, P[50:100], 0.0 * P[100:150], -0.2 * P[150:]])
    jitter = np.asarray(JITTER_LEVELS, dtype=float)
    for P_ind, certified in ((inside, True), (outside, False)):
        ref = clip_independent(P, P_ind)
        for e in range(len(P)):
            out = np.zeros((3, 3))
            scratch = [np.full((3, 3), np.nan) for _ in range(3)]
            assert _clip_independent(P[e], P_ind[e], out, *scratch, jitter)
            np.testing.assert_allclose(out, ref[e], rtol=0, atol=1e-12 * np.abs(P[e]).max())
            factor_untouched = all(np.isnan(s).all() for s in scratch)
            assert factor_untouched == certified, e
