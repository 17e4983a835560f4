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

``f = min(2^((n - R) / R), G_i, f_max)`` (further capped below, ``A_i``)

(doubling every ``R`` further rejections, capped at ``recovery_inflation_cap``, and at the
robot's own covariance growth ``G_i = tr P_i,pos / tr P_i,pos(last acceptance)``, the factor
by which its position covariance grew since a measurement last passed the ordinary tests),
passes the chi-square gate ``NIS / f <= g`` (``g = recovery_gate``, in NIS units), and the
update then uses the robot's covariance inflated by ``f`` (a re-admitted measurement fused
with the overconfident covariance would barely move the estimate, and the next one would be
rejected again). The inflation stands for the model error the filter does not know about;
it grows only while *nothing* gets through.

The inflation stays in the covariance: the update's posterior keeps ``f P_i`` in the
directions the measurement does not observe (a robot that drifted in heading needs that:
its heading covariance must grow to the error, which one range and bearing do not fix).
So it compounds: the next re-admission inflates the already inflated covariance again, and
``G_i``, measured on it, allows more. Under a persistent lie (every sighting of a robot
rejected, then re-admitted, step after step) the covariance grew by up to ``f`` per
re-admission and the estimates diverged (MSLE ratios 1e11 to 1e88 in the adversary suite,
where the same stages without the recovery stayed finite). The stage therefore keeps
``A_i``, the product of the inflations applied since the robot's last ordinary acceptance
(1 after it), and a re-admission applies at most ``f_max^2 / A_i``:

``f = min(2^((n - R) / R), G_i, f_max, max(f_max^2 / A_i, 1))``,  ``A_i <- A_i f``.

Between two ordinary acceptances the recovery multiplies the robot's covariance by at most
``f_max^2`` in all (``f_max`` per re-admission, as before). Why ``f_max^2`` and not
``f_max``: a robot back from a 40 s blackout with 2 m and 0.8 rad of drift needs about
``5 10^3`` (measured: 16, then 18 twice, in tests/test_defence_recovery.py), and a total of
``f_max = 100`` leaves it lost. The alternatives considered, a growth reference reset at
each re-admission and a posterior from the uninflated prior (Joseph form with the inflated
gain), both remove the heading inflation the honest recovery needs: measured, neither
brings that robot back.

Bound (what an attacker gains from the recovery). To put robot i into recovery the attacker
must have every measurement of robot i discarded ``R`` times in a row: a single honest
measurement that passes resets the count, so an attacker controlling only some of a robot's
links never triggers it. Once in recovery, a measurement is re-admitted only with ``NIS <= g
min(G_i, f_max)``: an innovation of at most ``sqrt(g min(G_i, f_max))`` innovation standard
deviations, where ``G_i`` is the growth of the robot's own position covariance since its
last ordinary acceptance. The attacker cannot speed that growth up beyond ``f_max^2``: it is
the filter's dead-reckoning growth over the time the attacker kept every measurement of the
robot rejected, times the inflations re-admissions applied since, at most ``f_max^2`` (a
lie of ``b`` standard deviations needs ``G_i >= b^2 / g`` and at least ``R (1 + log2(b^2 /
g))`` consecutive rejections; never when ``b^2 > f_max g``). A robot that
truly lost its sightings for a long time has a large ``G_i``, so it recovers. While
re-admissions go on the count is frozen; it restarts at 0 only when a measurement passes the
ordinary tests. A persistent lie of ``b`` sigmas therefore displaces the robot by at most
that lie (the estimate moves to agree with it, after which it passes the ordinary gate), and
each further ``b`` sigmas of displacement costs the attacker another run of ``R (1 +
log2(b^2 / g))`` measurements all of which it must control. What the attacker cannot do
any more is grow the robot's covariance without bound by keeping it in recovery: between
two ordinary acceptances all re-admissions together inflate it by at most ``f_max^2``, so
the gate's acceptance region (and the estimate) stays finite. Against an attacker that
controls every sighting of a robot no detector run by that robot alone can tell a lie from a
displacement; the bound limits how far and how fast it can steer it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from resloc.cl.cusum import nis
from resloc.cl.memory import LinkMemory, LinkStatistic
from resloc.cl.params import CLParams, at_robots

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = [
    "RejectionRecovery",
    "recovery_inflation",
    "remaining_inflation",
    "update_rejection_runs",
]


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
    with np.errstate(over="ignore"):  # a long run: 2**n is inf, and the cap applies
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
        applied = memory.stage_statistic("recovery_applied")
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
        # What the cap leaves after the inflations already in the covariance.
        before_applied = applied.get(ev.i, ev.i)
        f = remaining_inflation(f, before_applied, at_robots(params.recovery_inflation_cap, ev.i))
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
        _record_applied(applied, ev.i, before_applied, ~ev.detected, readmitted, f)
        update_rejection_runs(runs, ev.i, detected, readmitted)
        return detected


def remaining_inflation(f: np.ndarray, applied: np.ndarray, cap: float | np.ndarray) -> np.ndarray:
    """The inflation a re-admission may apply, ``min(f, f_max / A_i)`` (``nan`` stays).

    Parameters
    ----------
    f : ndarray, shape (E,)
        ``min(2^((n - R) / R), G_i, f_max)`` (``nan``: not in recovery).
    applied : ndarray, shape (E,)
        ``A_i``: the product of the inflations re-admissions applied to robot i's covariance
        since its last ordinary acceptance (0 or 1: none).
    cap : float or ndarray, shape (E,)
        ``f_max``.

    Returns
    -------
    ndarray, shape (E,)
        At least 1 where ``f`` is finite: ``A_i`` never exceeds ``f_max``.
    """
    total = np.square(cap)
    return np.minimum(f, np.maximum(total / np.maximum(applied, 1.0), 1.0))


def _record_applied(
    applied: LinkStatistic,
    i: np.ndarray,
    before: np.ndarray,
    passed: np.ndarray,
    readmitted: np.ndarray,
    f: np.ndarray,
) -> None:
    """``A_i``: back to 1 (stored 0) for a robot with a row the ordinary stages passed;
    times the applied inflation for one whose rows were re-admitted (the rows of one robot
    in one call share ``f``); else unchanged."""
    touched = passed | readmitted
    if not touched.any():
        return
    value = np.where(passed, 0.0, np.maximum(before, 1.0) * np.where(readmitted, f, 1.0))
    robots, inverse = np.unique(i[touched], return_inverse=True)
    # A pass wins over a re-admission of the same robot in the same call.
    reset = np.zeros(len(robots), bool)
    np.logical_or.at(reset, inverse, passed[touched])
    robot_value = np.zeros(len(robots))
    np.maximum.at(robot_value, inverse, value[touched])
    applied.set(robots, robots, np.where(reset, 0.0, robot_value))
