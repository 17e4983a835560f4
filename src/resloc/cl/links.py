"""What one CL step is given and what it decides, one row per directed link ``(i, j)``."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["LinkBatch", "LinkOutcome", "NeighbourStates"]


@dataclass(frozen=True)
class NeighbourStates:
    """The neighbours' estimates of a :class:`LinkBatch` by reference: link ``e`` reads
    ``x[index[e]]`` and ``P[index[e]]`` (e.g. the step's predicted arrays), so that the
    ``(E, 3)`` and ``(E, 3, 3)`` copies are made only if someone reads ``x_nb``/``P_nb``.

    Attributes
    ----------
    index : ndarray of int, shape (E,)
    x : ndarray, shape (S, 3)
    P : ndarray, shape (S, 3, 3)
    """

    index: np.ndarray
    x: np.ndarray
    P: np.ndarray


@dataclass
class LinkBatch:
    """The relative measurements of one step, one row per directed link ``(i, j)``.

    Rows must be sorted by ``i`` (then by ``j``: the sequential update order).

    Attributes
    ----------
    i : ndarray of int, shape (E,)
        Observer, as an index into the batch ``[0, B)``.
    j : ndarray of int, shape (E,)
        Observed robot's id (used only as a key of the per-link memory).
    z : ndarray, shape (E, 2)
        Measured ``[range, bearing]`` (possibly falsified).
    x_nb : ndarray, shape (E, 3)
        Neighbour j's current predicted estimate: what a transmission would carry.
    P_nb : ndarray, shape (E, 3, 3)
    channel_ok : ndarray of bool, shape (E,)
        Whether a transmission on this link would get through (False in a jammed CDZ).
    risk_s, risk_c : ndarray, shape (B,)
        ``Ds(i)``, ``Dc(i)`` for every robot of the batch.
    lambda2 : ndarray, shape (B,)
        Algebraic connectivity seen by every robot of the batch.
    tamper : callable ``(rows, z_hat, S) -> z``, optional
        Issue 6: an adversary that sees robot i's predicted measurement ``(len(rows), 2)``
        and innovation covariance ``(len(rows), 2, 2)`` of ``rows`` and returns the
        measurements i receives there (the stealthy attacker of
        :mod:`resloc.world.adversary`, supplied by the simulator). None: ``z`` as is.
    P_nb_ind : ndarray, shape (E, 3, 3), optional
        Independent part of ``P_nb`` (split covariance intersection, transmitted with it).
    neighbours : NeighbourStates, optional
        Where ``x_nb`` and ``P_nb`` come from when they are given as None (the simulator's
        form, :meth:`from_predicted`): the copies are gathered on first read and kept, so
        that every reader (the numpy path, an attacker that alters them) sees ordinary
        arrays, while the compiled kernel reads the estimates by index and copies nothing.
    z_reciprocal : ndarray, shape (E,), optional
        The range neighbour j reported of the same pair this step (``nan``: none): what
        zone-aware trust (:mod:`resloc.cl.detection_zone`) substitutes for a reading taken
        inside a danger zone. None: the correction takes it from the batch's reverse links.
    """

    i: np.ndarray
    j: np.ndarray
    z: np.ndarray
    x_nb: np.ndarray
    P_nb: np.ndarray
    channel_ok: np.ndarray
    risk_s: np.ndarray
    risk_c: np.ndarray
    lambda2: np.ndarray
    tamper: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None
    P_nb_ind: np.ndarray | None = None
    neighbours: NeighbourStates | None = None
    z_reciprocal: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.i)

    @classmethod
    def from_predicted(
        cls,
        i: np.ndarray,
        j: np.ndarray,
        z: np.ndarray,
        x: np.ndarray,
        P: np.ndarray,
        channel_ok: np.ndarray,
        risk_s: np.ndarray,
        risk_c: np.ndarray,
        lambda2: np.ndarray,
        **extras,
    ) -> LinkBatch:
        """The links of a batch whose neighbours are members of the same batch: ``j`` are
        batch indices and the transmitted estimates are ``x[j]``, ``P[j]`` (the predicted
        arrays ``x: (B, 3)``, ``P: (B, 3, 3)``), held by reference (:class:`NeighbourStates`).
        ``extras``: the optional fields (``tamper``, ``P_nb_ind``)."""
        source = NeighbourStates(np.asarray(j), x, P)
        return cls(
            i, j, z, None, None, channel_ok, risk_s, risk_c, lambda2, **extras, neighbours=source
        )

    def neighbour_rows(self) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
        """``(index, x, P)`` with link ``e``'s neighbour estimate at ``x[index[e]]``,
        ``P[index[e]]``, without copying when nobody has read ``x_nb``/``P_nb``; ``index``
        is None when the estimates are the per-link arrays themselves (row ``e``)."""
        stored_x = self.__dict__.get("_x_nb")
        stored_P = self.__dict__.get("_P_nb")
        if stored_x is None and stored_P is None and self.neighbours is not None:
            return self.neighbours.index, self.neighbours.x, self.neighbours.P
        return None, self.x_nb, self.P_nb


class _GatheredOnRead:
    """``LinkBatch.x_nb``/``P_nb``: the array given, or gathered once from
    ``LinkBatch.neighbours`` when None was given."""

    def __init__(self, name: str, part: str) -> None:
        self.slot = "_" + name
        self.part = part

    def __get__(self, obj, owner=None):
        if obj is None:
            return self
        value = obj.__dict__.get(self.slot)
        if value is None and obj.neighbours is not None:
            source = obj.neighbours
            value = getattr(source, self.part)[source.index]
            obj.__dict__[self.slot] = value
        return value

    def __set__(self, obj, value) -> None:
        obj.__dict__[self.slot] = value


# Installed after the dataclass is made: its __init__ then stores through them.
LinkBatch.x_nb = _GatheredOnRead("x_nb", "x")  # type: ignore[assignment]
LinkBatch.P_nb = _GatheredOnRead("P_nb", "P")  # type: ignore[assignment]


@dataclass
class LinkOutcome:
    """What happened on every link of a :class:`LinkBatch`.

    Attributes
    ----------
    norm : ndarray, shape (E,)
        Trigger-norm of the innovation ``||Lambda_ij||`` (eq. 9).
    threshold : ndarray, shape (E,)
        ``delta_ij`` of eq. (11) (``nan`` where the detector discarded the link first).
    detected : ndarray of bool, shape (E,)
        Discarded by the attack detector.
    triggered : ndarray of bool, shape (E,)
        A transmission was attempted (eq. 10).
    delivered : ndarray of bool, shape (E,)
        The transmission got through (``sigma_ij = 1``).
    fused : ndarray of bool, shape (E,)
        ``z_ij`` was used in a Kalman update.
    repaired : ndarray of bool, shape (E,)
        The observer's covariance had to be projected back to positive definite after this
        link's update (``summed`` updates: on the robot's first fused link).
    compiled : bool
        The compiled kernel computed the outcome (else the numpy reference path).
    """

    norm: np.ndarray
    threshold: np.ndarray
    detected: np.ndarray
    triggered: np.ndarray
    delivered: np.ndarray
    fused: np.ndarray
    repaired: np.ndarray
    compiled: bool = False

    @property
    def repairs(self) -> int:
        """Covariances that had to be projected back to positive definite."""
        return int(np.count_nonzero(self.repaired))

    @classmethod
    def empty(cls, E: int) -> LinkOutcome:
        return cls(np.full(E, np.nan), np.full(E, np.nan), *np.zeros((5, E), dtype=bool))
