"""Compiled twins of the per-robot detector stages: the robot CUSUM and the recovery.

:class:`~resloc.cl.detection_robot.RobotCusum` and
:class:`~resloc.cl.detection_recovery.RejectionRecovery` keep one statistic per *robot*
(keyed ``(i, i)`` in :class:`~resloc.cl.memory.LinkStatistic` stores of the run's
:class:`~resloc.cl.memory.LinkMemory`). In the sequential update each round holds at most
one link of a robot, and robot ``i``'s links are its rows in ascending ``j``: the compiled
loop (:mod:`resloc.cl.kernels_links`), which walks the rows in that order, updates the
statistics link after link exactly as the reference's rounds do. :func:`defence_state`
gives the loop the stores' value arrays and each link's slot in them (a robot never seen is
inserted at 0, the value the reference reads for it); :meth:`DetectorState.undo
<resloc.cl.kernels_detection.DetectorState.undo>` puts them back when the kernel gives up
on a step. The stores then hold the reference's values; they may also hold keys at 0 the
reference has not inserted yet (a robot whose measurements the gate all discarded), which
:meth:`LinkStatistic.get <resloc.cl.memory.LinkStatistic.get>` reads as the same 0.

The recovery's third store, ``A_i`` (the inflation re-admissions applied since robot ``i``'s
last ordinary acceptance, capped at ``f_max^2``), is kept the same way. When the recovery
re-admits a measurement with robot ``i``'s covariance inflated by ``f > 1``, the loop
computes that link's moments a second time from ``f P_i`` and updates with them, as
:func:`resloc.cl.step.correct` does.

=============================  ==========================================================
kernel function                numpy twin
=============================  ==========================================================
:func:`robot_cusum_step`       :func:`resloc.cl.detection_robot.robot_cusum` and
                               ``RobotCusum.discard``
:func:`recovery_step`          ``RejectionRecovery.discard`` (with
                               :func:`~resloc.cl.detection_recovery.recovery_inflation`,
                               :func:`~resloc.cl.detection_recovery.update_rejection_runs`)
:func:`defend_link`            the per-robot stages of :func:`resloc.cl.detection.detect`
=============================  ==========================================================
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from resloc.cl.kernels_detection import (
    DetectorState,
    gain_at,
    nis_of,
    shared_slots,
    store_slots,
)
from resloc.cl.kernels_math import gain_array, jit_inline, per_params
from resloc.cl.kernels_stores import group_slots, keep_state, steady_state
from resloc.cl.params import CLParams

__all__ = [
    "KernelDefence",
    "defence_state",
    "defend_link",
    "recovery_step",
    "robot_cusum_step",
]


class KernelDefence(NamedTuple):
    """The per-robot stages as the kernel takes them.

    Gains are ``(1,)`` (one value) or ``(B,)`` (per observer); a stage that is off gets
    empty arrays, never read.
    """

    robot_cusum: bool
    robot_k: np.ndarray  # (1,) or (B,)
    robot_h: np.ndarray
    robot_g: np.ndarray  # (n,) the store's values, written in place
    robot_slot: np.ndarray  # (E,) int64, the slot of each link's observer
    recovery: bool
    after: np.ndarray  # R, consecutive rejections before recovery
    gate: np.ndarray  # the inflated NIS gate
    cap: np.ndarray  # f_max
    runs: np.ndarray  # (n,) consecutive discarded measurements per robot
    runs_slot: np.ndarray  # (E,) int64
    spread: np.ndarray  # (n,) tr P_pos at the robot's last ordinary acceptance
    spread_slot: np.ndarray  # (E,) int64
    applied: np.ndarray  # (n,) product of the inflations applied since then (0: none)
    applied_slot: np.ndarray  # (E,) int64


_NO_GAIN = np.zeros(1)
_NO_SLOTS = np.zeros(0, np.int64)
_NO_VALUES = np.zeros(0)


@per_params
def _defence_gains(params: CLParams) -> tuple[tuple, tuple]:
    """The robot CUSUM's ``(k, h)`` and the recovery's ``(after, gate, cap)`` as the kernel
    takes them; empty for a stage that is off."""
    robot = (gain_array(params.robot_cusum_k), gain_array(params.robot_cusum_h))
    recovery = tuple(
        gain_array(g)
        for g in (params.recovery_after, params.recovery_gate, params.recovery_inflation_cap)
    )
    return (robot if params.robot_cusum else ()), (recovery if params.recovery else ())


def defence_state(params: CLParams, memory, i: np.ndarray) -> DetectorState | None:
    """The per-robot stages of ``params`` for the links of observers ``i`` of one step.

    Parameters
    ----------
    params : CLParams
    memory : LinkMemory or None
    i : ndarray of int, shape (E,)
        Observers (sorted; a robot repeats on its links' rows).

    Returns
    -------
    DetectorState or None
        Its ``kernel`` is a :class:`KernelDefence`. None when a stage is on and there is no
        memory (the reference path raises the explanatory error).
    """
    robot_gains, recovery_gains = _defence_gains(params)
    if (robot_gains or recovery_gains) and memory is None:
        return None
    robot = memory.stage_statistic("robot_cusum") if robot_gains else None
    if recovery_gains:
        # the stores of RejectionRecovery (detection_recovery._runs, its spread and the
        # inflation applied)
        runs = memory.stage_statistic("recovery", width=None)
        spread = memory.stage_statistic("recovery_spread")
        applied = memory.stage_statistic("recovery_applied")
    stores = ((robot,) if robot_gains else ()) + ((runs, spread, applied) if recovery_gains else ())
    if stores:  # the last step's state, its links looked up again (kernels_stores)
        state = steady_state(stores, params, i, i)
        if state is not None:
            return state
    saved: list = []
    first: list = []  # the first store's (store, slots): the others share them when they can

    def slots_one(store) -> np.ndarray:
        # every store is keyed (i, i) by the same observers: in a run's steady state they
        # hold the same keys, and a comparison of ~B keys replaces a look-up of E links
        slots = shared_slots(store, *first[0], saved) if first else None
        if slots is None:
            slots = store_slots(store, i, i, saved)
            if not first:
                first.append((store, slots))
        return slots

    # one look-up and one save for every store in a run's steady state (kernels_stores)
    shared = group_slots(stores, i, i, saved) if stores else None

    def slots_of(store) -> np.ndarray:  # (shared, or store by store: the path that inserts)
        return shared if shared is not None else slots_one(store)

    if robot_gains:
        store = robot
        slot = slots_of(store)
        robot_part = (True, *robot_gains, store.values, slot)
    else:
        robot_part = (False, _NO_GAIN, _NO_GAIN, _NO_VALUES, _NO_SLOTS)
    if recovery_gains:
        runs_slot = slots_of(runs)
        spread_slot = slots_of(spread)
        applied_slot = slots_of(applied)
        recovery_part = (True, *recovery_gains, runs.values, runs_slot, spread.values, spread_slot)
        recovery_part += (applied.values, applied_slot)
    else:
        recovery_part = (False, _NO_GAIN, _NO_GAIN, _NO_GAIN)
        recovery_part += (_NO_VALUES, _NO_SLOTS, _NO_VALUES, _NO_SLOTS, _NO_VALUES, _NO_SLOTS)
    state = DetectorState(KernelDefence(*robot_part, *recovery_part), tuple(saved))
    if shared is not None:
        keep_state(stores, params, state, shared)
    return state


# ---------------------------------------------------------------------------------------
# Per-link pieces, inlined into the CL loop of resloc.cl.kernels_links.
# ---------------------------------------------------------------------------------------
@jit_inline
def robot_cusum_step(g, stat, k, h, passed):
    """One step of the CUSUM of the NIS over all of robot i's links from statistic ``g``:
    ``(g', discard)`` with ``g' = min(max(0, g + (NIS - k)), 2 h)`` when the gate ``passed``
    the measurement (else ``g``); the stage discards while ``g' > h`` a measurement with
    ``NIS > k``. Scalars only (a loop over lanes calls it without passing arrays).
    Twin: :func:`resloc.cl.detection_robot.robot_cusum` and ``RobotCusum.discard``."""
    if passed:
        v = g + (stat - k)
        if v < 0.0:
            v = 0.0
        cap = 2.0 * h
        if v > cap:
            v = cap
        g = v
    return g, g > h and stat > k


@jit_inline
def _robot_cusum(g, slot, stat, k, h, passed):
    """:func:`robot_cusum_step` on the statistic ``g[slot]``, stored in place."""
    v, discard = robot_cusum_step(g[slot], stat, k, h, passed)
    g[slot] = v
    return discard


@jit_inline
def recovery_step(start, spread, applied, detected, stat, trace, after, gate, cap):
    """Recovery after a run of rejections on one link of robot i, from its run count
    ``start``, the spread at its last ordinary acceptance and ``A_i`` (``applied``):
    ``(detected, inflation, runs', spread', applied')``.

    ``f = min(2^((n - R) / R), f_max, max(G_i, 1), max(f_max^2 / A_i, 1))`` while ``n >= R``
    (``G_i``: growth of ``tr P_i,pos`` since the last ordinary acceptance; ``A_i``: the
    inflation re-admissions applied since then); a discarded measurement with ``NIS / f <=
    gate`` is re-admitted with inflation ``f``. Scalars only. Twin:
    ``RejectionRecovery.discard`` (with ``recovery_inflation``, ``remaining_inflation``,
    ``_record_applied`` and ``update_rejection_runs``).
    """
    f = math.nan  # not in recovery: stays NaN, as np.minimum keeps it
    if start >= after:  # (the bounds' divisions only here: a NaN f compares False)
        f = np.exp2((start - after) / after)
        if f > cap:
            f = cap
        growth = trace / spread if spread > 0.0 else math.inf
        if growth < 1.0:
            growth = 1.0
        if f > growth:
            f = growth
        remaining = (cap * cap) / (applied if applied > 1.0 else 1.0)
        if remaining < 1.0:
            remaining = 1.0
        if f > remaining:
            f = remaining
    new_spread = spread
    new_applied = applied
    if not detected:
        new_spread = trace
        new_applied = 0.0
    inflation = 1.0
    readmitted = False
    if detected and math.isfinite(f) and stat / f <= gate:
        detected = False
        readmitted = True
        inflation = f
        new_applied = (applied if applied > 1.0 else 1.0) * f
    runs = start
    if not detected and not readmitted:
        runs = 0.0
    elif not readmitted:
        runs = start + 1.0
    return detected, inflation, runs, new_spread, new_applied


@jit_inline
def _recovery(
    runs, run_slot, spread, spread_slot, applied, applied_slot, detected, stat, trace,
    after, gate, cap,
):  # fmt: skip
    """:func:`recovery_step` on the stores' values at the slots, stored in place:
    ``(detected, inflation)``."""
    detected, inflation, n, g, a = recovery_step(
        runs[run_slot], spread[spread_slot], applied[applied_slot], detected, stat, trace,
        after, gate, cap,
    )  # fmt: skip
    runs[run_slot] = n
    spread[spread_slot] = g
    applied[applied_slot] = a
    return detected, inflation


@jit_inline
def defend_link(defence, e, i, detected, gated, Pi, nu0, nu1, l00, l10, l11):
    """The per-robot stages on link ``e`` of observer ``i`` (``P_i``: its running
    covariance), after the per-link stages' verdict ``detected`` and the gate's ``gated``:
    ``(detected, inflation)``. The robot CUSUM adds discards; the recovery runs last and
    overrides. Twin: the per-robot stages of :func:`resloc.cl.detection.detect`."""
    robot, rk, rh, rg, rslot, recovery, after, gate, cap = defence[:9]
    runs, runs_slot, spread, sslot, applied, aslot = defence[9:]
    stat = nis_of(nu0, nu1, l00, l10, l11)
    if robot and _robot_cusum(rg, rslot[e], stat, gain_at(rk, i), gain_at(rh, i), not gated):
        detected = True
    inflation = 1.0
    if recovery:
        trace = Pi[0, 0] + Pi[1, 1]
        detected, inflation = _recovery(
            runs, runs_slot[e], spread, sslot[e], applied, aslot[e], detected, stat, trace,
            gain_at(after, i), gain_at(gate, i), gain_at(cap, i),
        )  # fmt: skip
    return detected, inflation
