"""Covariance hygiene: symmetrize, Cholesky with escalating jitter, SPD solves.

Every covariance that leaves a filter function has passed through :func:`symmetrize`;
every square root comes from :func:`cholesky_jitter`; no function here calls ``inv``.
"""

from __future__ import annotations

import numpy as np

from resloc.errors import NumericalError

__all__ = [
    "cholesky_jitter",
    "forward_substitution",
    "is_positive_definite",
    "solve_spd",
    "symmetrize",
]

#: Relative jitter levels tried in order by :func:`cholesky_jitter` (times mean diagonal).
JITTER_LEVELS = (0.0, 1e-12, 1e-10, 1e-8, 1e-6)


def symmetrize(P: np.ndarray) -> np.ndarray:
    """Return ``(P + P^T) / 2``.

    Parameters
    ----------
    P : ndarray, shape (..., n, n)
    """
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def cholesky_jitter(P: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor ``L`` with ``L L^T = P + eps I``, escalating ``eps`` if needed.

    The batch is factorized at once; only the members that fail are retried with
    jitter ``eps = level * mean(diag(P))`` for the levels in :data:`JITTER_LEVELS`.

    Parameters
    ----------
    P : ndarray, shape (B, n, n)
        Symmetric matrices.

    Returns
    -------
    ndarray, shape (B, n, n)
        Lower-triangular factors.

    Raises
    ------
    NumericalError
        If a matrix is not positive definite even with the largest jitter, or is not finite.
    """
    try:
        L = np.linalg.cholesky(P)
        # LAPACK does not always raise on NaN/inf input: it can return a non-finite factor.
        if np.all(np.isfinite(L)):
            return L
    except np.linalg.LinAlgError:
        pass
    P = np.asarray(P, dtype=float)
    out = np.empty_like(P)
    n = P.shape[-1]
    eye = np.eye(n)
    for b in range(P.shape[0]):
        out[b] = _cholesky_one(P[b], eye)
    return out


def _cholesky_one(Pb: np.ndarray, eye: np.ndarray) -> np.ndarray:
    if not np.all(np.isfinite(Pb)):
        raise NumericalError("covariance contains NaN or inf; the filter diverged")
    scale = max(float(np.mean(np.abs(np.diag(Pb)))), 1e-300)
    for level in JITTER_LEVELS:
        try:
            return np.linalg.cholesky(Pb + (level * scale) * eye)
        except np.linalg.LinAlgError:
            continue
    eig = np.linalg.eigvalsh(Pb)
    raise NumericalError(
        f"covariance is not positive definite (smallest eigenvalue {eig[0]:.3e}) "
        f"even with jitter {JITTER_LEVELS[-1]:g} x mean diagonal"
    )


def is_positive_definite(P: np.ndarray) -> np.ndarray:
    """Per-matrix positive-definiteness check by smallest eigenvalue.

    Parameters
    ----------
    P : ndarray, shape (B, n, n)

    Returns
    -------
    ndarray of bool, shape (B,)
    """
    P = np.asarray(P, dtype=float)
    finite = np.all(np.isfinite(P), axis=(-1, -2))
    ok = np.zeros(P.shape[0], dtype=bool)
    if finite.any():
        ok[finite] = np.linalg.eigvalsh(symmetrize(P[finite]))[:, 0] > 0.0
    return ok


def solve_spd(S: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Solve ``S X = B`` for symmetric positive definite ``S`` via Cholesky.

    Parameters
    ----------
    S : ndarray, shape (E, m, m)
    B : ndarray, shape (E, m, k)

    Returns
    -------
    ndarray, shape (E, m, k)
    """
    L = cholesky_jitter(S)
    Y = forward_substitution(L, B)
    return _backward(np.swapaxes(L, -1, -2), Y)


def forward_substitution(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Solve ``L X = B`` for lower-triangular ``L: (E, m, m)``, ``B: (E, m, k)`` (small m:
    explicit loops over m, vectorized over E)."""
    m = L.shape[-1]
    Y = np.empty_like(B, dtype=float)
    for r in range(m):
        acc = B[:, r, :].astype(float, copy=True)
        for c in range(r):
            acc -= L[:, r, c, None] * Y[:, c, :]
        Y[:, r, :] = acc / L[:, r, r, None]
    return Y


def _backward(U: np.ndarray, Y: np.ndarray) -> np.ndarray:
    m = U.shape[-1]
    X = np.empty_like(Y)
    for r in range(m - 1, -1, -1):
        acc = Y[:, r, :].copy()
        for c in range(r + 1, m):
            acc -= U[:, r, c, None] * X[:, c, :]
        X[:, r, :] = acc / U[:, r, r, None]
    return X
