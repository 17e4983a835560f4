"""Witnesses: a robot's observers compare notes on it (a per-robot test across observers).

Every per-link test judges a neighbour's broadcast against one observer's view; a
compromised robot that tells each neighbour the largest lie that neighbour's tests accept
stays under all of them, and two agreeing liars around one victim look like a majority
(``docs/attack/compromised_long.md``). Each observer, however, has its own reading of the
liar, and the liar's lies must survive all of them at once. This stage sums that evidence.

**Notes.** Each step every robot i, for each neighbour j it measured and whose broadcast
it received this step (the link's ``channel_ok``: no note on an estimate jammed in the CDZ,
which a robot's process never gets), computes the position of j its own estimate and its
reading imply, ``g_ij = p_i + r u(theta_i + b)``, and the
residual between j's broadcast position and it,

``u_ij = p_j - g_ij``,   ``cov = P_j,pos + Q_ij``,  ``Q_ij = J_x P_i J_x^T + J_z R J_z^T``

(first order in i's estimate and the sensor noise, at the predicted geometry; the range
corrected for the mean shortening the angle's noise causes, as
:func:`~resloc.cl.detection_redundancy_fixes.position_fix` does). The residuals of different
observers of j share j's own estimation error: ``P_j,pos`` (j's *claimed* covariance: a
robot claiming a small covariance asserts small residuals) is common to all of them, and
only the ``Q_ij`` are treated as independent (the observers' cross-covariances with each
other, which naive CL fusion does not track either, are ignored). Robot i sends its notes
(j's id, ``u_ij``, ``Q_ij`` and ``P_j,pos``, as the runtime encodes them) with its next
broadcast: one frame per robot and step (``WIRE_BYTES["witness_frame"]`` plus
``"witness_note"`` per note). Notes of readings the observer itself distrusts (its estimate
inside the zone-trust map) are ignored by the receivers (they are sent and counted: a
receiver sees where the observer says it is).
In one robot's process (:class:`~resloc.cl.node.RobotNode`) the stage sees only that robot's
notes unless the runtime hands it the notes its neighbours' frames carried
(:meth:`~resloc.cl.node.RobotNode.receive_witness`, ``docs/runtime.md``). In the
simulator each receiver judges the notes it received (:mod:`resloc.cl.detection_witness_frames`:
the frames travel over the links' channels, jammed in the CDZ like the estimates).

**The aggregate of robot j's notes, robust to f lying observers** (``witness_liars``: the
compromised robots also send notes, and may exonerate each other or accuse honest robots).
For a set ``K`` of notes the information-weighted mean and its covariance are

``m_K = Y_K^-1 sum_K Q_k^-1 u_k``,  ``Y_K = sum_K Q_k^-1``,
``T_K = m_K^T (P_j,pos + Y_K^-1)^-1 m_K``   (chi-square, 2 dof, for an honest j),

and the set is *consistent* when ``c_K = sum_K u_k^T Q_k^-1 u_k - m_K^T Y_K m_K`` (the
spread of the notes about their mean; j's own error cancels in it) is under the
chi-square quantile with ``2 (|K| - 1)`` degrees of freedom at ``witness_false_alarm``.
The step's statistic of j is the smallest ``T_K`` over the consistent sets left after
dropping any ``d <= f`` notes:

``T_j = min { T_K : K = all notes minus at most f, c_K consistent }``.

So j is accused only if *every* way of discarding f notes still convicts it: f liars'
accusations of an honest robot can always be dropped (the honest notes alone are a
candidate set, consistent with probability ``1 - witness_false_alarm``), and f fellow
liars' notes can pull the mean of a liar's notes only as far as the honest notes'
consistency allows. A robot with at most ``f`` notes in a step is not judged (its
statistic only decays). When no candidate set is consistent (more than f notes disagree:
outside the threat model, or j lying inconsistently to its observers) the step counts
``witness_h / 2``.

**Sequence test, with recovery.** Per receiver r and robot j, over the notes on j that r
received, ``S_{r,j} <- clip(S_{r,j} + min(T, h / 2) - k, 0, 2 h)`` (``k = witness_k``,
``h = witness_h``; a step without judgement adds ``-k``). While ``S_{r,j} > h`` receiver r
discards j's broadcasts (the link ``(r, j)``). The notes keep coming (the readings are the
observers' own), so a robot that stops lying decays back under ``h`` in at most
``h / (k - 2)`` steps on average: no robot is locked out forever.

**Latency.** The notes of step ``t`` travel in the observers' frames of step ``t + 1``
(:func:`~resloc.cl.detection_witness_frames.record_witness` keeps them at the end of step
``t``; :func:`~resloc.cl.detection_witness_frames.deliver_witness` delivers them at the
start of step ``t + 1``, before any verdict): the verdict applied in step ``t + 1`` reads
the notes up to step ``t``. An attacker that knows the defence keeps every honest
receiver's ``S_{r,j}`` under ``h`` (the compromised robot's oracle,
:mod:`resloc.world.attackers.witness`).

What it assumes, where it fails (``docs/attack/witness.md``): at most f of a robot's
observers lie (in their notes) in any step; the observers' readings of j are honest
(sensing attacks inside the mapped zone are excluded through the zone-trust map; without
the map an in-zone sensing attack makes honest observers' notes lie); the observers'
own estimates are not all pulled the same way by the lie (an observer a lie pulled by
``delta`` sees every neighbour ``delta`` off: the test compares j with the observers'
consensus, not with the truth). The compiled correction takes the stage's verdict as a
per-link mask known before its loop (:mod:`resloc.cl.kernels_witness`); robot processes
carry the notes on their estimate frames (``docs/runtime.md``).
"""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams, at_robots

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = [
    "WitnessCheck",
    "WitnessNotes",
    "liars_at",
    "note_groups",
    "note_information",
    "reference_statistic",
    "set_statistic",
    "step_notes",
    "witness_cusum",
    "witness_notes",
    "witness_state",
    "witness_statistic",
]

