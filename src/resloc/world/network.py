"""Range-limited sensing/communication graphs over a batch of independent teams."""

from __future__ import annotations

import numpy as np

__all__ = ["CELL_LIST_MIN", "PAIRWISE_MAX", "radius_links"]

#: Up to this many robots :func:`radius_links` tests every pair directly (one ``B x B``
#: array, a handful of numpy calls): at a team's size that is several times faster than
#: building a KD-tree, and the run does not import :mod:`scipy.spatial`.
PAIRWISE_MAX = 128

#: From this many robots on, :func:`radius_links` finds the pairs by cell lists (uniform
#: grid hashing, ``O(B)`` per step after one sort) instead of a KD-tree; both give the
#: same pair set (tested), the cell lists faster at scale.
CELL_LIST_MIN = 2048


def radius_links(
    p: np.ndarray, team: np.ndarray, radius: float, method: str = "auto"
) -> tuple[np.ndarray, np.ndarray]:
    """All directed links ``(i, j)``, ``i != j``, of robots of the same team within ``radius``.

    No ``B x B`` distance matrix above :data:`PAIRWISE_MAX` robots. Teams (Monte Carlo
    trials) are kept apart by shifting each team far along ``x`` before the search. Two
    equivalent searches: a KD-tree (``scipy.spatial.cKDTree.query_pairs``, ``O(B log B)``)
    and cell lists (the plane cut into squares of side ``radius``; a robot's neighbours are
    in its own and the 8 surrounding squares; ``O(B + E)`` work after sorting the robots by
    square); up to :data:`PAIRWISE_MAX` robots every pair is tested. A pair is linked when
    ``dx^2 + dy^2 <= radius^2`` in the shifted coordinates, the KD-tree's own test, so all
    three give the same links.

    Parameters
    ----------
    p : ndarray, shape (B, 2)
        Positions.
    team : ndarray of int, shape (B,)
        Team (trial) index of every robot.
    radius : float
    method : {"auto", "kdtree", "cells", "pairs"}
        ``auto``: every pair up to :data:`PAIRWISE_MAX` robots, cell lists from
        :data:`CELL_LIST_MIN` robots on, a KD-tree between.

    Returns
    -------
    i, j : ndarray of int, shape (E,)
        Sorted by ``i`` then ``j``.
    """
    if method not in ("auto", "kdtree", "cells", "pairs"):
        raise ValueError(f"method must be 'auto', 'kdtree', 'cells' or 'pairs', got {method!r}")
    if len(p) < 2:
        e = np.zeros(0, dtype=np.int64)
        return e, e.copy()
    x = p[:, 0]
    span = float(x.max() - x.min()) + 4.0 * radius + 1.0  # np.ptp
    shifted = p.astype(float, copy=True)
    shifted[:, 0] += team * span
    if method == "auto":
        method = "cells" if len(p) >= CELL_LIST_MIN else "kdtree"
        method = "pairs" if len(p) <= PAIRWISE_MAX else method
    if method == "pairs":
        return _pairwise_links(shifted, float(radius))
    if method == "cells":
        found = _cell_list_links(shifted, float(radius))
        if found is not None:
            return found
    from scipy.spatial import cKDTree

    pairs = cKDTree(shifted).query_pairs(radius, output_type="ndarray")
    if len(pairs) == 0:
        e = np.zeros(0, dtype=np.int64)
        return e, e.copy()
    i = np.concatenate([pairs[:, 0], pairs[:, 1]]).astype(np.int64)
    j = np.concatenate([pairs[:, 1], pairs[:, 0]]).astype(np.int64)
    order = np.lexsort((j, i))
    return i[order], j[order]


def _pairwise_links(q: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Directed links within ``radius`` of the points ``q: (B, 2)`` by testing every pair
    (``dx^2 + dy^2 <= radius^2``, as the KD-tree does), sorted by ``i`` then ``j``."""
    dx = q[None, :, 0] - q[:, None, 0]
    dy = q[None, :, 1] - q[:, None, 1]
    near = dx * dx + dy * dy <= radius * radius
    np.fill_diagonal(near, False)
    i, j = np.nonzero(near)
    return i.astype(np.int64), j.astype(np.int64)


def _cell_list_links(q: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Directed links within ``radius`` of the points ``q: (B, 2)`` by cell lists, sorted by
    ``i`` then ``j``; None when the grid is unusable (a radius that is not a positive
    finite number, non-finite positions, or more squares than an int64 key can number)."""
    B = len(q)
    if not (np.isfinite(radius) and radius > 0.0) or not np.all(np.isfinite(q)):
        return None
    lo = q.min(axis=0)
    cells = np.floor((q - lo) / radius)
    extent = cells.max(axis=0) + 3.0  # a free column and row on each side
    if extent[0] * extent[1] >= 2.0**62:
        return None
    width = np.int64(extent[0])
    n_cells = int(extent[0] * extent[1])
    cell = cells.astype(np.int64) + 1
    key = cell[:, 1] * width + cell[:, 0]
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    qs = q[order]  # robots in square order: the pairs are found between near rows
    if n_cells <= 4 * B + 4096:  # first robot of every square (a dense table)
        first = np.zeros(n_cells + 1, dtype=np.int64)
        np.cumsum(np.bincount(sorted_key, minlength=n_cells), out=first[1:])

        def run(lo_key, hi_key):
            return first[lo_key], first[hi_key + 1]
    else:  # sparse grid: binary search in the sorted keys

        def run(lo_key, hi_key):
            return (
                np.searchsorted(sorted_key, lo_key, side="left"),
                np.searchsorted(sorted_key, hi_key, side="right"),
            )

    # The 3 x 3 squares around a robot are three runs of consecutive keys (one per row).
    i_parts, j_parts = [], []
    r2 = radius * radius
    rows = np.arange(B, dtype=np.int64)
    for row in (-1, 0, 1):
        centre = sorted_key + row * width
        start, stop = run(centre - 1, centre + 1)
        count = stop - start
        total = int(count.sum())
        if total == 0:
            continue
        i = np.repeat(rows, count)
        j = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(count) - count - start, count)
        dx = qs[j, 0] - qs[i, 0]
        dy = qs[j, 1] - qs[i, 1]
        near = (dx * dx + dy * dy <= r2) & (i != j)
        i_parts.append(order[i[near]])
        j_parts.append(order[j[near]])
    if not i_parts:
        e = np.zeros(0, dtype=np.int64)
        return e, e.copy()
    link = np.concatenate(i_parts) * B + np.concatenate(j_parts)
    link.sort()
    return link // B, link % B
