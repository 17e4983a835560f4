"""Per-link memory of a robot (or a batch of robots): sparse, keyed by ``(i, j)``."""

from __future__ import annotations

import numpy as np

__all__ = ["LinkMemory", "LinkStatistic"]

_COMPILED: list = []


def _compiled_lookups():
    """:mod:`resloc.cl.kernels_memory` when the backend is numba, else None (imported on
    first use: numba's import is for commands that step an estimator; an import statement
    costs about a microsecond, and this runs a few times a step)."""
    if not _COMPILED:
        from resloc.cl import kernels_memory
        from resloc.cl.backend import backend

        _COMPILED.extend((backend, kernels_memory))
    backend, kernels_memory = _COMPILED
    return kernels_memory if backend() == "numba" else None


def _memory_kernels():
    """:mod:`resloc.cl.kernels_memory`, whatever the backend (for callers on the compiled
    path already)."""
    if not _COMPILED:
        _compiled_lookups()
    return _COMPILED[1]


def _float_rows(a, shape: tuple) -> bool:
    return (
        type(a) is np.ndarray
        and a.dtype == np.float64
        and a.shape == shape
        and a.flags.c_contiguous
    )


class LinkMemory:
    """What robot i remembers about each neighbour j it has received from.

    Stores, per directed link ``(i, j)``: the last received estimate of j (``x: (3,)``,
    ``P: (3, 3)``) and the innovation norm of the last delivered transmission. Keys are
    ``i * n_nodes + j`` kept sorted; look-ups are vectorized with ``searchsorted``, so memory
    grows with the number of links actually used, never ``N x N``.

    Optional extensions (issue 6, ``docs/beyond.md``): ``cusum``, the per-link CUSUM
    statistic of the detector (a :class:`LinkStatistic`, updated for every *evaluated* link,
    delivered or not); ``mean_cusum``, the four signed CUSUMs of the whitened innovation
    (``+w_r, -w_r, +w_b, -w_b``, likewise); ``independent``, the independent covariance parts
    ``(n_nodes, 3, 3)`` of split covariance intersection (None until a caller initializes it,
    e.g. with the initial covariances); ``joint``, the bookkeeping of ``tracked``,
    ``factorized`` or ``gauge`` fusion (:mod:`resloc.cl.tracking`, :mod:`resloc.cl.factorized`,
    :mod:`resloc.cl.gauge`), None until initialized; ``local``, True in one robot's process
    (:class:`~resloc.cl.node.RobotNode`), where end-of-step exchanges arrive as messages.

    Parameters
    ----------
    n_nodes : int
        Size of the id space of ``j`` (robots in the batch).
    """

    def __init__(self, n_nodes: int) -> None:
        self.n_nodes = int(n_nodes)
        self.keys = np.empty(0, dtype=np.int64)
        self.x = np.empty((0, 3))
        self.P = np.empty((0, 3, 3))
        self.last_norm = np.empty(0)
        self.cusum = LinkStatistic(self.n_nodes)
        self.mean_cusum = LinkStatistic(self.n_nodes, width=4)
        self.independent: np.ndarray | None = None
        self.joint = None  # JointCovariance (tracked) / FactorizedCovariance (factorized)
        # One robot's process: end-of-step exchanges arrive as messages, not from the batch.
        self.local = False
        # One robot's process: the witness statistic of this robot as a receiver, delivered
        # from the notes its neighbours' frames carried (RobotNode.receive_witness), which
        # the next correction takes instead of delivering from this memory (None: none).
        self.delivered_witness: LinkStatistic | None = None
        # ... and its view for the outvoted stage: the notes on this robot that reached it
        # (keyed (observer, 0)) beside its own sequence test (None: this memory's notes).
        self.outvoted_view: LinkMemory | None = None
        # Simulation only: the robots whose software an attacker runs (bool (B,)). No stage
        # widens their own covariance (a compromised robot would not weaken its own claims;
        # None: every robot runs the defence; detection_widening.keep_exempt).
        self.exempt: np.ndarray | None = None
        self._stage_statistics: dict[str, LinkStatistic] = {}
        # cached_rows' last gather: (keys, stores, x_link, P_link, positions), what
        # store_delivered needs to store by those positions (None: none to use)
        self._gathered: tuple | None = None

    def stage_statistic(self, name: str, width: int | None = None) -> LinkStatistic:
        """The per-link statistic a detector stage keeps under ``name`` (created empty on
        first use; a per-robot statistic is keyed ``(i, i)``)."""
        if name not in self._stage_statistics:
            self._stage_statistics[name] = LinkStatistic(self.n_nodes, width=width)
        return self._stage_statistics[name]

    def __len__(self) -> int:
        return len(self.keys)

    def lookup(self, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions of links ``(i, j)`` in the store.

        Parameters
        ----------
        i, j : ndarray of int, shape (E,)

        Returns
        -------
        found : ndarray of bool, shape (E,)
        pos : ndarray of int, shape (E,)
            Valid where ``found``.
        """
        k = np.asarray(i, np.int64) * self.n_nodes + np.asarray(j, np.int64)
        n = len(self.keys)
        if n == 0:
            return np.zeros(k.shape, dtype=bool), np.zeros(k.shape, dtype=np.intp)
        pos = np.searchsorted(self.keys, k)
        # a key past the last one lands on the last position, whose key is smaller: not found
        np.minimum(pos, n - 1, out=pos)
        return self.keys[pos] == k, pos

    def store(
        self,
        i: np.ndarray,
        j: np.ndarray,
        x: np.ndarray,
        P: np.ndarray,
        norm: np.ndarray,
    ) -> None:
        """Insert or overwrite links ``(i, j)``.

        Shapes: ``i, j, norm: (E,)``, ``x: (E, 3)``, ``P: (E, 3, 3)``.
        """
        if len(i) == 0:
            return
        if self._overwrite_compiled(i, j, x, P, norm):
            return
        found, pos = self.lookup(i, j)
        if found.all():  # every link known (a run's steady state): overwrite in place
            self.x[pos] = x
            self.P[pos] = P
            self.last_norm[pos] = norm
            return
        self.x[pos[found]] = x[found]
        self.P[pos[found]] = P[found]
        self.last_norm[pos[found]] = norm[found]
        new = ~found
        if new.any():
            k = np.asarray(i, np.int64)[new] * self.n_nodes + np.asarray(j, np.int64)[new]
            keys = np.concatenate([self.keys, k])
            order = np.argsort(keys, kind="stable")
            self.keys = keys[order]
            self.x = np.concatenate([self.x, x[new]])[order]
            self.P = np.concatenate([self.P, P[new]])[order]
            self.last_norm = np.concatenate([self.last_norm, norm[new]])[order]

    def cached_rows(self, i, j, rows, x_nb, P_nb, last_sent: bool) -> tuple:
        """The per-link inputs of ``cached`` neighbour estimates for the compiled link loop,
        by one compiled pass (:func:`resloc.cl.kernels_memory.gather_cached`): the
        transmitted estimates per link ``x_link: (E, 3)``, ``P_link: (E, 3, 3)``
        (``x_nb[rows]``, ``P_nb[rows]``), the estimates the moments use (j's last received
        where robot i has one, else the transmitted), whether there is one ``(E,)`` and,
        with ``last_sent``, the last delivered norms ``(E,)`` (else ``(0,)``). The links'
        positions are kept for :meth:`store_delivered` of the same step. Numba only; the
        arguments as the compiled path passes them (``i``, ``j``, ``rows``: int64 (E,),
        sorted by key for speed; ``x_nb``, ``P_nb``: C-contiguous float64).

        Returns ``(x_link, P_link, x_ref, P_ref, known, last)``.
        """
        kernels_memory = _memory_kernels()
        E = len(i)
        x_link, x_ref = np.empty((2, E, 3))
        P_link, P_ref = np.empty((2, E, 3, 3))
        known = np.empty(E, dtype=np.bool_)
        last = np.empty(E if last_sent else 0)
        pos = np.empty(E, np.int64)
        stores = (
            np.ascontiguousarray(self.x),
            np.ascontiguousarray(self.P),
            np.ascontiguousarray(self.last_norm),
        )
        kernels_memory.gather_cached(
            self.keys, self.n_nodes, *stores, i, j, rows, x_nb, P_nb, x_link, P_link, x_ref,
            P_ref, known, last, pos,
        )  # fmt: skip
        self._gathered = (self.keys, stores, x_link, P_link, pos)
        return x_link, P_link, x_ref, P_ref, known, last

    def store_delivered(
        self,
        i: np.ndarray,
        j: np.ndarray,
        delivered: np.ndarray,
        x: np.ndarray,
        P: np.ndarray,
        rows: np.ndarray,
        norm: np.ndarray,
    ) -> None:
        """:meth:`store` of the links a step delivered: ``(i[e], j[e])`` with ``x[rows[e]]``,
        ``P[rows[e]]`` and ``norm[e]`` for every ``e`` where ``delivered``; by one compiled
        call when every delivered link is stored (a run's steady state) and the arrays are
        as the compiled path passes them (no per-step copies of the delivered rows).

        Shapes: ``i, j, delivered, rows, norm: (E,)``, ``x: (S, 3)``, ``P: (S, 3, 3)``.
        """
        if self._store_gathered(delivered, x, P, rows, norm):
            return
        if self._overwrite_delivered(i, j, delivered, x, P, rows, norm):
            return
        d = np.flatnonzero(delivered)
        r = np.asarray(rows)[d]
        self.store(np.asarray(i)[d], np.asarray(j)[d], x[r], P[r], np.asarray(norm)[d])

    def _store_gathered(self, delivered, x, P, rows, norm) -> bool:
        """:meth:`store_delivered` at the positions :meth:`cached_rows` found, by one
        compiled call (no search), when ``x``, ``P`` are the rows it gathered and neither
        the keys nor the store's arrays changed since; False, nothing written, otherwise
        (or when a delivered link was not stored then). The gather is used once."""
        gathered, self._gathered = self._gathered, None
        if gathered is None:
            return False
        keys, stores, x_link, P_link, pos = gathered
        if not (x is x_link and P is P_link and keys is self.keys):
            return False
        if not (stores[0] is self.x and stores[1] is self.P and stores[2] is self.last_norm):
            return False  # not the store's own arrays (cached_rows read copies)
        E = len(pos)
        if not (type(delivered) is np.ndarray and delivered.dtype == np.bool_):
            return False
        rows = _memory_kernels().int64_rows(rows)
        if rows is None or len(rows) != E or delivered.shape != (E,):
            return False
        if not _float_rows(norm, (E,)):
            return False
        return _memory_kernels().store_gathered(pos, delivered, rows, x, P, norm, *stores)

    def _overwrite_delivered(self, i, j, delivered, x, P, rows, norm) -> bool:
        """:meth:`store_delivered` by one compiled call; False, nothing written, when a
        delivered link is not stored or an array is not as the compiled path passes it."""
        compiled = _compiled_lookups() if len(self.keys) else None
        if compiled is None:
            return False
        ri, rj, rr = compiled.int64_rows(i), compiled.int64_rows(j), compiled.int64_rows(rows)
        E, S, K = len(i), len(x), len(self.keys)
        if ri is None or rj is None or rr is None or len(rj) != E or len(rr) != E:
            return False
        if not (type(delivered) is np.ndarray and delivered.dtype == np.bool_):
            return False
        shapes = (x, (S, 3)), (P, (S, 3, 3)), (norm, (E,)), (self.x, (K, 3))
        shapes += (self.P, (K, 3, 3)), (self.last_norm, (K,))
        if delivered.shape != (E,) or not all(_float_rows(a, shape) for a, shape in shapes):
            return False
        stores = (self.x, self.P, self.last_norm)
        return compiled.overwrite_delivered(
            self.keys, self.n_nodes, ri, rj, delivered, rr, x, P, norm, stores,
            np.empty(E, np.int64),
        )  # fmt: skip

    def _overwrite_compiled(self, i, j, x, P, norm) -> bool:
        """:meth:`store` by one compiled call when every link is stored (a run's steady
        state) and the arrays are as the compiled path passes them; False, nothing
        written, otherwise."""
        compiled = _compiled_lookups() if len(self.keys) else None
        if compiled is None:
            return False
        ri, rj = compiled.int64_rows(i), compiled.int64_rows(j)
        E = len(i)
        if ri is None or rj is None or len(rj) != E:
            return False
        stores = (self.x, (len(self.keys), 3)), (self.P, (len(self.keys), 3, 3))
        given = (x, (E, 3)), (P, (E, 3, 3)), (norm, (E,)), (self.last_norm, (len(self.keys),))
        if not all(_float_rows(a, shape) for a, shape in (*stores, *given)):
            return False
        pos = np.empty(E, np.int64)
        return compiled.overwrite_stored(
            self.keys, self.n_nodes, ri, rj, x, P, norm, self.x, self.P, self.last_norm, pos
        )


class LinkStatistic:
    """A sparse per-link statistic keyed by ``(i, j)`` (e.g. a CUSUM statistic), 0 when unseen.

    Parameters
    ----------
    n_nodes : int
        Size of the id space of ``j``.
    width : int, optional
        None: one scalar per link (values ``(E,)``); an int: a vector per link
        (values ``(E, width)``).
    keys, values : ndarray, optional
        The store's sorted int64 keys ``i * n_nodes + j`` and their values, held as given
        (default: none).
    """

    def __init__(
        self,
        n_nodes: int,
        width: int | None = None,
        keys: np.ndarray | None = None,
        values: np.ndarray | None = None,
    ) -> None:
        self.n_nodes = int(n_nodes)
        self.keys = np.empty(0, dtype=np.int64) if keys is None else keys
        self.shape = () if width is None else (int(width),)
        self.values = np.empty((0, *self.shape)) if values is None else values
        # the stores sharing this one's keys and their saved values, when this store is a
        # group's first (resloc.cl.kernels_stores.group_slots; None: none)
        self.group = None

    @classmethod
    def holding(cls, n_nodes: int, keys: np.ndarray, values: np.ndarray) -> LinkStatistic:
        """A scalar store (``width`` None) of ``keys`` (int64, sorted) and ``values``,
        taken as they are, without the two empty arrays a new store starts with (the
        witness stage's delivered store, new each step: 0.43 us against 0.71 for an empty
        store then filled, by timeit)."""
        return cls(n_nodes, keys=keys, values=values)

    def __len__(self) -> int:
        return len(self.keys)

    def __getstate__(self) -> dict:
        # a copy (a checkpoint, an attacker's scratch memory) leaves the group behind: its
        # buffers are views of this store's arrays, which a deep copy would not keep views
        state = self.__dict__.copy()
        state["group"] = None
        return state

    def _keys(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        return np.asarray(i, np.int64) * self.n_nodes + np.asarray(j, np.int64)

    def get(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Values of links ``(i, j)``, shape (E,) or (E, width); 0 for links never stored."""
        k = self._keys(i, j)
        if not len(self.keys):
            return np.zeros((len(k), *self.shape))
        pos = np.minimum(np.searchsorted(self.keys, k), len(self.keys) - 1)
        hit = (self.keys[pos] == k).reshape((-1,) + (1,) * len(self.shape))
        return np.where(hit, self.values[pos], 0.0)

    def set(self, i: np.ndarray, j: np.ndarray, values: np.ndarray) -> None:
        """Insert or overwrite links ``(i, j)`` (distinct within one call), shape (E,)."""
        k = self._keys(i, j)
        if not len(k):
            return
        values = np.asarray(values, float)
        pos = np.minimum(np.searchsorted(self.keys, k), max(len(self.keys) - 1, 0))
        found = (pos < len(self.keys)) & (self.keys[pos] == k) if len(self.keys) else (k < 0)
        self.values[pos[found]] = values[found]
        new = ~found
        if new.any():
            keys = np.concatenate([self.keys, k[new]])
            order = np.argsort(keys, kind="stable")
            self.keys = keys[order]
            self.values = np.concatenate([self.values, values[new]])[order]

    def slots(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Positions of links ``(i, j)`` in :attr:`values`, inserting the missing ones with
        0 (what :meth:`get` gives a link never stored), so that a compiled loop can read and
        write each link's statistic in place.

        Parameters
        ----------
        i, j : ndarray of int, shape (E,)

        Returns
        -------
        ndarray of int64, shape (E,)
        """
        compiled = _compiled_lookups() if len(self.keys) else None
        if compiled is not None:  # every link stored before (a run's steady state)
            ri, rj = compiled.int64_rows(i), compiled.int64_rows(j)
            if ri is not None and rj is not None and len(ri) == len(rj):
                pos = np.empty(len(ri), np.int64)
                if compiled.stored_positions(self.keys, self.n_nodes, ri, rj, pos):
                    return pos
        k = self._keys(i, j)
        if len(k):
            pos = np.searchsorted(self.keys, k)
            found = pos < len(self.keys)
            found[found] = self.keys[pos[found]] == k[found]
            if not found.all():
                new = np.unique(k[~found])
                keys = np.concatenate([self.keys, new])
                order = np.argsort(keys, kind="stable")
                self.keys = keys[order]
                zeros = np.zeros((len(new), *self.shape))
                self.values = np.ascontiguousarray(np.concatenate([self.values, zeros])[order])
        return np.searchsorted(self.keys, k).astype(np.int64)
