"""Range-limited sensing/communication graphs over a batch of independent teams."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["radius_links"]


def radius_links(p: np.ndarray, team: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """All directed links ``(i, j)``, ``i != j``, of robots of the same team within ``radius``.

    Uses a KD-tree (``O(B log B)``), never a ``B x B`` distance matrix. Teams (Monte Carlo
    trials) are kept apart by shifting each team far along ``x`` before the search.

    Parameters
    ----------
    p : ndarray, shape (B, 2)
        Positions.
    team : ndarray of int, shape (B,)
        Team (trial) index of every robot.
    radius : float

    Returns
    -------
    i, j : ndarray of int, shape (E,)
        Sorted by ``i`` then ``j``.
    """
    if len(p) < 2:
        e = np.zeros(0, dtype=np.int64)
        return e, e.copy()
    span = float(np.ptp(p[:, 0])) + 4.0 * radius + 1.0
    shifted = p.astype(float, copy=True)
    shifted[:, 0] += team * span
    pairs = cKDTree(shifted).query_pairs(radius, output_type="ndarray")
    if len(pairs) == 0:
        e = np.zeros(0, dtype=np.int64)
        return e, e.copy()
    i = np.concatenate([pairs[:, 0], pairs[:, 1]]).astype(np.int64)
    j = np.concatenate([pairs[:, 1], pairs[:, 0]]).astype(np.int64)
    order = np.lexsort((j, i))
    return i[order], j[order]
