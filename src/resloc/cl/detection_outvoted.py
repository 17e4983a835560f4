"""Outvoted: a robot its observers' notes place elsewhere widens its own covariance.

The per-link tests all assume the robot's own estimate is consistent with its covariance.
A robot that compromised neighbours pulled off early (while every gate was wide, in the
first steps) and whose covariance then shrank is not: its honest neighbours' readings now
look like attacks to its NIS gate, it discards most of them, and the few it fuses are those
whose geometry cannot see its error. The recovery stage (:mod:`resloc.cl.detection_recovery`)
does not fire: some measurements still pass. Measured on the default scenario against three
compromised robots (seed 4, ``docs/attack/outvoted.md``): an honest robot with two liars
among its nearer neighbours, pulled in the first steps, then a few mm off with a 1.2-2 mm
standard deviation for a few hundred steps, discarding most of its honest neighbours.

The witness stage's notes (:mod:`resloc.cl.detection_witness`) already carry it: each
observer o of robot j sends ``u_oj = p_j - g_oj``, j's broadcast position minus where o's
estimate and reading put j, with its independent covariance ``Q_oj``. This stage lets j
read the notes *on itself* that reached it (the frames of this step: the link (j, o) with
its channel through, the rule of
:func:`resloc.cl.detection_witness_frames.received_groups`) and take the witness statistic
on them (the smallest ``T_K`` over the consistent sets left after dropping any
``f = witness_liars`` notes, :func:`resloc.cl.detection_witness.group_statistic`):

``T_j = min_K m_K^T (P_j,pos + Y_K^-1)^-1 m_K``,

summed over time by the witness stage's own sequence test (its ``k`` and ``h``; a step
with at most ``f`` notes adds ``-k``, one with no consistent set ``h / 2``):

``S_j <- clip(S_j + min(T_j, h / 2) - k, 0, 2 h)``.

One step's notes are weak (the bearing noise makes each a few cm wide at the team's ranges);
a persistent offset adds up. While ``S_j > h`` the robot's own covariance understates its
error, and it widens it before the step's correction (covariance matching, the adaptive
filter's fading factor, on the offset the notes show, their coordinatewise median ``m_j``,
robust to ``f`` of them):

``P_j <- lambda P_j``,  ``lambda = min(max(m_j^T P_j,pos^-1 m_j / 2, 1), outvoted_cap,
max(s^2 / max(P_j,xx, P_j,yy), 1))``, ``s = outvoted_max_std``

(the whole 3 x 3 block: a robot pulled off in position is usually off in heading too). Its
gate then admits its honest neighbours, which pull it back. The notes were computed in the
step before, at the broadcast that preceded the last correction: a robot that widened its
covariance skips the next step (the notes it then receives predate the widening's effect).

Why the notes, and what an attacker can do with them:

* **f lying observers cannot trigger it**: the honest notes alone are a candidate set, so
  ``T_j`` is at most theirs (chi-square for an honest robot on target). Lying notes can only
  lower it (exonerate), and only within the honest notes' consistency; the compromised
  robots do exactly that (:mod:`resloc.world.attackers.outvoted`). The median moves by at
  most the ``f`` lying notes' rank.
* **It discards nothing** and changes no other robot's weights: its effect is on the robot's
  own covariance, which the attacker's oracle reads (the tamper is handed the innovation
  covariances computed with the widened ``P_j``): a compromised neighbour's lie at the
  widened robot's gate is larger in metres, for the steps the robot is widened.
* **What it needs**: the witness stage's notes (``detector.witness``); a robot with at most
  ``f`` notes on itself in a step is not judged.

It runs before the correction, on both paths (:func:`resloc.cl.step.correct`): the
compiled correction is handed the widened covariances (``compiled = True``). With the numba
backend the stage itself runs compiled in one pass (:mod:`resloc.cl.kernels_outvoted`);
the numpy functions here are its specification (:func:`reference_widen`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from resloc.cl.detection_widening import applied_stage_factors, floor_factors, scale_robots
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = [
    "Outvoted",
    "applied_factors",
    "group_medians",
    "outvoted_statistic",
    "reference_widen",
    "widen_outvoted",
]

#: Per robot (keyed (j, j)): its sequence test ``S_j`` and the factor it widened its
#: covariance by in its last step (1: none).
OUTVOTED_STATE = "outvoted"


def outvoted_statistic(
    params: CLParams,
    notes,
    i: np.ndarray,
    j: np.ndarray,
    channel_ok: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each robot's witness statistic on the notes on itself that reached it, and their
    coordinatewise median.

    Parameters
    ----------
    params : CLParams
    notes : WitnessNotes
        The notes the observers send with this step's frames
        (:func:`~resloc.cl.detection_witness_frames.pending_notes`).
    i, j, channel_ok : ndarray, shape (E,)
        The step's links: receiver, sender, whether the sender's messages get through.

    Returns
    -------
    robots : ndarray of int, shape (G,)
        The robots with a note on themselves received.
    T : ndarray, shape (G,)
        Their statistic (``nan``: not judged, at most ``f`` notes; ``inf``: no consistent
        set).
    offset : ndarray, shape (G, 2)
        The median of the notes (coordinatewise): where the observers put the robot's
        broadcast position relative to their own view of it, robust to ``f`` of them.
    """
    from resloc.cl.detection_witness import group_statistic

    empty = np.zeros(0, np.int64)
    sel = np.flatnonzero(notes.sent)
    if sel.size == 0:
        return empty, np.zeros(0), np.zeros((0, 2))
    n = 1 + int(
        max(np.max(notes.i[sel]), np.max(notes.j[sel]), np.max(i, initial=0), np.max(j, initial=0))
    )
    ok = np.asarray(channel_ok, bool)
    reached = np.asarray(i, np.int64)[ok] * n + np.asarray(j, np.int64)[ok]
    # The note of observer o on robot r reaches r with o's frame over the link (r, o).
    keys = notes.j[sel].astype(np.int64) * n + notes.i[sel].astype(np.int64)
    rows = sel[np.isin(keys, reached)]
    rows = rows[np.lexsort((notes.i[rows], notes.j[rows]))]
    if rows.size == 0:
        return empty, np.zeros(0), np.zeros((0, 2))
    on = notes.j[rows]
    start = np.flatnonzero(np.r_[True, on[1:] != on[:-1]])
    count = np.diff(np.r_[start, len(rows)])
    ids = on[start].astype(np.int64)
    T, judged = group_statistic(notes, params, rows, start, count, ids)
    T = np.where(np.asarray(judged, bool), np.asarray(T, float), np.nan)
    T = np.where(np.asarray(judged, bool) & np.isnan(T), np.inf, T)
    return ids, T, group_medians(notes.u[rows], start, count)


