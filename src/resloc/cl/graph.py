"""Graph Laplacian and algebraic connectivity ``lambda2(G)``.

Graphs of at most :data:`DENSE_MAX` nodes (a team of robots, a few trials) are handled with
dense numpy arrays only; :mod:`scipy.sparse` is imported when a larger graph needs it (its
import costs about a fifth of a second, more than a whole small run's graph work).
"""

from __future__ import annotations

import enum
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import scipy.sparse as sp

__all__ = [
    "DENSE_MAX",
    "Lambda2Memo",
    "Lambda2Source",
    "algebraic_connectivity",
    "component_labels",
    "component_lambda2",
    "dense_laplacian",
    "laplacian",
]


class Lambda2Source(enum.StrEnum):
    """Which ``lambda2`` a robot's trigger divides by (eq. 11).

    ``component``: of the robot's connected component of the communication graph.
    ``global``: of the whole graph (0 while it is disconnected).
    ``distributed``: the robot's own estimate (:mod:`resloc.cl.connectivity`).
    """

    COMPONENT = "component"
    GLOBAL = "global"
    DISTRIBUTED = "distributed"

    @property
    def graph_mode(self) -> str:
        """The ``mode`` of :func:`component_lambda2` giving the true value (a distributed
        estimate is scored against its component's)."""
        return "global" if self is Lambda2Source.GLOBAL else "component"


#: Graphs (or components) of at most this many nodes use the dense symmetric eigensolver;
#: larger ones a sparse shift-invert Lanczos solver (``O(n^1.5)`` for planar-like graphs
#: instead of ``O(n^3)``, and no ``n x n`` array). Both agree to ~1e-13 relative.
DENSE_MAX = 256

#: Shift of the shift-invert solver: ``(L + SHIFT I)`` is factorized (``L`` is singular).
SHIFT = 1e-6


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
    import scipy.sparse as sp

    A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    A = ((A + A.T) > 0).astype(float)
    deg = np.asarray(A.sum(axis=1)).ravel()
    return (sp.diags(deg) - A).tocsr()


def algebraic_connectivity(L: np.ndarray | sp.spmatrix) -> float:
    """Second-smallest eigenvalue of a Laplacian (0 for a disconnected graph).

    Dense ``eigvalsh`` up to :data:`DENSE_MAX` nodes (or for a dense ``L``); above, for a
    sparse ``L``, a connectivity check (``O(n + E)``) then shift-invert Lanczos
    (:func:`scipy.sparse.linalg.eigsh`, two eigenvalues nearest ``-SHIFT``).

    Parameters
    ----------
    L : ndarray or sparse matrix, shape (n, n)
    """
    n = L.shape[0]
    if n < 2:
        return 0.0
    if isinstance(L, np.ndarray):
        return float(_dense_lambda2(np.asarray(L, float)[None])[0])
    import scipy.sparse as sp

    if sp.issparse(L) and n > DENSE_MAX:
        return _sparse_lambda2(sp.csr_matrix(L))
    dense = L.toarray() if sp.issparse(L) else np.asarray(L, float)
    return float(_dense_lambda2(dense[None])[0])


def _dense_lambda2(L: np.ndarray) -> np.ndarray:
    """``lambda2`` of a stack of dense Laplacians ``(C, n, n)`` -> ``(C,)``."""
    n = L.shape[-1]
    w = np.linalg.eigvalsh(L)
    # Round-off leaves ~1e-17 instead of 0 for a disconnected graph; a connected graph has
    # lambda2 >= 4 / n^2, far above this tolerance.
    tol = n * np.finfo(float).eps * np.maximum(w[:, -1], 1.0)
    return np.where(w[:, 1] > tol, w[:, 1], 0.0)


def _sparse_lambda2(L: sp.csr_matrix) -> float:
    """``lambda2`` of a large sparse Laplacian: 0 if disconnected, else shift-invert."""
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import eigsh

    if connected_components(L, directed=False)[0] > 1:
        return 0.0
    n = L.shape[0]
    # Deterministic start vector: ARPACK's default is random.
    v0 = np.cos(np.arange(n) * 0.7548776662466927) + 1.0
    w = eigsh(L.tocsc(), k=2, sigma=-SHIFT, which="LM", tol=0.0, v0=v0, return_eigenvectors=False)
    return float(max(np.sort(w)[1], 0.0))


class Lambda2Memo:
    """Memo of ``lambda2`` of large components between calls of :func:`component_lambda2`.

    A component whose node set and edges did not change since the previous call keeps its
    value without a new eigensolve (in a moving swarm most components are unchanged from
    one step to the next; only the changed ones are solved again).
    """

    def __init__(self) -> None:
        self.values: dict[bytes, float] = {}
        self.solves = 0
        self.hits = 0


def _component_key(idx: np.ndarray, sub: sp.csr_matrix) -> bytes:
    return b"|".join(
        (
            idx.astype(np.int64).tobytes(),
            sub.indptr.tobytes(),
            sub.indices.tobytes(),
            sub.data.tobytes(),
        )
    )


