"""Start-up: no robot's covariance shrinks below a floor in its first corrections.

At the start every covariance is the team's initial one (50 mm by default), every gate is
wide, and compromised neighbours' lies fit inside them (35-40 mm a link on the default
scenario). An honest robot with two liars among its nearer neighbours is pulled a few mm in
the first ~10 steps while its covariance shrinks to 1-2 mm on the lies; its NIS gate then
discards most of its honest neighbours (a partial lock-out that lasts hundreds of steps,
``docs/attack/outvoted.md`` section 1). The tests that see such a robot (the witness
notes, the outvoted stage's sequence test on them) need tens of steps of evidence.

This stage keeps every robot's prior covariance at or above a floor for its first
``startup_steps`` corrections: before the correction,

``P_j <- lambda P_j``,  ``lambda = max(s^2 / max(P_j,xx, P_j,yy), 1)``,
``s = startup_floor_std``

(the whole 3 x 3 block, as the outvoted stage widens it). The correction still shrinks the
posterior; the next step's prior is raised again. So during the start a robot's gate stays
wide enough to admit its honest neighbours, which outnumber the liars and keep pulling it
back, and it cannot lock itself out; when the start ends its covariance shrinks on
neighbours it is consistent with.

What it costs and what an attacker can do:

* **Clean run**: a wider prior weighs the neighbours' readings more in the first steps (a
  fading-memory filter); nothing is discarded. Measured, ``docs/attack/startup.md``.
* **Lies are larger in metres during the start**: the liars' oracle reads the victims'
  innovation covariances computed with the floored ``P`` (the stage runs first, on both
  paths, and records its factor: :func:`applied_startup_factors`), so every lie accepted
  is as large as the wider gate lets it be.
* **An attacker that waits** (lies only once the start is over, the compromised attacker's
  ``quiet`` parameter) beats it: measured on the default scenario, liars quiet for the
  first 10 steps cost x5.78 on one seed of ten where the defence without this stage holds
  them at x2.20 (``docs/attack/startup.md``): a fixed window is a schedule the attacker
  reads. Against liars lying from the start it holds every seed under 3x.
* **A decaying floor** (``startup_decay``): after the ``startup_steps`` corrections the
  floor is multiplied by the decay at each further correction instead of dropped
  (:func:`startup_floor_schedule`), so there is no step at which every prior falls at once
  for the liars to time (``docs/attack/startup.md`` section 5).

It runs before the correction on both paths (:func:`resloc.cl.step.correct`), the
correction being handed the floored covariances: with the numba backend by one compiled
pass (:func:`resloc.cl.kernels_startup.fast_floor`), else by the numpy spec
(:func:`reference_floor`). The count is per robot: the corrections it took part in as an
observer.

**Over.** Once the store holds every robot id with its floor ended and factor 1, and the
schedule cannot rise again (``startup_decay <= 1``), every later pass would write factor 1
again and return ``P`` (:func:`floor_over`): the stage skips it. Only the counts stop,
which nothing reads once the floor is over (the attacker reads the factors); the answer is
kept per store, so that a run's later steps cost a dictionary look-up.
"""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from resloc.cl.detection_widening import applied_stage_factors, floor_factors, scale_robots
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = [
    "StartupFloor",
    "applied_startup_factors",
    "claims_floored",
    "floor_over",
    "floored_claims",
    "reference_floor",
    "startup_floor",
    "startup_floor_schedule",
]

#: Per robot (keyed (j, j)): the corrections it took part in and the factor its covariance
#: was raised by in its last one (1: none).
STARTUP_STATE = "startup"

#: A floor below this (m) is over: far below the 1-2 mm a robot's covariance settles at.
STARTUP_FLOOR_END = 1e-4


#: Per memory: its stage store, the store's keys and values, the schedule and the
#: ``params`` when the stage was found over (:func:`floor_over`; it stays over: a skipped
#: pass writes nothing). Keyed by the memory, and ``params`` compared first by identity (a
#: run's): a run's later steps cost one look-up (the store's method and the schedule's
#: tuple were ~0.5 of ~1.5 us a step in runs).
_OVER: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _over(memory: LinkMemory) -> bool:
    """Whether the stage was found over for ``memory``'s store, its arrays unchanged since
    (the same objects), under any schedule."""
    over = _OVER.get(memory)
    return over is not None and over[1] is over[0].keys and over[2] is over[0].values


def _schedule(params: CLParams) -> tuple:
    return (params.startup_steps, params.startup_floor_std, params.startup_decay)


#: :func:`resloc.cl.kernels_startup.fast_floor` once imported.
_FAST: list = []


def startup_floor(params: CLParams, memory: LinkMemory | None, links, P: np.ndarray) -> np.ndarray:
    """``P (B, 3, 3)`` with every robot still in its start-up (fewer than
    ``params.startup_steps`` corrections as an observer, or a decaying floor not yet below
    ``STARTUP_FLOOR_END``) raised to the floor (module docstring); ``P`` itself when none
    is raised (or the stage is off, or over). Counts the step. The compiled twin with the
    numba backend (:func:`resloc.cl.kernels_startup.fast_floor`), else the numpy spec
    (:func:`reference_floor`)."""
    if params.startup_steps <= 0 or memory is None:
        return P
    over = _OVER.get(memory)  # (_over inline: a call less a step)
    if over is not None and over[1] is over[0].keys and over[2] is over[0].values:
        if over[4] is params or over[3] == _schedule(params):
            return P
    state = memory.stage_statistic(STARTUP_STATE, width=2)
    if not _FAST:  # numba's import, on first use
        from resloc.cl.kernels_startup import fast_floor

        _FAST.append(fast_floor)
    status, fast = _FAST[0](params, state, links, P, STARTUP_FLOOR_END)
    if status == "done":
        return fast
    if status == "spec" and not floor_over(params, state):
        return reference_floor(params, state, links, P)
    _OVER[memory] = (state, state.keys, state.values, _schedule(params), params)
    return P