def group_medians(u: np.ndarray, start: np.ndarray, count: np.ndarray) -> np.ndarray:
    """The coordinatewise median ``(G, 2)`` of each group of rows of ``u (E, 2)``: group
    ``g`` is rows ``start[g] : start[g] + count[g]`` (contiguous, every count > 0). Equal to
    ``np.median`` per group, to the bit (the middle element, or the mean of the two middle
    ones; nan where the group holds a nan), in one sort instead of a call per group (a
    loop of ``np.median`` cost ~0.4 ms a step at 17 robots)."""
    group = np.repeat(np.arange(len(start)), count)
    lo, hi = start + (count - 1) // 2, start + count // 2
    out = np.empty((len(start), 2))
    for c in range(2):
        v = u[:, c]
        sorted_v = v[np.lexsort((v, group))]
        out[:, c] = (sorted_v[lo] + sorted_v[hi]) / 2.0
        out[np.add.reduceat(np.isnan(v), start) > 0, c] = np.nan
    return out


#: :func:`resloc.cl.kernels_outvoted.fast_widen` once imported (an import statement a
#: step costs ~0.5 us).
_FAST: list = []


def widen_outvoted(params: CLParams, memory: LinkMemory | None, links, P: np.ndarray) -> np.ndarray:
    """``P (B, 3, 3)`` with the covariance of every robot its observers' notes outvote
    widened; ``P`` itself when none is (or the stage is off). Reads the notes waiting in
    ``memory`` for this step's frames, updates each robot's sequence test (module
    docstring) and records which robots widened (they skip the next step). In one robot's
    process, the view its runtime delivered (``memory.outvoted_view``,
    :meth:`~resloc.cl.node.RobotNode.receive_witness`) is read instead. The compiled
    twin with the numba backend (:func:`resloc.cl.kernels_outvoted.fast_widen`), else the
    numpy spec (:func:`reference_widen`)."""
    if not params.outvoted or not params.witness or memory is None:
        return P
    view = memory.outvoted_view
    if view is not None:  # one robot's process: the notes on it its runtime delivered
        memory.outvoted_view = None
        memory = view
    if not _FAST:  # numba's import, on first use
        from resloc.cl.kernels_outvoted import fast_widen

        _FAST.append(fast_widen)
    fast = _FAST[0](params, memory, links, P)
    if fast is not None:
        return fast
    return reference_widen(params, memory, links, P)


