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
  get through by them (the next step's draws are not known when it lies). It scales its
  lies of the step so that every honest receiver's updated statistic stays at most
  ``witness_h``, given its fellows' lying notes; a receiver already above ``h`` with the
  liar's honest notes is given up (it convicts whatever the liar sends). How the budget is
  spread over the victims is a choice (:data:`WITNESS_BUDGETS`): by default the links whose
  notes nobody reads or the statistic can drop get their whole lie first (``"spared"``),
  the weaker ``"common"`` scales every lie by one factor.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from resloc.cl.detection_witness import WitnessNotes, liars_at, step_notes, witness_statistic
from resloc.cl.detection_witness_frames import delivered_store, received_state
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams, at_robots

__all__ = [
    "ACCUSATION",
    "EXONERATION",
    "WITNESS_BUDGETS",
    "liars_send_all",
    "lying_notes",
    "within_witness",
]

#: Multiples ``t`` of the honest observers' mean note a fellow liar may send, negated.
EXONERATION = (0.0, 0.5, 1.0, 2.0, 4.0)
#: An accusing note's shift along world +x, in standard deviations of the note.
ACCUSATION = 3.0
#: Bisection steps of the common factor on a liar's lies (resolution 2^-12).
BUDGET_BISECTIONS = 12
#: How a liar spends its witness budget across its victims (:func:`within_witness`):
#: ``"spared"`` (the default) or ``"common"`` (one factor on every lie, the weaker one
#: measured first).
WITNESS_BUDGETS = ("spared", "common")


def liars_send_all(notes: WitnessNotes, is_liar: np.ndarray) -> WitnessNotes:
    """``notes`` with every compromised observer's finite note marked sent: an honest
    observer sends none on a neighbour whose estimate was jammed to it, nor from inside the
    zone-trust map, but its receivers can check neither, so a liar is not bound by either."""
    extra = is_liar[notes.i] & ~notes.sent & np.isfinite(notes.u).all(axis=1)
    if not extra.any():
        return notes
    return WitnessNotes(notes.u, notes.Q, notes.P_pos, notes.i, notes.j, notes.sent | extra)


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
    notes = liars_send_all(notes, is_liar)
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
    budget: str = "spared",
    give_up: int = 0,
) -> np.ndarray:
    """The liars' fractions ``a (n,)`` on ``rows`` (their links this step, ``path(frac)``
    the readings they inject) scaled, per link, so that every honest receiver's witness
    statistic on each liar stays at most ``witness_h`` once this step's notes arrive.

    ``z_all (E, 2)``: the step's readings (honest outside ``rows``); ``x_obs, P_obs``: the
    observers' predicted estimates; ``x_nb, P_nb``: the broadcast estimates and claims;
    ``channel_ok``: the step's channel outcomes; all rows of the step (the notes of every
    observer enter the statistic). The receivers' statistics now are those after the notes
    of the step before arrive with this step's frames (what the defence computes at the start
    of the step, from ``memory``); which receiver will get this step's notes is predicted
    by this step's channel outcomes (the next step's draws are not known yet). A receiver
    already above ``h`` with honest notes (it convicts the liar whatever the liar sends,
    e.g. after a frame the prediction missed) constrains nothing.

    ``budget`` (:data:`WITNESS_BUDGETS`): how the lies are scaled. ``"common"``: one factor
    per liar on all its lies (bisection). ``"spared"`` (the default, stronger): the links
    whose notes no receiver reads (observer inside the zone-trust map) keep their whole lie;
    the links whose notes the statistic's drop-any-``f`` rule can discard (the fellow liars'
    own links, whose notes are replaced by exonerating ones, and the ``f`` honest victims
    whose notes carry the largest share of the lie, ``a |Q^-1 e_x|``) are filled first, then
    the rest by one common factor (one bisection along that path); per liar, when the spared
    links alone cannot be filled, the common factor is also tried and the larger total lie
    (``sum a c``) kept. ``give_up``: per liar, at most that many honest receivers may be
    above ``h`` (convicting it) at any time, those already above counted (the constraint is
    on the next largest statistic; without the count, each step would give up one more).
    """
    if budget not in WITNESS_BUDGETS:
        raise ValueError(f"witness budget {budget!r}: unknown; known: {', '.join(WITNESS_BUDGETS)}")
    liars = np.unique(j[rows])
    where = np.searchsorted(liars, j[rows])
    h_of = np.broadcast_to(np.asarray(at_robots(params.witness_h, liars), float), liars.shape)
    now = delivered_store(params, memory, i, j, channel_ok, liars)

    def after(c_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        z = np.array(z_all, float)
        z[rows] = path((c_rows * a)[None])[0]
        notes = lying_notes(
            step_notes(z, x_obs, P_obs, x_nb, P_nb, i, j, params, channel_ok), is_liar, params
        )
        recv, on, S = received_state(notes, params, now, i, j, channel_ok, liars)
        honest = ~is_liar[recv]
        return recv[honest], on[honest], S[honest]

    recv0, on0, S0 = after(np.zeros(len(rows)))
    h0 = h_of[np.searchsorted(liars, on0)]
    savable = S0 <= h0
    n = len(is_liar)
    keys0 = recv0 * n + on0  # sorted (receiver, then robot)
    # At most ``give_up`` receivers convict a liar at any time: those already above h count.
    above = np.bincount(np.searchsorted(liars, on0[~savable]), minlength=len(liars))
    rank = np.maximum(int(give_up) - above, 0)

    def fits(c_rows: np.ndarray) -> np.ndarray:  # (len(rows),) factors -> (L,) all kept
        recv, on, S = after(c_rows)
        pos = np.minimum(np.searchsorted(keys0, recv * n + on), max(len(keys0) - 1, 0))
        counted = (keys0[pos] == recv * n + on) & savable[pos] if len(keys0) else S < 0
        liar_of = np.searchsorted(liars, on[counted])
        worst = np.zeros(len(liars))  # a liar nobody received a note on is not judged
        for k in range(len(liars)):
            mine = np.sort(S[counted][liar_of == k])[::-1]
            worst[k] = mine[rank[k]] if len(mine) > rank[k] else 0.0
        return worst <= h_of

    def bisect(factors: Callable[[np.ndarray], np.ndarray], top: float) -> np.ndarray:
        """The largest ``s`` per liar in ``[0, top]`` with ``factors(s)`` kept (every
        fraction a lower bound tested good: ``s = 0`` sends nothing on the scaled links)."""
        ok = fits(factors(np.full(len(liars), top)))
        lo, hi = np.zeros(len(liars)), np.full(len(liars), top)
        if ok.all():
            return hi
        for _ in range(BUDGET_BISECTIONS + (top > 1.0)):
            mid = np.where(ok, top, 0.5 * (lo + hi))
            good = fits(factors(mid))
            lo = np.where(good, mid, lo)
            hi = np.where(good, hi, mid)
        return np.where(ok, top, lo)

    def common(s: np.ndarray) -> np.ndarray:
        return s[where]

    if budget == "common":
        return common(bisect(common, 1.0)) * a

    notes0 = step_notes(
        np.array(z_all, float), x_obs, P_obs, x_nb, P_nb, i, j, params, channel_ok
    )  # the honest notes: who is read, and each note's weight
    free = ~notes0.sent[rows]
    from_fellow = is_liar[i[rows]]
    Qx = np.linalg.solve(notes0.Q[rows], np.broadcast_to([1.0, 0.0], (len(rows), 2))[..., None])
    share = np.where(free | from_fellow, -np.inf, a * np.hypot(Qx[:, 0, 0], Qx[:, 1, 0]))
    f = liars_at(params, liars)
    spared = from_fellow & ~free
    for k in range(len(liars)):
        mine = np.flatnonzero((where == k) & np.isfinite(share))
        spared[mine[np.argsort(-share[mine], kind="stable")[: f[k]]]] = True

    def filled(s: np.ndarray) -> np.ndarray:  # s in [0, 2]: the spared links, then the rest
        s = s[where]
        return np.where(free, 1.0, np.where(spared, np.clip(s, 0, 1), np.clip(s - 1, 0, 1)))

    s = bisect(filled, 2.0)
    c = filled(s)
    short = s < 1.0
    if short.any():
        c_common = common(bisect(common, 1.0))
        value = np.bincount(where, c * a, len(liars))
        better = np.bincount(where, c_common * a, len(liars)) > value
        c = np.where(better[where], c_common, c)
    return c * a
