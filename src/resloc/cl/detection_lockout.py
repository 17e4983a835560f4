"""Lock-out floor: a robot whose own tests discard most of what it sees raises its covariance.

Every per-link test assumes the robot's own estimate is consistent with its covariance.
Compromised neighbours that pull an honest robot a few mm while its covariance is 1-2 mm
break that: its gate then discards most of its *honest* neighbours, the few it still fuses
are those whose geometry cannot see its error, and the offset lasts hundreds of steps
(a partial lock-out). Measured on the default scenario against three compromised robots
(``docs/attack/startup.md`` section 6.3): in mid-run (steps 200-600), 51-60% of the worst
robot's honest links discarded, 28-34% of all, the MSLE 3.4-6x the clean run's, while the
outvoted stage (which reads its observers' notes) never fired and the recovery stage
(which waits for *every* measurement of the robot to be discarded) was reset by the few that
passed.

The signature is visible to the robot itself, with no notes: the share of its own
measurements its detector discards. This stage keeps, per robot ``i``, an exponentially
weighted share over its corrections as an observer,

``s_i <- (1 - a) s_i + a d_i / m_i``,  ``a = 1 / lockout_window``

(``m_i``: the links the detector judged in the step, ``d_i``: those it discarded, by any
stage; jammed links and the readings zone trust withholds are not judged; a step with none
judged leaves ``s_i``), and while ``s_i > lockout_share`` it raises
the robot's *prior* covariance to a floor before the correction, as the start-up stage does
(:mod:`resloc.cl.detection_startup`):

``P_i <- lambda P_i``,  ``lambda = max(f^2 / max(P_i,xx, P_i,yy), 1)``,
``f = lockout_floor_std``

(the whole 3 x 3 block). Its gate then admits its honest neighbours, which pull it back;
once it agrees with them again its share falls under the threshold and the floor is
released.

Why a share and a majority, and what an attacker can do:

* **Liars alone cannot raise it** while they are a minority of a robot's judged links:
  with ``lockout_share >= 0.5`` the liars' own discarded lies never make the share on their
  own (a robot with liars for half of its neighbours is beyond the honest-majority
  assumption every redundancy test here makes). It is the robot's honest neighbours being
  discarded that raises it: the lock-out itself.
* **The attacker knows it**: the floor is recorded per robot (:func:`applied_lockout_factors`)
  and the liars' oracle is handed the covariances the correction uses
  (:func:`resloc.world.attackers.outvoted.widened`), so a lie at a floored victim is as
  large as its wider gate allows; the floor is the price of re-admitting the honest ones.
* **The liars do not floor themselves**: a compromised robot runs its own software; a
  floor on its own covariance would widen what it claims and weaken its lies. In the
  simulation the attacker marks its robots (``LinkMemory.exempt``) and no stage that
  widens a robot's own covariance applies to them (:func:`resloc.cl.step.correct`;
  measured: counting the liars' floors, seed 4 of the evaluation seeds fell
  from x3.02 to x2.77 through floors on a liar alone, ``docs/attack/lockout.md``).
* **What it cannot see**: a robot pulled so little that its gate keeps most of its
  neighbours (then the pull is of the order of its covariance); a robot whose every
  neighbour is a liar.

It runs before the correction on both paths (:func:`resloc.cl.step.correct`): the
compiled correction is handed the floored covariances (``compiled = True``). The share is
recorded after the correction from its outcome (:func:`record_lockout`), on both paths.
With the numba backend both passes run compiled (:mod:`resloc.cl.kernels_lockout`); the
numpy functions here are their specification (:func:`reference_floor`,
:func:`reference_record`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from resloc.cl.detection_widening import applied_stage_factors, floor_factors, scale_robots
from resloc.cl.detection_zone import inside_zone_map
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence
    from resloc.cl.links import LinkOutcome

__all__ = [
    "Lockout",
    "applied_lockout_factors",
    "discard_share",
    "discarded_shares",
    "lockout_floor",
    "record_lockout",
    "reference_floor",
    "reference_record",
]

#: Per robot (keyed (i, i)): its discarded share ``s_i`` and the factor its covariance was
#: raised by in its last correction (1: none).
LOCKOUT_STATE = "lockout"

#: :mod:`resloc.cl.kernels_lockout` once imported.
_FAST: list = []


def lockout_floor(params: CLParams, memory: LinkMemory | None, links, P: np.ndarray) -> np.ndarray:
    """``P (B, 3, 3)`` with every observer of ``links`` whose discarded share is above
    ``params.lockout_share`` raised to the floor (module docstring); ``P`` itself when none
    is raised (or the stage is off). Records each observer's factor (1: none). The compiled
    twin with the numba backend (:func:`resloc.cl.kernels_lockout.fast_floor`), else the
    numpy spec (:func:`reference_floor`)."""
    if params.lockout_share <= 0.0 or memory is None:
        return P
    if not _FAST:  # numba's import, on first use
        from resloc.cl import kernels_lockout

        _FAST.append(kernels_lockout)
    fast = _FAST[0].fast_floor(params, memory, links, P)
    if fast is not None:
        return fast
    return reference_floor(params, memory.stage_statistic(LOCKOUT_STATE, width=2), links, P)


def reference_floor(params: CLParams, state, links, P: np.ndarray) -> np.ndarray:
    """:func:`lockout_floor` in numpy (its executable specification; the stage on) on the
    stage's store ``state`` (:data:`LOCKOUT_STATE`)."""
    robots = np.unique(np.asarray(links.i))
    known = state.get(robots, robots)
    share = known[:, 0]
    factor = np.ones(len(robots))
    alarm = share > params.lockout_share
    if alarm.any():
        factor[alarm] = floor_factors(np.asarray(P, float)[robots[alarm]], params.lockout_floor_std)
    if alarm.any() or (known[:, 1] > 1.0).any():
        state.set(robots, robots, np.column_stack([share, factor]))
    return scale_robots(P, robots, factor)