def reference_widen(params: CLParams, memory: LinkMemory, links, P: np.ndarray) -> np.ndarray:
    """:func:`widen_outvoted` in numpy (its executable specification; the stage on)."""
    from resloc.cl.detection_witness_frames import pending_notes

    state = memory.stage_statistic(OUTVOTED_STATE, width=2)
    robots, T, offset = outvoted_statistic(
        params, pending_notes(memory), links.i, links.j, links.channel_ok
    )
    robots_all = np.unique(np.asarray(links.i))
    known = state.get(robots_all, robots_all)
    k, h = float(params.witness_k), float(params.witness_h)
    # (a robot's notes reach it over its own links: every judged robot is an observer)
    where = np.searchsorted(robots_all, robots)
    judged = ~np.isnan(T)
    stat = np.zeros(len(robots_all))  # no judgement: decays by k
    stat[where[judged]] = np.minimum(T[judged], h / 2.0)
    S = np.clip(known[:, 0] + stat - k, 0.0, 2.0 * h)
    factor = np.ones(len(robots_all))
    m = np.full((len(robots_all), 2), np.nan)
    m[where[judged]] = offset[judged]
    alarm = (S > h) & (known[:, 1] <= 1.0) & np.isfinite(m).all(axis=1)
    if alarm.any():
        a = np.flatnonzero(alarm)
        Pp = np.asarray(P, float)[robots_all[a], :2, :2]
        # The widening that makes the robot's own position covariance cover the offset the
        # notes show (covariance matching, 2 dof): lambda = m^T P^-1 m / 2.
        w = np.linalg.solve(Pp, m[a][..., None])[..., 0]
        factor[a] = np.clip(np.einsum("ni,ni->n", m[a], w) / 2.0, 1.0, params.outvoted_cap)
        # Bounded: unbounded, repeated widenings let the displaced robot's consistent lies
        # run the team's estimates away (kilometres; docs/attack/outvoted.md, section 7).
        ceiling = floor_factors(np.asarray(P, float)[robots_all[a]], params.outvoted_max_std)
        factor[a] = np.minimum(factor[a], ceiling)
    state.set(robots_all, robots_all, np.column_stack([S, factor]))
    return scale_robots(P, robots_all, factor)


def applied_factors(memory: LinkMemory, B: int) -> np.ndarray:
    """The factor ``(B,)`` each robot's covariance was widened by in its last correction
    (1: none; what a full-knowledge attacker reads to see the covariances the step uses)."""
    return applied_stage_factors(memory, OUTVOTED_STATE, B)


class Outvoted:
    """The stage's place in the registry: it discards nothing (its effect is on the robot's
    own covariance before the correction, :func:`widen_outvoted`, applied by
    :func:`resloc.cl.step.correct` on both paths)."""

    name: ClassVar[str] = "outvoted"
    compiled: ClassVar[bool] = True
    overrides: ClassVar[bool] = False

    def problem(self, options) -> str | None:
        """Why the scenario's ``[detector]`` ``options`` make no stage (names the fix)."""
        if getattr(options, "outvoted", False) and not options.witness:
            return "outvoted: reads the witness notes; set detector.witness = true"
        return None

    def active(self, params: CLParams) -> bool:
        return bool(params.outvoted)

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        return np.zeros(len(evidence.nu), bool)
