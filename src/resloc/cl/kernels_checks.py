"""The compiled link loop's index preconditions, checked in one compiled pass.

The loop (:mod:`resloc.cl.kernels_links`, :mod:`resloc.cl.kernels_rounds`) does not check
the indices it reads; :func:`resloc.cl.kernels.fast_correct` gives the correction to the
numpy reference (which raises the explanatory error) when they are not all in range. At a
team's size the half-dozen numpy reductions that checked them cost as much as the loop's
arithmetic; this is one call.
"""

from __future__ import annotations

from resloc.cl.kernels_math import jit

__all__ = ["observer_bound"]


@jit
def observer_bound(i, j, rows, row_count):
    """``1 + max(i)``, or ``-1`` when the links are not what the loop may read: an observer
    is negative, a link repeats the one before it (a duplicated link would read its own
    store within one call), or a neighbour row is outside ``[0, row_count)``.

    Parameters
    ----------
    i, j : ndarray of int64, shape (E,)
        Observers (sorted) and observed nodes.
    rows : ndarray of int64, shape (E,) or (0,)
        Rows of the neighbour estimates (empty: the per-link arrays themselves).
    row_count : int
        Rows of the neighbour estimates.

    Returns
    -------
    int
    """
    top = -1
    for e in range(i.shape[0]):
        a = i[e]
        if a < 0:
            return -1
        if e > 0 and a == i[e - 1] and j[e] == j[e - 1]:
            return -1
        top = max(top, a)
    for e in range(rows.shape[0]):
        if rows[e] < 0 or rows[e] >= row_count:
            return -1
    return top + 1
