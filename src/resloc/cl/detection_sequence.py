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


class RedundancySequence:
    """Per-link sequence test on the redundancy residuals; holds a flagged link out."""

    name: ClassVar[str] = "redundancy_sequence"
    compiled: ClassVar[bool] = False
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

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        if memory is None:
            raise ValueError(
                "detector redundancy sequence (params.redundancy_sequence) needs a LinkMemory"
            )
        ev = evidence
        if ev.fix_residual is None or ev.fix_residual_cov is None:
            raise ValueError(
                "detector redundancy sequence (params.redundancy_sequence) needs the step's "
                "redundancy residuals (Evidence.fix_residual: "
                "resloc.cl.detection_redundancy.fix_evidence; set params.redundancy)"
            )
        E = len(ev.i)
        store = memory.stage_statistic(self.name, width=WIDTH)
        state = store.get(ev.i, ev.j)
        judged = np.isfinite(ev.fix_residual).all(axis=1)
        if ev.zone_substituted is not None:
            judged &= ~ev.zone_substituted  # fused as the partner's fix, not this reading

        def per_row(value) -> np.ndarray:
            return np.broadcast_to(at_robots(value, ev.i), (E,)).astype(float)

        discard, _, new = sequence_step(
            state,
            np.nan_to_num(ev.fix_residual),
            np.nan_to_num(ev.fix_residual_cov),
            judged,
            per_row(params.redundancy_sequence_gate),
            per_row(params.redundancy_sequence_hold),
            per_row(params.redundancy_sequence_forget),
        )
        # A link may repeat in one call (an attacker's stacked candidates, each judged
        # against the state before the call): store one row per link.
        keys = np.asarray(ev.i, np.int64) * store.n_nodes + np.asarray(ev.j, np.int64)
        _, first = np.unique(keys, return_index=True)
        store.set(ev.i[first], ev.j[first], new[first])
        return discard
