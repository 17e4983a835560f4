"""What compromised robots do against the witness stage (:mod:`resloc.cl.detection_witness`).

Two things, both with full knowledge of the defence:

* **Their own notes lie** (:func:`lying_notes`). On a fellow compromised robot a liar sends
  the note that exonerates it most: minus ``t`` times the honest observers' mean note on it,
  ``t`` from :data:`EXONERATION` chosen per robot to minimise its statistic (``t = 0``: "I
  see it exactly where it says"; larger ``t`` pulls the mean back until the set's own
  consistency test drops the note), or its honest note when that exonerates best. On an
  honest neighbour it accuses: its honest note moved by :data:`ACCUSATION` standard
  deviations along world +x, the direction of the lies (a note far beyond that is dropped
  by the consistency test anyway).
* **Their broadcasts stay under every receiver's test** (:func:`within_witness`). The notes
  of the step arrive with the next step's frames, and each receiver updates its own
  statistic on the liar with the notes it received; a receiver whose statistic then
  exceeds ``witness_h`` ignores the liar from then on. The attacker knows every receiver's
  statistic (the memory) and this step's channel outcomes, and predicts which frames will
  get through by them (the next step's draws are not known when it lies). It scales all of
  one liar's lies of the step by one factor ``c`` in ``[0, 1]``, the largest (bisection)
  that keeps every honest receiver's updated statistic at most ``witness_h``, given its
  fellows' lying notes; a receiver already above ``h`` with the liar's honest notes is
  given up (it convicts whatever the liar sends). (One common factor per liar, not an
  allocation across victims: the per-victim oracle has already put every lie at its
  victim's own limit.)
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from resloc.cl.detection_witness import WitnessNotes, step_notes, witness_statistic
from resloc.cl.detection_witness_frames import delivered_store, received_state
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams, at_robots

__all__ = ["ACCUSATION", "EXONERATION", "lying_notes", "within_witness"]

#: Multiples ``t`` of the honest observers' mean note a fellow liar may send, negated.
EXONERATION = (0.0, 0.5, 1.0, 2.0, 4.0)
#: An accusing note's shift along world +x, in standard deviations of the note.
ACCUSATION = 3.0
#: Bisection steps of the common factor on a liar's lies (resolution 2^-12).
BUDGET_BISECTIONS = 12


def lying_notes(notes: WitnessNotes, is_liar: np.ndarray, params: CLParams) -> WitnessNotes:
    """``notes`` with the compromised observers' notes replaced by their lies.

    Parameters
    ----------
    notes : WitnessNotes
    is_liar : ndarray of bool, shape (B,)
        Which robots of the batch are compromised.
    params : CLParams
        The victims' (the statistic the exoneration minimises).
    """
    liar_obs = is_liar[notes.i] & notes.sent
    if not liar_obs.any():
        return notes
    on_liar = is_liar[notes.j]
    u = notes.u.copy()
    Q = notes.Q
    accuse = liar_obs & ~on_liar
    sd = np.sqrt(0.5 * (Q[:, 0, 0] + Q[:, 1, 1]))
    u[accuse, 0] += ACCUSATION * sd[accuse]
    exonerate = np.flatnonzero(liar_obs & on_liar)
    if exonerate.size:
        honest = np.flatnonzero(notes.sent & ~is_liar[notes.i] & on_liar)
        Y = np.linalg.inv(Q[honest])
        n = len(is_liar)
        info = np.zeros((n, 2, 2))
        vec = np.zeros((n, 2))
        np.add.at(info, notes.j[honest], Y)
        np.add.at(vec, notes.j[honest], (Y @ u[honest][:, :, None])[:, :, 0])
        seen = np.linalg.det(info) > 0.0
        mean = np.zeros((n, 2))
        mean[seen] = np.linalg.solve(info[seen], vec[seen][:, :, None])[:, :, 0]
        liars = np.unique(notes.j[exonerate])
        best_T = np.full(len(liars), np.inf)
        best_u = u[exonerate].copy()
        for t in (None, *EXONERATION):  # None: its honest note, if that exonerates best
            trial = u.copy()
            if t is not None:
                trial[exonerate] = -t * mean[notes.j[exonerate]]
            ids, T, _ = witness_statistic(
                WitnessNotes(trial, Q, notes.P_pos, notes.i, notes.j, notes.sent), params, liars
            )
            T_of = np.full(len(liars), np.inf)
            T_of[np.searchsorted(liars, ids)] = T
            better = T_of < best_T
            best_T = np.where(better, T_of, best_T)
            rows_better = better[np.searchsorted(liars, notes.j[exonerate])]
            best_u[rows_better] = trial[exonerate][rows_better]
        u[exonerate] = best_u
    return WitnessNotes(u, Q, notes.P_pos, notes.i, notes.j, notes.sent)


def within_witness(
    a: np.ndarray,
    path: Callable[[np.ndarray], np.ndarray],
    rows: np.ndarray,
    z_all: np.ndarray,
    x_obs: np.ndarray,
    P_obs: np.ndarray,
    x_nb: np.ndarray,
    P_nb: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    channel_ok: np.ndarray,
    is_liar: np.ndarray,
    params: CLParams,
    memory: LinkMemory,
) -> np.ndarray:
    """The liars' fractions ``a (n,)`` on ``rows`` (their links this step, ``path(frac)``
    the readings they inject) scaled, per liar, by the largest common factor that keeps
    every honest receiver's witness statistic on it at most ``witness_h`` once this step's
    notes arrive.

    ``z_all (E, 2)``: the step's readings (honest outside ``rows``); ``x_obs, P_obs``: the
    observers' predicted estimates; ``x_nb, P_nb``: the broadcast estimates and claims;
    ``channel_ok``: the step's channel outcomes; all rows of the step (the notes of every
    observer enter the statistic). The receivers' statistics now are those after the notes
    of the step before arrive with this step's frames (what the defence computes at the start
    of the step, from ``memory``); which receiver will get this step's notes is predicted
    by this step's channel outcomes (the next step's draws are not known yet). A receiver
    already above ``h`` with honest notes (it convicts the liar whatever the liar sends,
    e.g. after a frame the prediction missed) constrains nothing.
    """
    liars = np.unique(j[rows])
    where = np.searchsorted(liars, j[rows])
    h_of = np.broadcast_to(np.asarray(at_robots(params.witness_h, liars), float), liars.shape)
    now = delivered_store(params, memory, i, j, channel_ok, liars)

    def after(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        z = np.array(z_all, float)
        z[rows] = path((c[where] * a)[None])[0]
        notes = lying_notes(step_notes(z, x_obs, P_obs, x_nb, P_nb, i, j, params), is_liar, params)
        recv, on, S = received_state(notes, params, now, i, j, channel_ok, liars)
        honest = ~is_liar[recv]
        return recv[honest], on[honest], S[honest]

    recv0, on0, S0 = after(np.zeros(len(liars)))
    h0 = h_of[np.searchsorted(liars, on0)]
    savable = S0 <= h0
    n = len(is_liar)
    keys0 = recv0 * n + on0  # sorted (receiver, then robot)

    def worst(c: np.ndarray) -> np.ndarray:  # (L,) factors -> (L,) largest savable statistic
        recv, on, S = after(c)
        pos = np.minimum(np.searchsorted(keys0, recv * n + on), max(len(keys0) - 1, 0))
        counted = (keys0[pos] == recv * n + on) & savable[pos] if len(keys0) else S < 0
        out = np.zeros(len(liars))  # a liar nobody received a note on is not judged
        np.maximum.at(out, np.searchsorted(liars, on[counted]), S[counted])
        return out

    ok = worst(np.ones(len(liars))) <= h_of
    if ok.all():
        return a
    lo, hi = np.zeros(len(liars)), np.ones(len(liars))
    for _ in range(BUDGET_BISECTIONS):
        mid = np.where(ok, 1.0, 0.5 * (lo + hi))
        good = worst(mid) <= h_of
        lo = np.where(good, mid, lo)
        hi = np.where(good, hi, mid)
    c = np.where(ok, 1.0, lo)
    return c[where] * a
