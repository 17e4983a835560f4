"""The redundancy stage's test (:mod:`resloc.cl.detection_redundancy`): each position fix
against the information-weighted mean of its observer's *other* fixes (leave-one-out,
:func:`leave_one_out`), the statistic ``T_j = d_j^T (C_j + (sum_{k != j} C_k^-1)^-1)^-1
d_j`` (:func:`redundancy_statistic`) and the fault exclusion over each observer's fixes,
one at a time (:func:`exclude_inconsistent`). Everything is 2 x 2 and symmetric, written in
closed form on the entries.
"""

from __future__ import annotations

import numpy as np

__all__ = ["exclude_inconsistent", "leave_one_out", "redundancy_statistic"]

#: A reference with no peer (never used: such rows are not judged) gets this covariance (m^2).
_NO_PEER_COV = 1e12


def _sym2(M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The entries ``(a, b, c)`` of symmetric 2 x 2 matrices ``[[a, b], [b, c]]``."""
    return M[:, 0, 0], 0.5 * (M[:, 0, 1] + M[:, 1, 0]), M[:, 1, 1]


def _information(
    a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``[[a, b], [b, c]]^-1`` in closed form (2 x 2 SPD: ``det > 0``), as ``(a, b, c)``."""
    det = a * c - b * b
    return c / det, -b / det, a / det


def _group_sums(inverse: np.ndarray, n: int, *values: np.ndarray) -> list[np.ndarray]:
    return [np.bincount(inverse, weights=v, minlength=n) for v in values]


def _reference(
    fix: np.ndarray, C3: tuple, inverse: np.ndarray, n: int, included: np.ndarray
) -> tuple[np.ndarray, tuple, np.ndarray]:
    """Leave-one-out reference of every row over the included rows of its group (entries
    form); see :func:`leave_one_out`."""
    w = included.astype(float)
    Ya, Yb, Yc = (v * w for v in _information(*C3))
    ya = Ya * fix[:, 0] + Yb * fix[:, 1]
    yb = Yb * fix[:, 0] + Yc * fix[:, 1]
    Sa, Sb, Sc, sa, sb, count = _group_sums(inverse, n, Ya, Yb, Yc, ya, yb, w)
    Ra, Rb, Rc = Sa[inverse] - Ya, Sb[inverse] - Yb, Sc[inverse] - Yc
    ra, rb = sa[inverse] - ya, sb[inverse] - yb
    peers = np.rint(count[inverse] - w).astype(int)
    has = peers > 0
    det = np.where(has, Ra * Rc - Rb * Rb, 1.0)
    Qa = np.where(has, Rc / det, _NO_PEER_COV)
    Qb = np.where(has, -Rb / det, 0.0)
    Qc = np.where(has, Ra / det, _NO_PEER_COV)
    reference = np.where(
        has[:, None], np.stack([Qa * ra + Qb * rb, Qb * ra + Qc * rb], axis=1), fix
    )
    return reference, (Qa, Qb, Qc), peers


def _statistic(fix: np.ndarray, C3: tuple, reference: np.ndarray, Q3: tuple) -> np.ndarray:
    """``d^T (C + Q)^-1 d`` in closed form, shape (E,)."""
    a, b, c = (x + y for x, y in zip(C3, Q3, strict=True))
    d0, d1 = fix[:, 0] - reference[:, 0], fix[:, 1] - reference[:, 1]
    return (c * d0 * d0 - 2.0 * b * d0 * d1 + a * d1 * d1) / (a * c - b * b)


def _matrix(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.stack([np.stack([a, b], -1), np.stack([b, c], -1)], -2)


def leave_one_out(
    fix: np.ndarray, C: np.ndarray, i: np.ndarray, included: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Information-weighted mean of each row's observer's *other* included fixes.

    Parameters
    ----------
    fix : ndarray, shape (E, 2)
    C : ndarray, shape (E, 2, 2)
    i : ndarray of int, shape (E,)
    included : ndarray of bool, shape (E,), optional
        The fixes a reference may use (default: all).

    Returns
    -------
    reference : ndarray, shape (E, 2)
        ``m_-j`` (the row's own fix where it has no peer).
    reference_cov : ndarray, shape (E, 2, 2)
        ``(sum_{k != j} C_k^-1)^-1`` (a huge diagonal where it has no peer).
    peers : ndarray of int, shape (E,)
        Number of other included fixes of the same observer.

    Notes
    -----
    Everything is 2 x 2 and symmetric: the information sums and the solves are written in
    closed form on the entries (the attacker's oracle evaluates this on tens of thousands of
    rows per step).
    """
    E = len(fix)
    included = np.ones(E, bool) if included is None else np.asarray(included, bool)
    robots, inverse = np.unique(i, return_inverse=True)
    reference, Q3, peers = _reference(fix, _sym2(C), inverse, len(robots), included)
    return reference, _matrix(*Q3), peers


def redundancy_statistic(
    fix: np.ndarray, C: np.ndarray, reference: np.ndarray, reference_cov: np.ndarray
) -> np.ndarray:
    """``T = d^T (C + C_ref)^-1 d`` with ``d = fix - reference``, shape (E,)."""
    return _statistic(fix, _sym2(C), reference, _sym2(reference_cov))


def exclude_inconsistent(
    fix: np.ndarray,
    C: np.ndarray,
    i: np.ndarray,
    gate: float | np.ndarray,
    min_peers: float | np.ndarray,
    excluded: np.ndarray | None = None,
    residuals: bool = False,
) -> tuple[np.ndarray, ...]:
    """Fault exclusion over each observer's fixes, one at a time.

    Every round, each observer's included fixes are tested against the mean of its other
    included fixes; the one with the largest statistic above ``gate`` is excluded, if at
    least ``min_peers`` included fixes remain to have judged it. Rounds go on until no
    observer excludes any more. (Testing all rows once would not do: a gross lie pulls every
    honest row's reference by its share and they would all fail with it.)

    Parameters
    ----------
    fix : ndarray, shape (E, 2)
    C : ndarray, shape (E, 2, 2)
    i : ndarray of int, shape (E,)
        Observer of each row.
    gate, min_peers : float or ndarray, shape (E,)
    excluded : ndarray of bool, shape (E,), optional
        Rows excluded before the first round (they never enter a reference; e.g. links a
        sequence test holds out).
    residuals : bool
        Also return each row's residual against its reference and the residual's
        covariance.

    Returns
    -------
    excluded : ndarray of bool, shape (E,)
    statistic : ndarray, shape (E,)
        Each row's statistic against the observer's included fixes at the end (``nan``:
        fewer than ``min_peers`` of them, not judged).
    residual : ndarray, shape (E, 2)
        With ``residuals``: ``d = fix - m_-j`` at the end (``nan`` where not judged).
    residual_cov : ndarray, shape (E, 2, 2)
        With ``residuals``: ``C_j + (sum_{k != j} C_k^-1)^-1``.
    """
    E = len(fix)
    gate = np.broadcast_to(np.asarray(gate, float), (E,))
    min_peers = np.broadcast_to(np.asarray(min_peers, float), (E,))
    included = np.ones(E, bool) if excluded is None else ~np.asarray(excluded, bool)
    if E == 0:
        empty = (np.zeros((0, 2)), np.zeros((0, 2, 2))) if residuals else ()
        return ~included, np.zeros(0), *empty
    robots, inverse = np.unique(i, return_inverse=True)
    n = len(robots)
    C3 = _sym2(C)
    while True:
        reference, Q3, peers = _reference(fix, C3, inverse, n, included)
        stat = _statistic(fix, C3, reference, Q3)
        # An included row's peers stay to judge it once it is out.
        candidate = included & (peers >= min_peers) & (stat > gate)
        if not candidate.any():
            break
        rows = np.flatnonzero(candidate)
        # The worst candidate of each observer.
        order = rows[np.lexsort((-stat[rows], inverse[rows]))]
        first = np.r_[True, inverse[order][1:] != inverse[order][:-1]]
        included[order[first]] = False
    judged = peers >= min_peers
    if not residuals:
        return ~included, np.where(judged, stat, np.nan)
    residual = np.where(judged[:, None], fix - reference, np.nan)
    residual_cov = _matrix(*(x + y for x, y in zip(C3, Q3, strict=True)))
    return ~included, np.where(judged, stat, np.nan), residual, residual_cov
