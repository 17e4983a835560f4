"""Sequence test on a robot's innovations: a per-robot CUSUM of the NIS over all its links.

The per-link CUSUMs (:mod:`resloc.cl.cusum`) watch one neighbour at a time; an attacker
that spreads a lie over several links of one robot (a coordinated, displaced-robot lie, or
an attacker that rotates the link it uses) keeps each link's statistic low. This stage runs
Page's CUSUM on the NIS of *every* measurement robot i evaluates, whichever the neighbour:

``g_i <- min(max(0, g_i + sum_rows (NIS - k)), cap)``

(rows of robot i in one call summed: the ``summed`` update evaluates them together), alarms
while ``g_i > h`` and then discards robot i's measurements whose own NIS exceeds ``k``
(as the per-link CUSUM does: honest-looking measurements still pass). Under no attack
``E[NIS] = 2 < k``; the statistic is keyed ``(i, i)`` in the robot's
:class:`~resloc.cl.memory.LinkMemory`, so it needs nothing from the neighbours and runs in
one robot's process.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from resloc.cl.cusum import cusum_alarm, nis
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams, at_robots

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = ["RobotCusum", "robot_cusum"]


def robot_cusum(
    g: np.ndarray, i: np.ndarray, stat: np.ndarray, k: np.ndarray, cap: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """One per-robot CUSUM step over rows that may repeat a robot.

    Parameters
    ----------
    g : ndarray, shape (U,)
        Statistics of the distinct robots ``robots`` (see Returns).
    i : ndarray of int, shape (E,)
        Observer of each row.
    stat : ndarray, shape (E,)
        NIS of each row.
    k, cap : ndarray, shape (E,)
        Reference and cap at each row.

    Returns
    -------
    robots : ndarray of int, shape (U,)
        The distinct observers (sorted), the order of ``g``.
    g_new : ndarray, shape (U,)
    """
    robots, inverse = np.unique(i, return_inverse=True)
    excess = np.bincount(inverse, weights=stat - k, minlength=len(robots))
    cap_r = np.full(len(robots), np.inf)
    np.minimum.at(cap_r, inverse, cap)
    return robots, np.minimum(np.maximum(g + excess, 0.0), cap_r)


class RobotCusum:
    """Per-robot CUSUM of the NIS (all of a robot's links together)."""

    name: ClassVar[str] = "robot_cusum"
    compiled: ClassVar[bool] = True
    overrides: ClassVar[bool] = False

    def active(self, params: CLParams) -> bool:
        return bool(params.robot_cusum)

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        if memory is None:
            raise ValueError("detector robot CUSUM (params.robot_cusum) needs a LinkMemory")
        ev = evidence
        store = memory.stage_statistic(self.name)
        stat = nis(ev.nu, ev.S)
        E = len(stat)
        k = np.broadcast_to(at_robots(params.robot_cusum_k, ev.i), (E,)).astype(float)
        h = np.broadcast_to(at_robots(params.robot_cusum_h, ev.i), (E,)).astype(float)
        # Only what the gate passed feeds the statistic (a gross outlier is already out).
        passed = ~ev.gated
        if passed.any():
            fed = np.unique(ev.i[passed])
            r, g_new = robot_cusum(
                store.get(fed, fed),
                ev.i[passed],
                stat[passed],
                k[passed],
                2.0 * h[passed],
            )
            store.set(r, r, g_new)
        return cusum_alarm(store.get(ev.i, ev.i), h) & (stat > k)
