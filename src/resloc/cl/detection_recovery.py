"""Recovery after rejection runs: a detector that can never lock a robot out.

Every per-measurement test (the raw-norm gate, the NIS gate, the CUSUMs) assumes the
robot's own estimate is consistent with its covariance. When it is not (a robot that went
a long time without sightings and drifted more than its odometry model says, or one whose
filter became overconfident), *every* honest measurement looks like an attack, every one is
discarded, and nothing ever corrects the estimate: a lock-out (measured on MRCLAM with the
paper's raw-norm detector: about 85 s of rejected sightings after a 40 s gap).

This stage keeps, per robot i, the number ``n_i`` of its *consecutive* discarded
measurements (every stage's verdict, all its links and landmarks together; any accepted
measurement resets it to 0). Once ``n_i >= R`` (``recovery_after``) the robot is in
recovery and a discarded measurement is re-admitted when its NIS, with the innovation
covariance inflated by

``f = min(2^((n - R) / R), G_i, f_max)``

(doubling every ``R`` further rejections, capped at ``recovery_inflation_cap``, and at the
robot's own covariance growth ``G_i = tr P_i,pos / tr P_i,pos(last acceptance)``, the factor
by which its position covariance grew since a measurement last passed the ordinary tests),
passes the chi-square gate ``NIS / f <= g`` (``g = recovery_gate``, in NIS units), and the update
then uses the robot's covariance inflated by ``f(n)`` (a re-admitted measurement fused with
the overconfident covariance would barely move the estimate, and the next one would be
rejected again). The inflation stands for the model error the filter does not know about;
it grows only while *nothing* gets through.

Bound (what an attacker gains from the recovery). To put robot i into recovery the attacker
must have every measurement of robot i discarded ``R`` times in a row: a single honest
measurement that passes resets the count, so an attacker controlling only some of a robot's
links never triggers it. Once in recovery, a measurement is re-admitted only with ``NIS <= g
min(G_i, f_max)``: an innovation of at most ``sqrt(g min(G_i, f_max))`` innovation standard
deviations, where ``G_i`` is the growth of the robot's own position covariance since its
last ordinary acceptance. The attacker cannot speed that growth up: it is the filter's dead-
reckoning growth over the time the attacker kept every measurement of the robot rejected (a
lie of ``b`` standard deviations needs ``G_i >= b^2 / g`` and at least ``R (1 + log2(b^2 /
g))`` consecutive rejections; never when ``b^2 > f_max g``). A robot that truly lost its
sightings for a long time has a large ``G_i``, so it recovers. While re-admissions go on the
count is frozen (the robot stays at that inflation); it restarts at 0 only when a
measurement passes the ordinary tests. A persistent lie of ``b`` sigmas therefore displaces
the robot by at most that lie (the estimate moves to agree with it, after which it passes
the ordinary gate), and each further ``b`` sigmas of displacement costs the attacker another
run of ``R (1 + log2(b^2 / g))`` measurements all of which it must control. Against an
attacker that controls every sighting of a robot no detector run by that robot alone can
tell a lie from a displacement; the bound limits how far and how fast it can steer it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from resloc.cl.cusum import nis
from resloc.cl.memory import LinkMemory, LinkStatistic
from resloc.cl.params import CLParams, at_robots

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = ["RejectionRecovery", "recovery_inflation", "update_rejection_runs"]


def recovery_inflation(
    run: np.ndarray, after: float | np.ndarray, cap: float | np.ndarray
) -> np.ndarray:
    """Inflation ``f(n) = min(2^((n - R) / R), f_max)`` of the innovation covariance.

    Parameters
    ----------
    run : ndarray, shape (E,)
        Consecutive discarded measurements ``n`` of each link's observer.
    after : float or ndarray, shape (E,)
        ``R``: recovery starts at ``n >= R`` (``f(R) = 1``).
    cap : float or ndarray, shape (E,)
        ``f_max``.

    Returns
    -------
    ndarray, shape (E,)
        ``f(n)``, ``nan`` where ``n < R`` (not in recovery).
    """
    after = np.asarray(after, dtype=float)
    f = np.minimum(np.exp2((run - after) / after), cap)
    return np.where(run >= after, f, np.nan)


def update_rejection_runs(
    runs: LinkStatistic,
    i: np.ndarray,
    discarded: np.ndarray,
    readmitted: np.ndarray | None = None,
) -> None:
    """Count each robot's consecutive discarded measurements (in place).

    Parameters
    ----------
    runs : LinkStatistic
        Per-robot counts, keyed ``(i, i)``.
    i : ndarray of int, shape (E,)
        Observers (a robot may appear on several rows: the ``summed`` update).
    discarded : ndarray of bool, shape (E,)
        The final verdict on each row.
    readmitted : ndarray of bool, shape (E,), optional
        Rows accepted only by the recovery (not by the ordinary stages).

    Notes
    -----
    A robot with a row the ordinary stages accepted restarts at 0; one whose accepted rows
    were all re-admitted keeps its count (it stays in recovery at the same inflation until
    its measurements pass the ordinary tests again); one with only discarded rows adds
    their number.
    """
    readmitted = np.zeros(len(i), bool) if readmitted is None else readmitted
    robots, inverse = np.unique(i, return_inverse=True)
    n_discarded = np.bincount(inverse, weights=discarded.astype(float), minlength=len(robots))
    n_readmitted = np.bincount(inverse, weights=readmitted.astype(float), minlength=len(robots))
    n_rows = np.bincount(inverse, minlength=len(robots))
    previous = runs.get(robots, robots)
    passed = n_rows - n_discarded - n_readmitted > 0
    kept = np.where(n_readmitted > 0, previous, previous + n_discarded)
    runs.set(robots, robots, np.where(passed, 0.0, kept))


def _runs(memory: LinkMemory) -> LinkStatistic:
    return memory.stage_statistic("recovery", width=None)


class RejectionRecovery:
    """Re-admit measurements of a robot locked out by ``R`` consecutive rejections.

    Runs after every other stage and overrides their verdict (:attr:`overrides`).
    """

    name: ClassVar[str] = "recovery"
    compiled: ClassVar[bool] = True
    overrides: ClassVar[bool] = True

    def active(self, params: CLParams) -> bool:
        return bool(params.recovery)

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        if memory is None:
            raise ValueError("detector recovery (params.recovery) needs a LinkMemory")
        ev = evidence
        runs = _runs(memory)
        spread = memory.stage_statistic("recovery_spread")
        detected = ev.detected.copy()
        start = runs.get(ev.i, ev.i)
        f = recovery_inflation(
            start,
            at_robots(params.recovery_after, ev.i),
            at_robots(params.recovery_inflation_cap, ev.i),
        )
        # The robot's position covariance now and at its last ordinary acceptance (0: none
        # yet, then only the cap bounds the inflation).
        trace = np.trace(ev.P_obs[:, :2, :2], axis1=1, axis2=2) if ev.P_obs is not None else None
        if trace is not None:
            before = spread.get(ev.i, ev.i)
            with np.errstate(divide="ignore", invalid="ignore"):
                growth = np.where(before > 0.0, trace / before, np.inf)
            f = np.minimum(f, np.maximum(growth, 1.0))
            passed = ~detected
            if passed.any():
                robots, first = np.unique(ev.i[passed], return_index=True)
                spread.set(robots, robots, trace[passed][first])
        candidates = detected & np.isfinite(f)
        readmitted = np.zeros(len(detected), bool)
        if candidates.any():
            c = np.flatnonzero(candidates)
            stat = nis(ev.nu[c], ev.S[c]) / f[c]
            readmit = stat <= at_robots(params.recovery_gate, ev.i[c])
            detected[c[readmit]] = False
            readmitted[c[readmit]] = True
            inflation = np.ones(len(detected))
            inflation[c[readmit]] = f[c[readmit]]
            ev.inflation = inflation
        update_rejection_runs(runs, ev.i, detected, readmitted)
        return detected
