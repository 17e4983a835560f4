"""The compromised robots against the outvoted stage (:mod:`resloc.cl.detection_outvoted`).

An honest robot their lies pulled off widens its own covariance when its observers' notes
on it convict it (the witness statistic on the notes on itself, summed over time), and its
honest neighbours then pull it back. The compromised robots, as its observers, send notes
on it too, and know the test: on every honest robot they send, among

* their accusing note (:func:`~resloc.world.attackers.witness.lying_notes`),
* their honest note,
* minus ``t`` times the honest observers' mean note on it (``t`` in
  :data:`~resloc.world.attackers.witness.EXONERATION`: the note that says it is where it
  believes),

the one (the same ``t`` for all the liars' notes on one robot) that makes its statistic
smallest: the victim is kept from widening where the notes can hide its offset, within the
honest notes' consistency. Their notes on fellow liars are
:func:`~resloc.world.attackers.witness.lying_notes`'.

The choice is made on the set of all notes on the robot (as the exoneration of a fellow
is), not per receiver: the outvoted stage reads the notes on a robot that reached that
robot, nearly all of them in the default team.

Their lies themselves already see the widening: the victims' innovation covariances the
tamper is handed are computed from the widened covariances, and the notes the liars' budget
predicts read them (:func:`widened`).
"""

from __future__ import annotations

import numpy as np

from resloc.cl.detection_witness import WitnessNotes, witness_statistic
from resloc.cl.params import CLParams
from resloc.world.attackers.witness import EXONERATION, liars_send_all, lying_notes

__all__ = ["shielding_notes", "widened"]


def shielding_notes(notes: WitnessNotes, is_liar: np.ndarray, params: CLParams) -> WitnessNotes:
    """``notes`` (the step's honest notes) with the compromised observers' notes replaced:
    on a fellow liar as :func:`~resloc.world.attackers.witness.lying_notes`; on an honest
    robot the candidate (module docstring) that minimises that robot's witness statistic.

    Parameters
    ----------
    notes : WitnessNotes
    is_liar : ndarray of bool, shape (B,)
    params : CLParams
    """
    notes = liars_send_all(notes, is_liar)
    lied = lying_notes(notes, is_liar, params)
    shield = np.flatnonzero(is_liar[notes.i] & notes.sent & ~is_liar[notes.j])
    if shield.size == 0:
        return lied
    Q = notes.Q
    honest = np.flatnonzero(notes.sent & ~is_liar[notes.i] & ~is_liar[notes.j])
    n = len(is_liar)
    info = np.zeros((n, 2, 2))
    vec = np.zeros((n, 2))
    Y = np.linalg.inv(Q[honest])
    np.add.at(info, notes.j[honest], Y)
    np.add.at(vec, notes.j[honest], (Y @ notes.u[honest][:, :, None])[:, :, 0])
    seen = np.linalg.det(info) > 0.0
    mean = np.zeros((n, 2))
    mean[seen] = np.linalg.solve(info[seen], vec[seen][:, :, None])[:, :, 0]
    victims = np.unique(notes.j[shield])
    slot = np.searchsorted(victims, notes.j[shield])
    candidates = [lied.u[shield], notes.u[shield]]
    candidates += [-t * mean[notes.j[shield]] for t in EXONERATION]
    best_T = np.full(len(victims), np.inf)
    best_u = lied.u[shield].copy()
    for cand in candidates:
        trial = lied.u.copy()
        trial[shield] = cand
        ids, T, _ = witness_statistic(
            WitnessNotes(trial, Q, notes.P_pos, notes.i, notes.j, notes.sent), params, victims
        )
        T_of = np.full(len(victims), np.inf)
        T_of[np.searchsorted(victims, ids)] = np.where(np.isnan(T), np.inf, T)
        better = T_of < best_T
        best_T = np.where(better, T_of, best_T)
        rows = better[slot]
        best_u[rows] = cand[rows]
    u = lied.u.copy()
    u[shield] = best_u
    return WitnessNotes(u, Q, notes.P_pos, notes.i, notes.j, notes.sent)


def widened(P: np.ndarray, memory, params: CLParams) -> np.ndarray:
    """The covariances ``P (B, 3, 3)`` as the step's correction uses them: times the factor
    each robot's outvoted, start-up and lock-out stages applied this step (``P`` itself when
    none)."""
    lockout = params.lockout_share > 0.0
    if not (params.outvoted or params.startup_steps > 0 or lockout) or memory is None:
        return P
    from resloc.cl.detection_lockout import applied_lockout_factors
    from resloc.cl.detection_outvoted import applied_factors
    from resloc.cl.detection_startup import applied_startup_factors

    f = applied_startup_factors(memory, len(P))
    if params.outvoted:
        f = f * applied_factors(memory, len(P))
    if lockout:
        f = f * applied_lockout_factors(memory, len(P))
    if memory.exempt is not None:  # the liars' own software skips the stages
        f = np.where(memory.exempt, 1.0, f)
    if not (f > 1.0).any():
        return P
    return np.asarray(P, float) * f[:, None, None]
