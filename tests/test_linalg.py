"""Tests of :mod:`resloc.linalg`: symmetrize, jittered Cholesky, SPD solves (STYLE habit 5)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from resloc.errors import NumericalError, ResLocError
from resloc.linalg import (
    JITTER_LEVELS,
    cholesky_jitter,
    is_positive_definite,
    solve_spd,
    symmetrize,
)

SpdFactory = Callable[..., np.ndarray]


def test_symmetrize(rng: np.random.Generator) -> None:
    A = rng.normal(size=(6, 4, 4))
    S = symmetrize(A)
    np.testing.assert_array_equal(S, np.swapaxes(S, -1, -2))
    np.testing.assert_allclose(S, 0.5 * (A + A.transpose(0, 2, 1)), rtol=0, atol=0)
    # Symmetric input is returned unchanged; single matrices work too.
    np.testing.assert_array_equal(symmetrize(S), S)
    np.testing.assert_array_equal(symmetrize(A[0]), S[0])


class TestCholeskyJitter:
    def test_pd_batch_is_plain_cholesky(
        self, rng: np.random.Generator, random_spd: SpdFactory
    ) -> None:
        P = random_spd(rng, 20, 5, scale=3.0, cond=1e4)
        L = cholesky_jitter(P)
        np.testing.assert_array_equal(L, np.linalg.cholesky(P))
        np.testing.assert_array_equal(np.triu(L, 1), 0.0)
        np.testing.assert_allclose(L @ np.swapaxes(L, -1, -2), P, rtol=1e-12, atol=1e-14)

    def test_psd_singular_is_rescued_by_jitter(
        self, rng: np.random.Generator, random_spd: SpdFactory
    ) -> None:
        # Rank-1 and rank-2 3x3 covariances: exact Cholesky fails on a zero pivot.
        v = rng.normal(size=(3, 1))
        W = rng.normal(size=(3, 2))
        singular = np.stack([v @ v.T, W @ W.T, np.ones((3, 3))])
        with pytest.raises(np.linalg.LinAlgError):
            np.linalg.cholesky(singular[2])
        good = random_spd(rng, 2, 3)
        P = np.concatenate([good[:1], singular, good[1:]])
        L = cholesky_jitter(P)
        assert np.all(np.isfinite(L))
        np.testing.assert_array_equal(np.triu(L, 1), 0.0)
        scale = np.mean(np.diagonal(P, axis1=-2, axis2=-1), axis=-1)
        err = np.abs(L @ np.swapaxes(L, -1, -2) - P).max(axis=(-1, -2))
        # At most the largest jitter level times the mean diagonal.
        assert np.all(err <= JITTER_LEVELS[-1] * scale * 1.01)
        # The positive definite members were not jittered at all.
        np.testing.assert_array_equal(L[0], np.linalg.cholesky(good[0]))
        np.testing.assert_array_equal(L[-1], np.linalg.cholesky(good[1]))

    def test_indefinite_raises(self) -> None:
        P = np.diag([1.0, -1.0, 2.0])[None]
        with pytest.raises(NumericalError, match="not positive definite"):
            cholesky_jitter(P)

    def test_slightly_indefinite_beyond_jitter_raises(self) -> None:
        # Smallest eigenvalue -1e-4 x mean diagonal: far beyond the largest jitter (1e-6).
        P = np.diag([1.0, 1.0, -1e-4])[None]
        with pytest.raises(NumericalError):
            cholesky_jitter(P)

    @pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
    @pytest.mark.parametrize("where", [(0, 0), (1, 1), (2, 0), (2, 2)])
    def test_non_finite_raises(self, bad: float, where: tuple[int, int]) -> None:
        P = np.stack([np.eye(3), 2.0 * np.eye(3)])
        P[1][where] = bad
        P[1][where[::-1]] = bad
        with pytest.raises(NumericalError):
            cholesky_jitter(P)

    def test_numerical_error_is_a_library_error(self) -> None:
        with pytest.raises(ResLocError):
            cholesky_jitter(np.full((1, 2, 2), np.nan))
        assert issubclass(NumericalError, ArithmeticError)


@pytest.mark.parametrize(("m", "k"), [(1, 1), (2, 1), (2, 3), (3, 3), (6, 2)])
def test_solve_spd_matches_numpy(
    m: int, k: int, rng: np.random.Generator, random_spd: SpdFactory
) -> None:
    S = random_spd(rng, 50, m, scale=10.0, cond=1e5)
    B = rng.normal(size=(50, m, k))
    X = solve_spd(S, B)
    assert X.shape == (50, m, k)
    np.testing.assert_allclose(X, np.linalg.solve(S, B), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(S @ X, B, rtol=1e-9, atol=1e-9)


def test_solve_spd_integer_rhs_and_empty_batch(random_spd: SpdFactory) -> None:
    S = random_spd(np.random.default_rng(3), 4, 2)
    B = np.arange(8).reshape(4, 2, 1)
    np.testing.assert_allclose(solve_spd(S, B), np.linalg.solve(S, B.astype(float)), rtol=1e-10)
    assert solve_spd(np.empty((0, 2, 2)), np.empty((0, 2, 1))).shape == (0, 2, 1)


def test_solve_spd_raises_on_nan() -> None:
    S = np.stack([np.eye(2), np.full((2, 2), np.nan)])
    with pytest.raises(NumericalError):
        solve_spd(S, np.ones((2, 2, 1)))


def test_is_positive_definite(rng: np.random.Generator, random_spd: SpdFactory) -> None:
    good = random_spd(rng, 3, 3)
    P = np.concatenate(
        [
            good,
            np.diag([1.0, -1e-9, 1.0])[None],  # indefinite
            np.zeros((1, 3, 3)),  # PSD, not PD
            np.diag([1.0, np.nan, 1.0])[None],
            np.diag([np.inf, 1.0, 1.0])[None],
            np.diag([1e-300, 1.0, 1.0])[None],  # tiny but positive
        ]
    )
    np.testing.assert_array_equal(
        is_positive_definite(P), [True, True, True, False, False, False, False, True]
    )
    # Asymmetric round-off is judged on the symmetric part.
    A = good[0].copy()
    A[0, 1] += 1e-14
    assert is_positive_definite(A[None])[0]