def component_lambda2(
    i: np.ndarray,
    j: np.ndarray,
    n: int,
    mode: str = "component",
    group: np.ndarray | None = None,
    memo: Lambda2Memo | None = None,
) -> np.ndarray:
    """``lambda2`` as seen by each node.

    Components (or groups) of equal size up to :data:`DENSE_MAX` nodes are solved together
    by one batched dense ``eigvalsh`` (no Python loop over them); larger ones one by one by
    the sparse solver of :func:`algebraic_connectivity`, skipped when ``memo`` holds the
    same component from the previous call. Time and memory are linear in the number of
    nodes for bounded component sizes.

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
    memo : Lambda2Memo, optional
        Values of large components kept from the previous call (updated in place).

    Returns
    -------
    ndarray, shape (n,)
    """
    if mode not in ("component", "global"):
        raise ValueError(f"lambda2 mode must be 'component' or 'global', got {mode!r}")
    if n <= DENSE_MAX:
        return _small_graph_lambda2(i, j, n, mode, group)
    from scipy.sparse.csgraph import connected_components

    L = laplacian(i, j, n)
    if mode == "global":
        if group is None:
            return np.full(n, algebraic_connectivity(L))
        labels = np.unique(group, return_inverse=True)[1]
    elif mode == "component":
        labels = connected_components(L, directed=False)[1]
    else:
        raise ValueError(f"lambda2 mode must be 'component' or 'global', got {mode!r}")
    out = np.zeros(n)
    if n == 0:
        return out
    labels = np.asarray(labels, dtype=np.int64)
    ncomp = int(labels.max()) + 1
    if ncomp == 1:
        out[:] = algebraic_connectivity(L)
        return out
    order, bounds, size = _component_extents(labels, ncomp)
    local = np.empty(n, dtype=np.int64)  # position of each node inside its component
    local[order] = np.arange(n) - bounds[labels[order]]
    # Small components: one batched dense eigensolve per distinct size.
    coo = L.tocoo()
    same = labels[coo.row] == labels[coo.col]
    rows, cols, vals = coo.row[same], coo.col[same], coo.data[same]
    comp_of_entry = labels[rows]
    for s in np.unique(size[(size > 1) & (size <= DENSE_MAX)]):
        comps = np.flatnonzero(size == s)
        slot = np.full(ncomp, -1, dtype=np.int64)
        slot[comps] = np.arange(len(comps))
        sel = slot[comp_of_entry] >= 0
        stack = np.zeros((len(comps), s, s))
        stack[slot[comp_of_entry[sel]], local[rows[sel]], local[cols[sel]]] = vals[sel]
        lam = _dense_lambda2(stack)
        node_slot = slot[labels]
        keep = node_slot >= 0
        out[keep] = lam[node_slot[keep]]
    # Large components: sparse solver, memoized across calls.
    values: dict[bytes, float] = {}
    for c in np.flatnonzero(size > DENSE_MAX):
        idx = order[bounds[c] : bounds[c + 1]]
        sub = L[idx][:, idx].tocsr()
        key = _component_key(idx, sub)
        if memo is not None and key in memo.values:
            lam2 = memo.values[key]
            memo.hits += 1
        else:
            lam2 = algebraic_connectivity(sub)
            if memo is not None:
                memo.solves += 1
        values[key] = lam2
        out[idx] = lam2
    if memo is not None:
        memo.values = values
    return out


def _component_extents(labels: np.ndarray, ncomp: int):
    """The nodes grouped by component: ``order`` (nodes sorted by component, stable, shape
    (n,)), ``bounds`` (component ``c`` is ``order[bounds[c]:bounds[c + 1]]``, shape
    (ncomp + 1,)) and ``size`` (nodes per component, shape (ncomp,))."""
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(ncomp + 1))
    return order, bounds, np.diff(bounds)


def dense_laplacian(i: np.ndarray, j: np.ndarray, n: int) -> np.ndarray:
    """:func:`laplacian` as a dense ``(n, n)`` array (the same values: integer degrees on
    the diagonal, ``-1`` per undirected edge), for graphs small enough to hold densely."""
    A = np.zeros((n, n))
    A[i, j] = 1.0
    A[j, i] = 1.0
    return np.diag(A.sum(axis=1)) - A


def component_labels(i: np.ndarray, j: np.ndarray, n: int) -> np.ndarray:
    """Connected component of every node of the undirected graph with edges ``(i, j)``,
    numbered ``0 .. C - 1`` in order of each component's smallest node, shape (n,).

    Minimum-label propagation with pointer jumping: every node takes the smallest label
    among itself and its neighbours until nothing changes (a few rounds for the graphs of
    a team; the number of rounds is bounded by the components' diameters).
    """
    label = np.arange(n)
    if len(i):
        while True:
            nxt = label.copy()
            np.minimum.at(nxt, i, label[j])
            np.minimum.at(nxt, j, label[i])
            nxt = nxt[nxt]  # jump: a label is a node whose own label may be smaller still
            if np.array_equal(nxt, label):
                break
            label = nxt
    return np.unique(label, return_inverse=True)[1].astype(np.int64)


def _small_graph_lambda2(
    i: np.ndarray, j: np.ndarray, n: int, mode: str, group: np.ndarray | None
) -> np.ndarray:
    """:func:`component_lambda2` of a graph of at most :data:`DENSE_MAX` nodes, dense: the
    same Laplacian values and the same batched eigensolve of each component's block (nodes
    in increasing order), so the same numbers as the sparse path, without scipy."""
    out = np.zeros(n)
    if n == 0:
        return out
    L = dense_laplacian(np.asarray(i, np.int64), np.asarray(j, np.int64), n)
    if mode == "global":
        if group is None:
            return np.full(n, algebraic_connectivity(L))
        labels = np.unique(group, return_inverse=True)[1].astype(np.int64)
    else:
        labels = component_labels(np.asarray(i, np.int64), np.asarray(j, np.int64), n)
    ncomp = int(labels.max()) + 1
    if ncomp == 1:
        out[:] = algebraic_connectivity(L)
        return out
    order, bounds, size = _component_extents(labels, ncomp)
    for s in np.unique(size[size > 1]):
        comps = np.flatnonzero(size == s)
        nodes = order[bounds[comps][:, None] + np.arange(s)]  # (C, s), increasing per row
        lam = _dense_lambda2(L[nodes[:, :, None], nodes[:, None, :]])
        out[nodes] = lam[:, None]
    return out
