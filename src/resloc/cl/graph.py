"""Graph Laplacian and algebraic connectivity ``lambda2(G)``."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

__all__ = ["algebraic_connectivity", "component_lambda2", "laplacian"]


def laplacian(i: np.ndarray, j: np.ndarray, n: int) -> sp.csr_matrix:
    """Laplacian ``L = D - A`` of the undirected graph with edges ``(i, j)``.

    Parameters
    ----------
    i, j : ndarray of int, shape (E,)
        Edge endpoints; each undirected edge may appear once or in both directions.
    n : int
        Number of nodes.

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n, n)
    """
    A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    A = ((A + A.T) > 0).astype(float)
    deg = np.asarray(A.sum(axis=1)).ravel()
    return (sp.diags(deg) - A).tocsr()


def algebraic_connectivity(L: np.ndarray | sp.spmatrix) -> float:
    """Second-smallest eigenvalue of a Laplacian (0 for a disconnected graph).

    Parameters
    ----------
    L : ndarray or sparse matrix, shape (n, n)
    """
    n = L.shape[0]
    if n < 2:
        return 0.0
    dense = L.toarray() if sp.issparse(L) else np.asarray(L, float)
    w = np.linalg.eigvalsh(dense)
    # Round-off leaves ~1e-17 instead of 0 for a disconnected graph; a connected graph has
    # lambda2 >= 4 / n^2, far above this tolerance.
    tol = n * np.finfo(float).eps * max(float(w[-1]), 1.0)
    return float(w[1]) if w[1] > tol else 0.0


def component_lambda2(
    i: np.ndarray,
    j: np.ndarray,
    n: int,
    mode: str = "component",
    group: np.ndarray | None = None,
) -> np.ndarray:
    """``lambda2`` as seen by each node.

    Parameters
    ----------
    i, j : ndarray of int, shape (E,)
        Communication-graph edges.
    n : int
        Number of nodes.
    mode : {"component", "global"}
        ``global``: the whole graph's ``lambda2`` for every node (0 when disconnected).
        ``component``: the ``lambda2`` of the connected component the node belongs to
        (equal to the global value on a connected graph; 0 for an isolated node).
    group : ndarray of int, shape (n,), optional
        Independent graphs batched together (e.g. Monte Carlo trials): ``global`` is then
        taken per group. Components never span groups when no edge joins them.

    Returns
    -------
    ndarray, shape (n,)
    """
    L = laplacian(i, j, n)
    if mode == "global":
        if group is None:
            return np.full(n, algebraic_connectivity(L))
        labels = np.unique(group, return_inverse=True)[1]
    elif mode == "component":
        labels = connected_components(L, directed=False)[1]
    else:
        raise ValueError(f"lambda2 mode must be 'component' or 'global', got {mode!r}")
    ncomp = int(labels.max()) + 1 if n else 0
    out = np.zeros(n)
    if ncomp == 1:
        out[:] = algebraic_connectivity(L)
        return out
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(ncomp + 1))
    for c in range(ncomp):
        idx = order[bounds[c] : bounds[c + 1]]
        if idx.size > 1:
            out[idx] = algebraic_connectivity(L[idx][:, idx])
    return out