def claims_floored(params: CLParams, memory: LinkMemory | None) -> bool:
    """Whether :func:`floored_claims` may raise a claim: the option on and the stage not
    over for ``memory``'s store (every floor ended: :func:`floor_over`, as
    :func:`startup_floor` found it)."""
    if not params.startup_claims or params.startup_steps <= 0 or memory is None:
        return False
    return not _over(memory)


def floored_claims(params: CLParams, memory: LinkMemory | None, i, P_nb: np.ndarray) -> np.ndarray:
    """The claims ``P_nb (E, 3, 3)`` an observer fuses, each raised to its observer ``i
    (E,)``'s start-up floor of this step (``startup_claims``; ``P_nb`` itself when none
    is raised, the option is off or the stage is over). Called after :func:`startup_floor`
    in the same step (it reads the count the stage has just advanced).

    Why: the floor widens the observer's own prior during its start, but its neighbours'
    claims stay as sent: an honest neighbour's 1-2 mm after a few steps, a compromised
    one's whatever it likes (x0.01 of its covariance). The observer then weighs each
    neighbour far above its own floored estimate and a lie accepted in the wide gate moves
    it almost the whole way. Floored as its own prior, every claim weighs as much as the
    observer's estimate during the start (``docs/attack/lockout.md`` section 4)."""
    if not claims_floored(params, memory):
        return P_nb
    state = memory.stage_statistic(STARTUP_STATE, width=2)
    i = np.asarray(i)
    floor = startup_floor_schedule(params, state.get(i, i)[:, 0] - 1.0)
    if not (floor > 0.0).any():
        return P_nb
    claims = np.asarray(P_nb, float)
    factor = np.where(floor > 0.0, floor_factors(claims, floor), 1.0)
    if not (factor > 1.0).any():
        return P_nb
    return claims * factor[:, None, None]


def reference_floor(params: CLParams, state, links, P: np.ndarray) -> np.ndarray:
    """:func:`startup_floor` in numpy (its executable specification; the stage on, not
    over) on the stage's store ``state`` (:data:`STARTUP_STATE`)."""
    robots = np.unique(np.asarray(links.i))
    seen = state.get(robots, robots)[:, 0]
    floor = startup_floor_schedule(params, seen)
    young = floor > 0.0
    factor = np.ones(len(robots))
    if young.any():
        factor[young] = floor_factors(np.asarray(P, float)[robots[young]], floor[young])
    state.set(robots, robots, np.column_stack([seen + 1.0, factor]))
    return scale_robots(P, robots, factor)


def floor_over(params: CLParams, state) -> bool:
    """Whether the stage is over for its store ``state``: every robot id ``0 .. n - 1``
    stored with factor 1 and a floor of 0 at its count, the schedule never rising again
    (``startup_decay <= 1``; then every later pass writes factor 1 and returns ``P``)."""
    n = state.n_nodes
    if len(state) != n or not params.startup_decay <= 1.0:
        return False
    values = state.values.reshape(n, 2)
    return bool(
        (state.keys == np.arange(n) * (n + 1)).all()
        and (values[:, 1] == 1.0).all()
        and (startup_floor_schedule(params, values[:, 0]) == 0.0).all()
    )


def startup_floor_schedule(params: CLParams, seen: np.ndarray) -> np.ndarray:
    """The floor (m) for a robot that has taken part in ``seen`` corrections before this one:
    ``startup_floor_std`` for the first ``startup_steps``, then multiplied by
    ``startup_decay`` at each further correction (0: dropped at once). Why a decay: a floor
    dropped at once is a release the liars can time (they lie from that step, when every
    prior falls from the floor to a few mm together, ``docs/attack/startup.md`` section 5);
    a geometric decay leaves no step where the prior shrinks faster than by ``decay``.
    Below ``STARTUP_FLOOR_END`` it is 0 (over: below any covariance the team reaches)."""
    seen = np.asarray(seen, float)
    past = np.maximum(seen - params.startup_steps + 1.0, 0.0)
    floor = params.startup_floor_std * np.power(float(params.startup_decay), past)
    return np.where(floor >= STARTUP_FLOOR_END, floor, 0.0)


def applied_startup_factors(memory: LinkMemory, B: int) -> np.ndarray:
    """The factor ``(B,)`` each robot's covariance was raised by in its last correction
    (1: none; what a full-knowledge attacker reads to see the covariances the step uses)."""
    return applied_stage_factors(memory, STARTUP_STATE, B)


class StartupFloor:
    """The stage's place in the registry: it discards nothing (its effect is on the robot's
    own covariance before the correction, :func:`startup_floor`, applied by
    :func:`resloc.cl.step.correct` on both paths)."""

    name: ClassVar[str] = "startup"
    compiled: ClassVar[bool] = True
    overrides: ClassVar[bool] = False

    def active(self, params: CLParams) -> bool:
        return params.startup_steps > 0

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        return np.zeros(len(evidence.nu), bool)
