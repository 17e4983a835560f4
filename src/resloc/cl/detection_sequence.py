"""Sequence test on a neighbour's redundancy residuals: a slow lie accumulates evidence.

The redundancy stage (:mod:`resloc.cl.detection_redundancy`) judges each step alone: link
``(i, j)``'s fix of robot i against i's other fixes, ``d_j = f_j - m_-j`` with covariance
``C_d = C_j + (sum_{k != j} C_k^-1)^-1``, discarded when ``d^T C_d^-1 d`` exceeds the
chi-square gate. A lie that stays inside that gate every step (a compromised neighbour
leading its victims a few standard deviations along one direction, step after step) is
never caught, and its victims, with their other neighbours, follow it: over 1000 steps
the lead adds up (``docs/attack/redundancy.md``).

This stage keeps, per link, the (optionally discounted) sums of the residuals and of their
covariances since the link was last admitted,

``s <- lambda s + d``,   ``V <- lambda^2 V + C_d``,

and flags the link when ``s^T V^-1 s`` exceeds a chi-square gate (2 degrees of freedom,
``redundancy_sequence_gate``). Honest residuals are zero-mean (white to first order: the
fix's error is dominated by the sensor noise of that step), so ``s^T V^-1 s`` stays
chi-square with 2 degrees of freedom; a neighbour whose fixes lead by a mean ``b``
(whitened) per step reaches ``n b^2`` after n steps (``lambda = 1``). Inside the gate, the
sum of what a liar can lead by over n steps is ``sqrt(gate n)`` standard deviations, not
``sqrt(per-step gate) n``: its mean lead per step falls as ``1 / sqrt(n)``.

A flagged link is held out: its measurements are discarded and its fix enters no
reference of the redundancy stage (:func:`held_out`) for ``redundancy_sequence_hold``
evaluations of the link; then it is re-admitted with its sums reset, so an honest neighbour
hit by a false alarm (probability ``redundancy_sequence_false_alarm`` per evaluation, under
the white-residual model) is never locked out for good. The statistic is keyed ``(i, j)``
in the observer's :class:`~resloc.cl.memory.LinkMemory`; it reads only what the redundancy
stage computed, so it runs in one robot's process too.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams, at_robots

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = ["RedundancySequence", "held_out", "sequence_step"]

#: Per-link state: residual sum (2), covariance sum (a, b, c of a symmetric 2 x 2), hold.
WIDTH = 6
_HOLD = 5


def held_out(
    params: CLParams,
    memory: LinkMemory | None,
    i: np.ndarray | None,
    j: np.ndarray | None,
) -> np.ndarray | None:
    """Links ``(i, j)`` the sequence test holds out now, shape (E,); None when the stage is
    off or there is no memory to read."""
    if not params.redundancy_sequence or memory is None or i is None or j is None:
        return None
    state = memory.stage_statistic(RedundancySequence.name, width=WIDTH).get(i, j)
    return state[:, _HOLD] > 0.0


def sequence_step(
    state: np.ndarray,
    residual: np.ndarray,
    residual_cov: np.ndarray,
    judged: np.ndarray,
    gate: np.ndarray,
    hold: np.ndarray,
    forget: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One evaluation of each row's link.

    Parameters
    ----------
    state : ndarray, shape (E, 6)
        ``[s_x, s_y, V_a, V_b, V_c, hold]`` of each row's link before this evaluation.
    residual : ndarray, shape (E, 2)
    residual_cov : ndarray, shape (E, 2, 2)
    judged : ndarray of bool, shape (E,)
        Rows with a residual this step (the redundancy stage judged them).
    gate, hold, forget : ndarray, shape (E,)
        Chi-square gate, evaluations a flagged link is held out, discount ``lambda``.

    Returns
    -------
    discard : ndarray of bool, shape (E,)
        Rows held out (before or by this evaluation).
    statistic : ndarray, shape (E,)
        ``s^T V^-1 s`` after this evaluation (``nan`` where not updated).
    new_state : ndarray, shape (E, 6)
    """
    new = state.copy()
    holding = state[:, _HOLD] > 0.0
    update = judged & ~holding
    lam = forget
    s = lam[:, None] * state[:, 0:2] + np.where(update[:, None], residual, 0.0)
    Va = lam * lam * state[:, 2] + np.where(update, residual_cov[:, 0, 0], 0.0)
    Vb = lam * lam * state[:, 3] + np.where(
        update, 0.5 * (residual_cov[:, 0, 1] + residual_cov[:, 1, 0]), 0.0
    )
    Vc = lam * lam * state[:, 4] + np.where(update, residual_cov[:, 1, 1], 0.0)
    det = Va * Vc - Vb * Vb
    with np.errstate(divide="ignore", invalid="ignore"):
        stat = (Vc * s[:, 0] ** 2 - 2.0 * Vb * s[:, 0] * s[:, 1] + Va * s[:, 1] ** 2) / det
    stat = np.where(update & (det > 0.0), stat, np.nan)
    alarm = update & (stat > gate)
    keep = update & ~alarm
    new[keep, 0:2] = s[keep]
    new[keep, 2], new[keep, 3], new[keep, 4] = Va[keep], Vb[keep], Vc[keep]
    # A flagged link starts its hold with its sums reset (re-admitted afresh).
    new[alarm, 0:5] = 0.0
    new[alarm, _HOLD] = hold[alarm]
    new[holding, _HOLD] = state[holding, _HOLD] - 1.0
    return holding | alarm, stat, new