#: The name of the per-robot statistic in :meth:`LinkMemory.stage_statistic` (keyed (j, j)).
STATE = "witness"


def witness_notes(
    z: np.ndarray, x_obs: np.ndarray, P_obs: np.ndarray, x_nb: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each observer's note on a neighbour: its broadcast position minus the position the
    observer's estimate and reading imply, and that residual's independent covariance.

    Parameters
    ----------
    z : ndarray, shape (E, 2)
        Range and bearing of j measured by i.
    x_obs, P_obs : ndarray, shapes (E, 3), (E, 3, 3)
        The observers' estimates.
    x_nb : ndarray, shape (E, 3)
        The neighbours' broadcast estimates.
    R : ndarray, shape (2, 2)

    Returns
    -------
    u : ndarray, shape (E, 2)
        ``p_j - g_ij``.
    Q : ndarray, shape (E, 2, 2)
        ``J_x P_i J_x^T + J_z R J_z^T`` (j's own covariance not included).
    """
    z, x_obs, P_obs, x_nb = (np.asarray(a, float) for a in (z, x_obs, P_obs, x_nb))
    a = x_obs[:, 2] + z[:, 1]
    # As position_fix: undo the mean shortening of a direction read with angle noise.
    r_mean = z[:, 0] * np.exp(0.5 * (R[1, 1] + P_obs[:, 2, 2]))
    implied = x_obs[:, :2] + r_mean[:, None] * np.stack([np.cos(a), np.sin(a)], axis=1)
    u = x_nb[:, :2] - implied
    # Jacobians at the predicted geometry (weights that moved with the reading's own noise
    # would bias the mean the notes are combined into).
    rel = x_nb[:, :2] - x_obs[:, :2]
    r = np.hypot(rel[:, 0], rel[:, 1])
    use = r > 0.0
    c = np.where(use, rel[:, 0] / np.where(use, r, 1.0), np.cos(a))
    s = np.where(use, rel[:, 1] / np.where(use, r, 1.0), np.sin(a))
    r = np.where(use, r, z[:, 0])
    E = len(z)
    J_x = np.zeros((E, 2, 3))
    J_x[:, 0, 0] = J_x[:, 1, 1] = 1.0
    J_x[:, 0, 2], J_x[:, 1, 2] = -r * s, r * c
    J_z = np.stack([np.stack([c, -r * s], 1), np.stack([s, r * c], 1)], 1)
    Q = J_x @ P_obs @ np.swapaxes(J_x, -1, -2) + J_z @ R @ np.swapaxes(J_z, -1, -2)
    return u, 0.5 * (Q + np.swapaxes(Q, -1, -2))


class WitnessNotes:
    """The notes of one step (every link), as the robots receive them.

    Attributes
    ----------
    u, Q : ndarray, shapes (E, 2), (E, 2, 2)
        :func:`witness_notes`.
    P_pos : ndarray, shape (E, 2, 2)
        The position block of the covariance neighbour j claimed to observer i.
    i, j : ndarray of int, shape (E,)
    sent : ndarray of bool, shape (E,)
        Notes the receivers use (not those of an observer inside the zone-trust map, nor
        those on a neighbour whose estimate the observer did not receive this step).
    """

    def __init__(self, u, Q, P_pos, i, j, sent) -> None:
        self.u, self.Q, self.P_pos = u, Q, P_pos
        self.i, self.j, self.sent = np.asarray(i), np.asarray(j), np.asarray(sent, bool)

    def __len__(self) -> int:
        return len(self.u)


def step_notes(
    z: np.ndarray,
    x_obs: np.ndarray,
    P_obs: np.ndarray,
    x_nb: np.ndarray,
    P_nb: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    params: CLParams,
    received: np.ndarray,
) -> WitnessNotes:
    """Every link's note of the step (what the CL step and an attacker's copy both
    compute): readings ``z (E, 2)`` as reported, the observers' predicted estimates, the
    neighbours' broadcast estimates with their claimed covariances ``P_nb (E, 3, 3)``.
    ``received (E,)``: observer i got j's estimate this step (the link's ``channel_ok``,
    the draw j's estimate message to i gets): a note on an estimate the observer never
    received is not sent (a robot's process cannot write it)."""
    from resloc.cl.detection_zone import inside_zone_map
    from resloc.cl.kernels_witness_notes import fast_notes  # numba's import, on first use

    notes = fast_notes(z, x_obs, P_obs, x_nb, params.R)
    u, Q = witness_notes(z, x_obs, P_obs, x_nb, params.R) if notes is None else notes
    sent = np.ones(len(u), bool)
    if params.zone_trust and params.zone_trust_map:
        sent = ~inside_zone_map(np.asarray(x_obs)[:, :2], params.zone_trust_map)
    sent &= np.isfinite(u).all(axis=1) & np.asarray(received, bool)
    return WitnessNotes(u, Q, np.asarray(P_nb, float)[:, :2, :2], i, j, sent)


_COMBINATIONS: dict[tuple[int, int], np.ndarray] = {}
_GATES: dict[tuple[float, int], float] = {}


def _dropped(m: int, d: int) -> np.ndarray:
    """Every set of ``d`` of ``m`` positions, shape (K, d)."""
    key = (m, d)
    if key not in _COMBINATIONS:
        combos = list(itertools.combinations(range(m), d))
        _COMBINATIONS[key] = np.array(combos, dtype=np.intp).reshape(len(combos), d)
    return _COMBINATIONS[key]


_GATE_TABLES: dict[tuple[float, int], np.ndarray] = {}


def consistency_gates(p: float, largest: int) -> np.ndarray:
    """``gates[n]``: the consistency gate of a set of ``n`` notes for ``2 <= n <= largest``
    (at least 16; ``inf`` below 2), kept per ``p``."""
    key = (float(p), max(int(largest), 16))
    if key not in _GATE_TABLES:
        gates = np.full(key[1] + 1, np.inf)
        for n in range(2, key[1] + 1):
            gates[n] = consistency_gate(p, 2 * (n - 1))
        _GATE_TABLES[key] = gates
    return _GATE_TABLES[key]


def consistency_gate(p: float, dof: int) -> float:
    key = (float(p), int(dof))
    if key not in _GATES:
        from resloc.distributions import chi2_isf

        _GATES[key] = float(chi2_isf(p, dof))
    return _GATES[key]


def witness_statistic(
    notes: WitnessNotes, params: CLParams, robots: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The step's statistic of every robot noted on: the smallest ``T_K`` over the
    consistent sets left after dropping at most ``f`` notes (module docstring).

    Parameters
    ----------
    notes : WitnessNotes
    params : CLParams
        ``witness_liars`` (f), ``witness_false_alarm``, ``witness_h`` (read at each robot).
    robots : ndarray of int, optional
        Judge only these robots (default: every robot with a sent note).

    Returns
    -------
    robots : ndarray of int, shape (G,)
        The robots noted on (sorted).
    T : ndarray, shape (G,)
        Their statistics (0 where not judged).
    judged : ndarray of bool, shape (G,)
        More than f notes on the robot this step.
    """
    from resloc.cl.kernels_witness_statistic import fast_statistic  # numba's import, on first use

    fast = fast_statistic(notes, params, robots)
    if fast is not None:
        return fast
    return reference_statistic(notes, params, robots)


def note_groups(
    notes: WitnessNotes, robots: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The sent notes grouped by the robot they are on: ``rows`` (sorted by ``j``, stable),
    and per group the robot ``ids``, its first position in ``rows`` and its size."""
    rows = np.flatnonzero(notes.sent)
    if robots is not None:
        rows = rows[np.isin(notes.j[rows], robots)]
    rows = rows[np.argsort(notes.j[rows], kind="stable")]
    ids, start, count = np.unique(notes.j[rows], return_index=True, return_counts=True)
    return rows, ids, start, count


def liars_at(params: CLParams, ids: np.ndarray) -> np.ndarray:
    """``f`` of each robot in ``ids (G,)``: the notes its statistic may drop, int64."""
    f = np.rint(at_robots(params.witness_liars, ids)).astype(np.int64)
    return np.ascontiguousarray(np.broadcast_to(f, ids.shape))


def reference_statistic(
    notes: WitnessNotes, params: CLParams, robots: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`witness_statistic` in numpy (its executable specification)."""
    rows, ids, start, count = note_groups(notes, robots)
    T, judged = reference_groups(notes, params, rows, start, count, ids)
    return ids, T, judged


def group_statistic(
    notes: WitnessNotes,
    params: CLParams,
    rows: np.ndarray,
    start: np.ndarray,
    count: np.ndarray,
    ids: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The statistic ``T (G,)`` and ``judged (G,)`` of any groups of notes: group ``g`` is
    ``rows[start[g] : start[g] + count[g]]`` of ``notes``, all on robot ``ids[g]`` (its
    ``f`` and ``h``). The compiled twin with the numba backend, else the numpy spec."""
    from resloc.cl.kernels_witness_statistic import fast_groups  # numba's import, on first use

    fast = fast_groups(notes, params, rows, start, count, ids)
    if fast is not None:
        return fast
    return reference_groups(notes, params, rows, start, count, ids)


def note_information(u: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Each note's information terms ``[Y_a, Y_b, Y_c, y_a, y_b, q]``, shape (E, 6), from
    ``u (E, 2)``, ``Q (E, 2, 2)``: ``Y = Q^-1`` (entries a, b, c of the symmetric 2 x 2),
    ``y = Y u``, ``q = u^T Y u``; a set's terms are their sums (module docstring)."""
    det = Q[:, 0, 0] * Q[:, 1, 1] - Q[:, 0, 1] * Q[:, 1, 0]
    Ya, Yb, Yc = Q[:, 1, 1] / det, -0.5 * (Q[:, 0, 1] + Q[:, 1, 0]) / det, Q[:, 0, 0] / det
    ya = Ya * u[:, 0] + Yb * u[:, 1]
    yb = Yb * u[:, 0] + Yc * u[:, 1]
    q = u[:, 0] * ya + u[:, 1] * yb
    return np.stack([Ya, Yb, Yc, ya, yb, q], axis=1)


def set_statistic(
    sums: np.ndarray, Pa: np.ndarray, Pb: np.ndarray, Pc: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A set's spread ``c_K`` and statistic ``T_K`` (module docstring) from its summed
    information terms ``sums (..., 6)`` (:func:`note_information`) and j's claimed position
    covariance entries ``Pa, Pb, Pc`` (broadcastable to ``sums[..., 0]``); shapes (...)."""
    Sa, Sb, Sc, sa, sb, sq = np.moveaxis(sums, -1, 0)
    dS = Sa * Sc - Sb * Sb
    Ia, Ib, Ic = Sc / dS, -Sb / dS, Sa / dS  # Y_K^-1
    ma, mb = Ia * sa + Ib * sb, Ib * sa + Ic * sb
    spread = sq - (ma * sa + mb * sb)
    Ca, Cb, Cc = Pa + Ia, Pb + Ib, Pc + Ic
    T = (Cc * ma * ma - 2.0 * Cb * ma * mb + Ca * mb * mb) / (Ca * Cc - Cb * Cb)
    return spread, T


def reference_groups(notes, params, rows, start, count, ids) -> tuple[np.ndarray, np.ndarray]:
    """:func:`group_statistic` in numpy (its executable specification)."""
    G = len(ids)
    T = np.zeros(G)
    f = liars_at(params, ids)
    judged = count > f
    if not judged.any():
        return T, judged
    per_note = note_information(notes.u[rows], notes.Q[rows])  # (E', 6)
    # j's claimed position covariance: the largest claim among its notes (per-link claims
    # could differ; the largest is the most lenient to j).
    P = notes.P_pos[rows]
    trace = P[:, 0, 0] + P[:, 1, 1]
    big = start + np.array(
        [np.argmax(trace[s : s + n]) for s, n in zip(start, count, strict=True)], dtype=np.intp
    )
    Pj = P[big]
    half_h = 0.5 * np.broadcast_to(np.asarray(at_robots(params.witness_h, ids), float), (G,))
    p_fa = float(np.max(params.witness_false_alarm))
    for m in np.unique(count[judged]):
        for fg in np.unique(f[judged & (count == m)]):
            g = np.flatnonzero(judged & (count == m) & (f == fg))
            members = per_note[start[g][:, None] + np.arange(m)]  # (n_g, m, 6)
            total = members.sum(axis=1)  # (n_g, 6)
            best = np.full(len(g), np.inf)
            for d in range(int(min(fg, m - 1)) + 1):
                drop = _dropped(int(m), d)  # (K, d)
                kept = total[:, None, :] - members[:, drop, :].sum(axis=2)  # (n_g, K, 6)
                spread, stat = set_statistic(
                    kept,
                    Pj[g, 0, 0][:, None],
                    0.5 * (Pj[g, 0, 1] + Pj[g, 1, 0])[:, None],
                    Pj[g, 1, 1][:, None],
                )
                size = int(m) - d
                ok = (
                    np.ones(spread.shape, bool)
                    if size == 1
                    else spread <= consistency_gate(p_fa, 2 * (size - 1))
                )
                best = np.minimum(best, np.where(ok, stat, np.inf).min(axis=1))
            T[g] = np.where(np.isfinite(best), best, half_h[g])
    return T, judged


def witness_cusum(
    S: np.ndarray, T: np.ndarray, judged: np.ndarray, k: np.ndarray, h: np.ndarray
) -> np.ndarray:
    """``clip(S + min(T, h / 2) - k, 0, 2 h)`` (``T`` counted only where ``judged``),
    shapes (G,)."""
    step = np.where(judged, np.minimum(T, 0.5 * h), 0.0)
    return np.clip(S + step - k, 0.0, 2.0 * h)


def witness_state(memory: LinkMemory, receivers: np.ndarray, robots: np.ndarray) -> np.ndarray:
    """``S_{r,j}`` of receivers ``r`` on ``robots`` ``j`` (both (G,)) as it stands (0 for a
    pair never judged)."""
    return memory.stage_statistic(STATE).get(np.asarray(receivers), np.asarray(robots))


class WitnessCheck:
    """Receiver i discards every link from a neighbour j that the notes i received convict:
    ``S_{i,j} > h`` after the notes that arrived with this step's frames
    (``params.witness``)."""

    name: ClassVar[str] = "witness"
    compiled: ClassVar[bool] = True
    overrides: ClassVar[bool] = False

    def active(self, params: CLParams) -> bool:
        return bool(params.witness)

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        if memory is None:
            raise ValueError("detector witness (params.witness) needs a LinkMemory")
        j = np.asarray(evidence.j)
        return witness_state(memory, evidence.i, j) > at_robots(params.witness_h, j)
