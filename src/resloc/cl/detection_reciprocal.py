"""Reciprocal range check: the two ends of a pair must agree on their distance.

When robots i and j both sense each other in a step, ``z_ij`` and ``z_ji`` measure the same
distance: with independent zero-mean range noise of standard deviation ``sigma_r`` at both
ends,

``d_ij = r_ij - r_ji ~ N(0, 2 sigma_r^2)``,   ``t = d_ij^2 / (2 sigma_r^2) ~ chi2(1)``.

Nothing about either robot's estimate enters ``d``: a lie on one end's range shows in full,
whatever the robots believe and whatever any other stage accepts. The partner's reading
arrives with its estimate message (``LinkBatch.z_reciprocal``, the zone-trust plumbing:
two numbers more per message).

Two tests, per link ``(i, j)`` of the observer's :class:`~resloc.cl.memory.LinkMemory`:

* **One step**: ``t > reciprocal_gate`` (the chi-square quantile at
  ``reciprocal_false_alarm``, 1e-3 by default): the reading is discarded this step.
* **Sequence**: ``s <- lambda s + d``, ``V <- lambda^2 V + 2 sigma_r^2`` since the link was
  last admitted; ``s^2 / V > reciprocal_sequence_gate`` (chi-square, 1 degree of freedom, at
  ``reciprocal_sequence_false_alarm``, 1e-6): the link is **held** out
  ``reciprocal_hold`` evaluations, then re-admitted with its sums reset (never locked out).
  A one-ended liar that stays under the one-step gate (``|b| < 3.3 sqrt(2) sigma_r`` per
  step) is caught by the sum after about ``gate_seq 2 sigma_r^2 / b^2`` steps: what it can
  shift a range by in sum over ``n`` steps falls from ``3.3 n`` to ``4.9 sqrt(n)`` times
  ``sqrt(2) sigma_r``.

**Which end is blamed.** The test says one of the two readings is false, not which:

* With zone trust (the map of the sensing danger zones, ``zone_trust_map``), a pair with
  exactly one end's estimate inside the map is left to the map: the end inside is the one
  the threat model lets lie (zone trust already withholds or substitutes its reading), so
  the outside end's reading is not judged by this stage.
* Otherwise **both links are held**: each end discards its own reading (both see the same
  ``|d|`` and keep the same sums, so the decision is symmetric without a message). Robot i
  cannot see j's other links, so it cannot tell from its own data which end the other
  stages would side with; blaming by i's redundancy verdict alone would let a liar at j
  keep i's honest reading out while j's own lie (which j's stages judge) goes on. Holding
  both costs an honest robot paired with a liar that one link (the redundancy stage and the
  robot's other neighbours carry it), and costs the liar's victim the lie.

Where it fails (``docs/attack/reciprocal.md``): an attacker that falsifies *both* readings of
a pair consistently (both ends in a danger zone, or a compromised robot lying about its own
readings with a falsified sensor at the other end) keeps ``d`` honest; the check then only
limits the *difference* of the two lies (the slack it spends). Bearings are not compared
(each is in its own robot's frame; the position fix of zone trust and the redundancy stage
use them).

The correction computes the verdict once per step over all links
(:func:`reciprocal_evidence`), so it is the same in either update mode and in one robot's
process (``RobotNode.correct``'s ``z_reciprocal``). Its compiled twin is the same pre-pass,
:func:`resloc.cl.kernels_reciprocal.reciprocal_verdicts`; with zone trust on (which withholds
and substitutes rows in the link loops, and the reference stores no state for them) the
state of those rows is put back after the loop
(:func:`resloc.cl.kernels_zone.keep_unjudged_state`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from resloc.cl.detection_zone import inside_zone_map, reciprocal_rows
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams, at_robots

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = [
    "ReciprocalCheck",
    "ReciprocalContext",
    "judged_pairs",
    "reciprocal_evidence",
    "reciprocal_step",
]

#: Per-link state: range-difference sum, its variance, evaluations left on hold.
STATE_WIDTH = 3
_SUM, _VAR, _HOLD = 0, 1, 2


def reciprocal_step(
    state: np.ndarray,
    difference: np.ndarray,
    judged: np.ndarray,
    variance: float | np.ndarray,
    gate: np.ndarray,
    sequence_gate: np.ndarray,
    hold: np.ndarray,
    forget: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One evaluation of each row's link.

    Parameters
    ----------
    state : ndarray, shape (E, 3)
        ``[s, V, hold]`` of each row's link before this evaluation.
    difference : ndarray, shape (E,)
        ``d = r_ij - r_ji`` (m; anything where not ``judged``).
    judged : ndarray of bool, shape (E,)
        Rows whose pair is judged this step (a partner reading, not left to the map).
    variance : float or ndarray, shape (E,)
        ``2 sigma_r^2`` (m^2).
    gate, sequence_gate, hold, forget : ndarray, shape (E,)
        One-step and summed chi-square gates (1 d.o.f.), evaluations a flagged link is held
        out, discount ``lambda`` of the sums.

    Returns
    -------
    discard : ndarray of bool, shape (E,)
        Held out (before or by this evaluation) or over the one-step gate.
    statistic : ndarray, shape (E,)
        ``s^2 / V`` after this evaluation (``nan`` where not updated).
    new_state : ndarray, shape (E, 3)
    """
    state = np.asarray(state, float)
    holding = state[:, _HOLD] > 0.0
    update = np.asarray(judged, bool) & ~holding
    d = np.where(update, difference, 0.0)
    var = np.broadcast_to(np.asarray(variance, float), d.shape)
    s = forget * state[:, _SUM] + d
    V = forget * forget * state[:, _VAR] + np.where(update, var, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        stat = np.where(update & (V > 0.0), s * s / V, np.nan)
        one_step = update & (d * d / var > gate)
    alarm = update & (stat > sequence_gate)
    new = state.copy()
    keep = update & ~alarm
    new[keep, _SUM], new[keep, _VAR] = s[keep], V[keep]
    # A flagged link starts its hold with its sums reset (re-admitted afresh).
    new[alarm, _SUM] = new[alarm, _VAR] = 0.0
    new[alarm, _HOLD] = hold[alarm]
    new[holding, _HOLD] = state[holding, _HOLD] - 1.0
    return holding | alarm | one_step, stat, new


def judged_pairs(
    z_reciprocal: np.ndarray | None,
    x_obs: np.ndarray | None,
    x_nb: np.ndarray | None,
    params: CLParams,
) -> np.ndarray:
    """Rows the check judges, shape (E,): a partner reading exists, and the pair is not
    left to the zone map (exactly one end's estimate inside it)."""
    if z_reciprocal is None:
        return np.zeros(0, bool)
    judged = np.isfinite(np.asarray(z_reciprocal, float)[:, 0])
    if params.zone_trust_map and x_obs is not None and x_nb is not None:
        inside = inside_zone_map(np.asarray(x_obs)[:, :2], params.zone_trust_map)
        partner = inside_zone_map(np.asarray(x_nb)[:, :2], params.zone_trust_map)
        judged &= inside == partner
    return judged


def reciprocal_evidence(
    z: np.ndarray,
    z_reciprocal: np.ndarray | None,
    i: np.ndarray,
    j: np.ndarray,
    params: CLParams,
    memory: LinkMemory | None,
    x_obs: np.ndarray | None = None,
    x_nb: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """The stage's :class:`~resloc.cl.detection.Evidence` fields for a whole step.

    Parameters
    ----------
    z : ndarray, shape (E, 2)
        The readings as reported (range, bearing).
    z_reciprocal : ndarray, shape (E, 2) or None
        The reverse link's reported reading (``nan``: none).
    i, j : ndarray of int, shape (E,)
        Observers (batch indices: per-robot gates are read at them) and neighbours (ids):
        the keys of the links' state in ``memory``.
    params : CLParams
    memory : LinkMemory or None
        Read, not modified (None: every link fresh).
    x_obs, x_nb : ndarray, shape (E, 3), optional
        The observers' and the neighbours' estimates (the zone map's blame rule).

    Returns
    -------
    dict
        ``reciprocal_discard (E,)`` and ``reciprocal_state (E, 3)`` (each row's link
        state after the step).
    """
    E = len(i)
    i = np.asarray(i)
    z_rec = np.full((E, 2), np.nan) if z_reciprocal is None else np.asarray(z_reciprocal, float)
    if memory is None:
        state = np.zeros((E, STATE_WIDTH))
    else:
        state = memory.stage_statistic(ReciprocalCheck.name, width=STATE_WIDTH).get(i, j)

    def per_row(value) -> np.ndarray:
        return np.broadcast_to(at_robots(value, i), (E,)).astype(float)

    discard, _, new = reciprocal_step(
        state,
        np.asarray(z, float)[:, 0] - z_rec[:, 0],
        judged_pairs(z_rec, x_obs, x_nb, params),
        2.0 * params.range_std**2,
        per_row(params.reciprocal_gate),
        per_row(params.reciprocal_sequence_gate),
        per_row(params.reciprocal_hold),
        per_row(params.reciprocal_forget),
    )
    return {"reciprocal_discard": discard, "reciprocal_state": new}


@dataclass
class ReciprocalContext:
    """What an attacker's copy of the detector needs to judge candidates on some rows of a
    step: the partner readings the victims will compare them with.

    Attributes
    ----------
    z : ndarray, shape (E, 2)
        Every link's reading of the step (as the attacker will leave it where it is not a
        candidate).
    i, j : ndarray of int, shape (E,)
    params : CLParams
        The victims'.
    rows : ndarray of int, shape (n,)
        The rows the candidates are for.
    memory : LinkMemory, optional
        The victims' (read only).
    x_obs, x_nb : ndarray, shape (E, 3), optional
        The victims' and their neighbours' estimates (the map's blame rule).
    """

    z: np.ndarray
    i: np.ndarray
    j: np.ndarray
    params: CLParams
    rows: np.ndarray
    memory: LinkMemory | None = None
    x_obs: np.ndarray | None = None
    x_nb: np.ndarray | None = None

    def fields(self, candidates: np.ndarray) -> dict[str, np.ndarray]:
        """Evidence fields for ``candidates``, shape (G, n, 2), flattened to (G n, ...).

        In each candidate set, a row whose reverse link is also a candidate row is compared
        with the partner's candidate of the same set (lies told on both ends together);
        otherwise with the partner's reading in :attr:`z`.
        """
        rows = np.asarray(self.rows)
        n = len(rows)
        candidates = np.asarray(candidates, float).reshape(-1, n, 2)
        G = len(candidates)
        reverse = reciprocal_rows(self.i, self.j)[rows]
        partner = np.where((reverse >= 0)[:, None], self.z[np.maximum(reverse, 0)], np.nan)
        partner = np.broadcast_to(partner, (G, n, 2)).copy()
        position = np.full(len(self.i), -1)
        position[rows] = np.arange(n)
        among = np.flatnonzero((reverse >= 0) & (position[np.maximum(reverse, 0)] >= 0))
        partner[:, among] = candidates[:, position[reverse[among]]]

        def tiled(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else np.tile(a[rows], (G, 1))

        return reciprocal_evidence(
            candidates.reshape(-1, 2),
            partner.reshape(-1, 2),
            np.tile(self.i[rows], G),
            np.tile(self.j[rows], G),
            self.params,
            self.memory,
            tiled(self.x_obs),
            tiled(self.x_nb),
        )


class ReciprocalCheck:
    """Discard a reading whose range disagrees with the partner's reading of the pair, this
    step or in sum since the link was admitted (held out a while, then re-admitted)."""

    name: ClassVar[str] = "reciprocal"
    compiled: ClassVar[bool] = True
    overrides: ClassVar[bool] = False

    def problem(self, options: Any) -> str | None:
        """Why the scenario's ``[detector]`` ``options`` cannot run as set (names the fix)."""
        if not getattr(options, "reciprocal", False):
            return None
        if options.reciprocal_sequence_false_alarm > options.reciprocal_false_alarm:
            return (
                f"reciprocal_sequence_false_alarm: {options.reciprocal_sequence_false_alarm!r}"
                f" is above reciprocal_false_alarm ({options.reciprocal_false_alarm!r}): the "
                "sum would hold honest links more often than the one-step test discards; "
                "set it <= reciprocal_false_alarm"
            )
        return None

    def active(self, params: CLParams) -> bool:
        return bool(params.reciprocal)

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        if memory is None:
            raise ValueError("detector reciprocal (params.reciprocal) needs a LinkMemory")
        ev = evidence
        if ev.reciprocal_discard is None or ev.reciprocal_state is None:
            raise ValueError(
                "detector reciprocal (params.reciprocal) needs the step's verdict on the "
                "partners' readings (Evidence.reciprocal_discard: "
                "resloc.cl.detection_reciprocal.reciprocal_evidence)"
            )
        keep = np.ones(len(ev.i), bool)
        if ev.zone_substituted is not None:
            # Fused as the partner's position fix, not as this reading: neither judged nor
            # counted.
            keep = ~ev.zone_substituted
        # A link may repeat in one call (an attacker's stacked candidates, each judged
        # against the state before the call): store one row per link.
        store = memory.stage_statistic(self.name, width=STATE_WIDTH)
        keys = np.asarray(ev.i, np.int64) * store.n_nodes + np.asarray(ev.j, np.int64)
        rows = np.flatnonzero(keep)
        _, first = np.unique(keys[rows], return_index=True)
        rows = rows[first]
        store.set(ev.i[rows], ev.j[rows], ev.reciprocal_state[rows])
        return ev.reciprocal_discard & keep