def sequence_evidence(
    residual: np.ndarray,
    residual_cov: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    params: CLParams,
    memory: LinkMemory | None,
    group: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """The stage's verdict for a whole step, from the redundancy residuals of every link.

    Per observer, at most one link is flagged a step: the one with the largest statistic
    above the gate (a liar's lead pulls the references of its observer's other fixes the
    other way, so their sums drift too, less in their own units; the liar's is the largest,
    as in the one-at-a-time exclusion of the redundancy stage). When a link is flagged, the
    sums of the observer's other links are reset: they were accumulated against references
    that held the flagged fix.

    Parameters
    ----------
    residual, residual_cov : ndarray, shapes (E, 2), (E, 2, 2)
        ``nan`` rows: not judged this step.
    i, j : ndarray of int, shape (E,)
        The links (their state is read from ``memory``, not modified).
    params : CLParams
    memory : LinkMemory or None
        None: no state (every link fresh).
    group : ndarray of int, shape (E,), optional
        Observer of each row for the one-per-observer choice (default ``i``; an attacker's
        stacked copies give each copy its own groups).

    Returns
    -------
    dict
        ``sequence_discard (E,)``: rows held out (before or by this step);
        ``sequence_state (E, 6)``: each row's link state after the step.
    """
    E = len(i)
    group = np.asarray(i if group is None else group)
    if memory is None:
        state = np.zeros((E, WIDTH))
    else:
        state = memory.stage_statistic(RedundancySequence.name, width=WIDTH).get(i, j)
    judged = np.isfinite(residual).all(axis=1)

    def per_row(value) -> np.ndarray:
        return np.broadcast_to(at_robots(value, i), (E,)).astype(float)

    gate = per_row(params.redundancy_sequence_gate)
    _, stat, new = sequence_step(
        state,
        np.nan_to_num(residual),
        np.nan_to_num(residual_cov),
        judged,
        np.full(E, np.inf),  # the alarm is chosen below, one per observer
        per_row(params.redundancy_sequence_hold),
        per_row(params.redundancy_sequence_forget),
    )
    over = np.flatnonzero(np.nan_to_num(stat, nan=-np.inf) > gate)
    discard = state[:, _HOLD] > 0.0
    if over.size:
        order = over[np.lexsort((-stat[over], group[over]))]
        first = np.r_[True, group[order][1:] != group[order][:-1]]
        alarm = order[first]
        flagged_groups = np.isin(group, group[alarm])
        reset = flagged_groups & judged & ~discard
        new[reset, 0:5] = 0.0
        new[alarm, _HOLD] = per_row(params.redundancy_sequence_hold)[alarm]
        discard[alarm] = True
    return {"sequence_discard": discard, "sequence_state": new}


class RedundancySequence:
    """Per-link sequence test on the redundancy residuals; holds a flagged link out."""

    name: ClassVar[str] = "redundancy_sequence"
    compiled: ClassVar[bool] = True  # resloc.cl.kernels_redundancy_verdicts.sequence_group
    overrides: ClassVar[bool] = False

    def problem(self, options: Any) -> str | None:
        """Why the scenario's ``[detector]`` ``options`` cannot run the stage (names the fix)."""
        if getattr(options, "redundancy_sequence", False) and not options.redundancy:
            return (
                "redundancy_sequence: true accumulates the redundancy stage's residuals; "
                "set detector.redundancy = true or redundancy_sequence = false"
            )
        return None

    def active(self, params: CLParams) -> bool:
        return bool(params.redundancy_sequence)

    def kernel_refusal(self, params: CLParams) -> str | None:
        """Why the compiled twin does not run ``params`` (it judges the redundancy stage's
        residuals: without the stage the reference raises the explanatory error)."""
        if not params.redundancy:
            return "the detector stage 'redundancy_sequence' needs redundancy = true"
        return None

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        if memory is None:
            raise ValueError(
                "detector redundancy sequence (params.redundancy_sequence) needs a LinkMemory"
            )
        ev = evidence
        if ev.sequence_discard is None or ev.sequence_state is None:
            raise ValueError(
                "detector redundancy sequence (params.redundancy_sequence) needs the step's "
                "verdict on the redundancy residuals (Evidence.sequence_discard: "
                "resloc.cl.detection_redundancy.fix_evidence with a LinkMemory)"
            )
        keep = np.ones(len(ev.i), bool)
        if ev.zone_substituted is not None:
            # Fused as the partner's fix, not as this reading: neither judged nor counted.
            keep = ~ev.zone_substituted
        # A link may repeat in one call (an attacker's stacked candidates, each judged
        # against the state before the call): store one row per link.
        store = memory.stage_statistic(self.name, width=WIDTH)
        keys = np.asarray(ev.i, np.int64) * store.n_nodes + np.asarray(ev.j, np.int64)
        rows = np.flatnonzero(keep)
        _, first = np.unique(keys[rows], return_index=True)
        rows = rows[first]
        store.set(ev.i[rows], ev.j[rows], ev.sequence_state[rows])
        return ev.sequence_discard & keep