def discard_share(
    i: np.ndarray, detected: np.ndarray, judged: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per observer, the share of its judged links its detector discarded in one step.

    Parameters
    ----------
    i : ndarray of int, shape (E,)
        The links' observers.
    detected, judged : ndarray of bool, shape (E,)
        Discarded by the detector; judged by it (the neighbour's estimate arrived).

    Returns
    -------
    robots : ndarray of int, shape (G,)
        The observers with at least one judged link (sorted).
    share : ndarray, shape (G,)
        ``d_i / m_i``.
    """
    i = np.asarray(i, np.int64)[judged]
    robots, slot = np.unique(i, return_inverse=True)
    m = np.bincount(slot, minlength=len(robots))
    d = np.bincount(slot, np.asarray(detected, float)[judged], minlength=len(robots))
    return robots, d / np.maximum(m, 1)


def record_lockout(
    params: CLParams, memory: LinkMemory | None, links, outcome: LinkOutcome, x: np.ndarray
) -> None:
    """After the correction: each observer's discarded share ``s_i`` updated with the
    step's (module docstring), ``x (B, 3)`` the estimates the correction started from. A
    link was judged when its neighbour's estimate arrived (``links.channel_ok``: a jammed
    link is no verdict on the robot) and its observer was outside the zone map with zone
    trust on (a withheld reading is a policy on the sensor, not a verdict: counted, every
    robot inside a zone would raise its floor)."""
    if params.lockout_share <= 0.0 or memory is None or len(links) == 0:
        return
    if not _FAST:  # numba's import, on first use
        from resloc.cl import kernels_lockout

        _FAST.append(kernels_lockout)
    if _FAST[0].fast_record(params, memory, links, outcome.detected, x):
        return
    judged = np.asarray(links.channel_ok, bool)
    if params.zone_trust:
        judged = judged & ~inside_zone_map(np.asarray(x)[links.i, :2], params.zone_trust_map)
    state = memory.stage_statistic(LOCKOUT_STATE, width=2)
    reference_record(params, state, links.i, outcome.detected, judged)


def reference_record(
    params: CLParams, state, i: np.ndarray, detected: np.ndarray, judged: np.ndarray
) -> None:
    """:func:`record_lockout`'s update in numpy (its executable specification) on the
    stage's store ``state``: ``i``, ``detected``, ``judged`` per link, shape (E,)."""
    robots, step_share = discard_share(i, detected, judged)
    if robots.size == 0:
        return
    known = state.get(robots, robots)
    weight = 1.0 / float(params.lockout_window)
    share = (1.0 - weight) * known[:, 0] + weight * step_share
    factor = np.where(known[:, 1] > 1.0, known[:, 1], 1.0)
    state.set(robots, robots, np.column_stack([share, factor]))


def discarded_shares(memory: LinkMemory, B: int) -> np.ndarray:
    """Each robot's discarded share ``s_i`` ``(B,)`` as the stage keeps it (0: none yet;
    what a full-knowledge attacker reads to keep a victim under the threshold)."""
    state = memory.stage_statistic(LOCKOUT_STATE, width=2)
    robots = np.arange(B)
    return state.get(robots, robots)[:, 0]


def applied_lockout_factors(memory: LinkMemory, B: int) -> np.ndarray:
    """The factor ``(B,)`` each robot's covariance was raised by in its last correction
    (1: none; what a full-knowledge attacker reads to see the covariances the step uses)."""
    return applied_stage_factors(memory, LOCKOUT_STATE, B)


class Lockout:
    """The stage's place in the registry: it discards nothing (its effect is on the robot's
    own covariance before the correction, :func:`lockout_floor`, and its share is kept
    from the correction's outcome, :func:`record_lockout`; both applied by
    :func:`resloc.cl.step.correct` on both paths)."""

    name: ClassVar[str] = "lockout"
    compiled: ClassVar[bool] = True
    overrides: ClassVar[bool] = False

    def active(self, params: CLParams) -> bool:
        return params.lockout_share > 0.0

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        return np.zeros(len(evidence.nu), bool)
