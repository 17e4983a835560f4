"""Redundancy: a neighbour whose position fix disagrees with the robot's other neighbours.

A robot usually has several neighbours, and each link gives an independent *fix* of the
robot's own position: neighbour j's broadcast position minus the relative position robot i
measured,

``f_ij = p_j - r_ij u(theta_i + b_ij)``,  ``u(a) = [cos a, sin a]``,

with covariance (first order in j's position, i's heading and the sensor noise)

``C_ij = P'_j,pos + J_theta P_i,thetatheta J_theta^T + J_z R J_z^T``.

A lie on one link, whether it arrives through the sensor (``z_ij`` falsified) or through
the radio (a compromised j broadcasting a false ``p_j``), moves that link's fix and no
other. This stage compares every fix with the information-weighted mean of the robot's
*other* fixes of the same step (leave-one-out; the robot's own prediction is left out, so a
robot already pulled off by a lie does not carry the lie into its reference):

``m_-j = (sum_{k != j} C_k^-1)^-1 sum_{k != j} C_k^-1 f_k``,
``d_j = f_j - m_-j``,  ``T_j = d_j^T (C_j + (sum_{k != j} C_k^-1)^-1)^-1 d_j``

and discards the link when ``T_j`` exceeds the chi-square gate (2 degrees of freedom,
``redundancy_gate``) and the robot has at least ``redundancy_min_peers`` other fixes (with
fewer there is no majority to side with; the other stages judge those links alone).

Claimed covariances are not taken at their word (a compromised robot claims a tiny one to
dominate both its victims' updates and the reference): in the test, each neighbour's claimed
position covariance ``P_j,pos`` is scaled up to at least the median trace of the claimed
position covariances of the robot's neighbours this step (``P'_j``), so no neighbour gets more
weight in the reference than a typical one. The common errors of the fixes (the team's
rigid-body error, in every ``p_j`` alike) cancel in ``d_j``; ``C_j`` keeps them, which makes
the test conservative, not blind.

What it assumes, and where it fails (``docs/attack/redundancy.md``): honest neighbours are
the majority *by this weight* among a robot's fixes; lies that move several fixes of one
robot consistently (a displaced robot: all its own readings are falsified consistently with
one false position, and every reading of it too) are not inconsistent with each other, and
a robot with fewer than ``redundancy_min_peers + 1`` fixes in a step is not protected by
this stage.

The correction computes the fixes and their references once per step, at the predicted
estimates, over all of a robot's links (:func:`fix_evidence`), so the verdict is the same in
the sequential and the summed update and in one robot's process; the stage itself judges
each row from the :class:`~resloc.cl.detection.Evidence` fields that carry them. An attacker's
copy of the detector supplies the same fields for its candidates
(:class:`FixContext`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams, at_robots

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = [
    "FixContext",
    "RedundancyCheck",
    "capped_claims",
    "exclude_inconsistent",
    "fix_evidence",
    "leave_one_out",
    "position_fix",
    "redundancy_statistic",
    "weight_capped_covariance",
]

#: A reference with no peer (never used: such rows are not judged) gets this covariance (m^2).
_NO_PEER_COV = 1e12


def weight_capped_covariance(P_nb: np.ndarray, i: np.ndarray) -> np.ndarray:
    """Neighbours' claimed position covariances, each scaled up to at least the median trace
    among the same observer's neighbours (no neighbour weighs more than a typical one).

    Parameters
    ----------
    P_nb : ndarray, shape (E, 3, 3)
        Claimed covariances of the neighbours' estimates.
    i : ndarray of int, shape (E,)
        Observer of each row.

    Returns
    -------
    ndarray, shape (E, 2, 2)
    """
    P = np.asarray(P_nb, float)[:, :2, :2]
    trace = P[:, 0, 0] + P[:, 1, 1]
    median = _group_median(trace, np.asarray(i))
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(trace > 0.0, np.maximum(median / trace, 1.0), 1.0)
    return P * scale[:, None, None]


def capped_claims(P_nb: np.ndarray, i: np.ndarray) -> np.ndarray:
    """The neighbours' claimed covariances ``(E, 3, 3)``, each scaled by the factor
    :func:`weight_capped_covariance` puts on its position block: what a robot fuses when
    ``redundancy_cap_fusion`` is on, so a neighbour weighs in the update no more than the
    redundancy test credited it (shape (E, 3, 3))."""
    P = np.asarray(P_nb, float)
    trace = P[:, 0, 0] + P[:, 1, 1]
    median = _group_median(trace, np.asarray(i))
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(trace > 0.0, np.maximum(median / trace, 1.0), 1.0)
    return P * scale[:, None, None]


def _group_median(values: np.ndarray, group: np.ndarray) -> np.ndarray:
    """The median of ``values: (E,)`` over the rows of each row's ``group``, shape (E,)."""
    if not len(values):
        return values.copy()
    order = np.lexsort((values, group))
    sorted_group = group[order]
    start = np.flatnonzero(np.r_[True, sorted_group[1:] != sorted_group[:-1]])
    count = np.diff(np.r_[start, len(values)])
    ranked = values[order]
    median = 0.5 * (ranked[start + (count - 1) // 2] + ranked[start + count // 2])
    per_row = np.empty(len(values))
    per_row[order] = np.repeat(median, count)
    return per_row


def position_fix(
    z: np.ndarray,
    x_obs: np.ndarray,
    P_obs: np.ndarray,
    x_nb: np.ndarray,
    P_nb_pos: np.ndarray,
    R: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Observer i's position as link ``(i, j)`` says: ``f = p_j - r u(theta_i + b)``
    (``r`` corrected for the mean shortening the angle's noise causes).

    Parameters
    ----------
    z : ndarray, shape (E, 2)
        Range and bearing of j measured by i.
    x_obs, P_obs : ndarray, shapes (E, 3), (E, 3, 3)
        Observer's estimate (its heading and heading variance are used).
    x_nb : ndarray, shape (E, 3)
        Neighbour's broadcast estimate.
    P_nb_pos : ndarray, shape (E, 2, 2)
        Position covariance credited to the neighbour.
    R : ndarray, shape (2, 2)

    Returns
    -------
    fix : ndarray, shape (E, 2)
    C : ndarray, shape (E, 2, 2)
    """
    r = z[:, 0]
    a = x_obs[:, 2] + z[:, 1]
    c, s = np.cos(a), np.sin(a)
    # A direction read with a zero-mean Gaussian angle error of variance s2 (the bearing
    # noise and the heading's variance) is shortened on average by exp(-s2 / 2): undone,
    # so that honest fixes are unbiased (a sequence test summing residuals over hundreds
    # of steps would otherwise see that bias as a lead).
    r_mean = r * np.exp(0.5 * (R[1, 1] + P_obs[:, 2, 2]))
    fix = x_nb[:, :2] - r_mean[:, None] * np.stack([c, s], axis=1)
    # d fix / d theta_i = d fix / d b = r [sin a, -cos a]; d fix / d r = -[cos a, sin a],
    # taken at the predicted geometry (the estimates' relative position), not at the
    # reading: weights that moved with the reading's own noise would bias the references
    # the fixes are compared with.
    rel = x_nb[:, :2] - x_obs[:, :2]
    r_pred = np.hypot(rel[:, 0], rel[:, 1])
    use = r_pred > 0.0
    c = np.where(use, rel[:, 0] / np.where(use, r_pred, 1.0), c)
    s = np.where(use, rel[:, 1] / np.where(use, r_pred, 1.0), s)
    r = np.where(use, r_pred, r)
    J_a = r[:, None] * np.stack([s, -c], axis=1)
    J_z = np.stack([np.stack([-c, J_a[:, 0]], 1), np.stack([-s, J_a[:, 1]], 1)], 1)
    C = (
        P_nb_pos
        + J_a[:, :, None] * J_a[:, None, :] * P_obs[:, 2, 2][:, None, None]
        + J_z @ R @ np.swapaxes(J_z, -1, -2)
    )
    return fix, 0.5 * (C + np.swapaxes(C, -1, -2))


def _sym2(M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The entries ``(a, b, c)`` of symmetric 2 x 2 matrices ``[[a, b], [b, c]]``."""
    return M[:, 0, 0], 0.5 * (M[:, 0, 1] + M[:, 1, 0]), M[:, 1, 1]


def _information(
    a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``[[a, b], [b, c]]^-1`` in closed form (2 x 2 SPD: ``det > 0``), as ``(a, b, c)``."""
    det = a * c - b * b
    return c / det, -b / det, a / det


def _group_sums(inverse: np.ndarray, n: int, *values: np.ndarray) -> list[np.ndarray]:
    return [np.bincount(inverse, weights=v, minlength=n) for v in values]


def _reference(
    fix: np.ndarray, C3: tuple, inverse: np.ndarray, n: int, included: np.ndarray
) -> tuple[np.ndarray, tuple, np.ndarray]:
    """Leave-one-out reference of every row over the included rows of its group (entries
    form); see :func:`leave_one_out`."""
    w = included.astype(float)
    Ya, Yb, Yc = (v * w for v in _information(*C3))
    ya = Ya * fix[:, 0] + Yb * fix[:, 1]
    yb = Yb * fix[:, 0] + Yc * fix[:, 1]
    Sa, Sb, Sc, sa, sb, count = _group_sums(inverse, n, Ya, Yb, Yc, ya, yb, w)
    Ra, Rb, Rc = Sa[inverse] - Ya, Sb[inverse] - Yb, Sc[inverse] - Yc
    ra, rb = sa[inverse] - ya, sb[inverse] - yb
    peers = np.rint(count[inverse] - w).astype(int)
    has = peers > 0
    det = np.where(has, Ra * Rc - Rb * Rb, 1.0)
    Qa = np.where(has, Rc / det, _NO_PEER_COV)
    Qb = np.where(has, -Rb / det, 0.0)
    Qc = np.where(has, Ra / det, _NO_PEER_COV)
    reference = np.where(
        has[:, None], np.stack([Qa * ra + Qb * rb, Qb * ra + Qc * rb], axis=1), fix
    )
    return reference, (Qa, Qb, Qc), peers


def _statistic(fix: np.ndarray, C3: tuple, reference: np.ndarray, Q3: tuple) -> np.ndarray:
    """``d^T (C + Q)^-1 d`` in closed form, shape (E,)."""
    a, b, c = (x + y for x, y in zip(C3, Q3, strict=True))
    d0, d1 = fix[:, 0] - reference[:, 0], fix[:, 1] - reference[:, 1]
    return (c * d0 * d0 - 2.0 * b * d0 * d1 + a * d1 * d1) / (a * c - b * b)


def _matrix(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.stack([np.stack([a, b], -1), np.stack([b, c], -1)], -2)


def leave_one_out(
    fix: np.ndarray, C: np.ndarray, i: np.ndarray, included: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Information-weighted mean of each row's observer's *other* included fixes.

    Parameters
    ----------
    fix : ndarray, shape (E, 2)
    C : ndarray, shape (E, 2, 2)
    i : ndarray of int, shape (E,)
    included : ndarray of bool, shape (E,), optional
        The fixes a reference may use (default: all).

    Returns
    -------
    reference : ndarray, shape (E, 2)
        ``m_-j`` (the row's own fix where it has no peer).
    reference_cov : ndarray, shape (E, 2, 2)
        ``(sum_{k != j} C_k^-1)^-1`` (a huge diagonal where it has no peer).
    peers : ndarray of int, shape (E,)
        Number of other included fixes of the same observer.

    Notes
    -----
    Everything is 2 x 2 and symmetric: the information sums and the solves are written in
    closed form on the entries (the attacker's oracle evaluates this on tens of thousands of
    rows per step).
    """
    E = len(fix)
    included = np.ones(E, bool) if included is None else np.asarray(included, bool)
    robots, inverse = np.unique(i, return_inverse=True)
    reference, Q3, peers = _reference(fix, _sym2(C), inverse, len(robots), included)
    return reference, _matrix(*Q3), peers


def redundancy_statistic(
    fix: np.ndarray, C: np.ndarray, reference: np.ndarray, reference_cov: np.ndarray
) -> np.ndarray:
    """``T = d^T (C + C_ref)^-1 d`` with ``d = fix - reference``, shape (E,)."""
    return _statistic(fix, _sym2(C), reference, _sym2(reference_cov))


def exclude_inconsistent(
    fix: np.ndarray,
    C: np.ndarray,
    i: np.ndarray,
    gate: float | np.ndarray,
    min_peers: float | np.ndarray,
    excluded: np.ndarray | None = None,
    residuals: bool = False,
) -> tuple[np.ndarray, ...]:
    """Fault exclusion over each observer's fixes, one at a time.

    Every round, each observer's included fixes are tested against the mean of its other
    included fixes; the one with the largest statistic above ``gate`` is excluded, if at
    least ``min_peers`` included fixes remain to have judged it. Rounds go on until no
    observer excludes any more. (Testing all rows once would not do: a gross lie pulls every
    honest row's reference by its share and they would all fail with it.)

    Parameters
    ----------
    fix : ndarray, shape (E, 2)
    C : ndarray, shape (E, 2, 2)
    i : ndarray of int, shape (E,)
        Observer of each row.
    gate, min_peers : float or ndarray, shape (E,)
    excluded : ndarray of bool, shape (E,), optional
        Rows excluded before the first round (they never enter a reference; e.g. links a
        sequence test holds out).
    residuals : bool
        Also return each row's residual against its reference and the residual's
        covariance.

    Returns
    -------
    excluded : ndarray of bool, shape (E,)
    statistic : ndarray, shape (E,)
        Each row's statistic against the observer's included fixes at the end (``nan``:
        fewer than ``min_peers`` of them, not judged).
    residual : ndarray, shape (E, 2)
        With ``residuals``: ``d = fix - m_-j`` at the end (``nan`` where not judged).
    residual_cov : ndarray, shape (E, 2, 2)
        With ``residuals``: ``C_j + (sum_{k != j} C_k^-1)^-1``.
    """
    E = len(fix)
    gate = np.broadcast_to(np.asarray(gate, float), (E,))
    min_peers = np.broadcast_to(np.asarray(min_peers, float), (E,))
    included = np.ones(E, bool) if excluded is None else ~np.asarray(excluded, bool)
    if E == 0:
        empty = (np.zeros((0, 2)), np.zeros((0, 2, 2))) if residuals else ()
        return ~included, np.zeros(0), *empty
    robots, inverse = np.unique(i, return_inverse=True)
    n = len(robots)
    C3 = _sym2(C)
    while True:
        reference, Q3, peers = _reference(fix, C3, inverse, n, included)
        stat = _statistic(fix, C3, reference, Q3)
        # An included row's peers stay to judge it once it is out.
        candidate = included & (peers >= min_peers) & (stat > gate)
        if not candidate.any():
            break
        rows = np.flatnonzero(candidate)
        # The worst candidate of each observer.
        order = rows[np.lexsort((-stat[rows], inverse[rows]))]
        first = np.r_[True, inverse[order][1:] != inverse[order][:-1]]
        included[order[first]] = False
    judged = peers >= min_peers
    if not residuals:
        return ~included, np.where(judged, stat, np.nan)
    residual = np.where(judged[:, None], fix - reference, np.nan)
    residual_cov = _matrix(*(x + y for x, y in zip(C3, Q3, strict=True)))
    return ~included, np.where(judged, stat, np.nan), residual, residual_cov


def fix_evidence(
    z: np.ndarray,
    x_obs: np.ndarray,
    P_obs: np.ndarray,
    x_nb: np.ndarray,
    P_nb: np.ndarray,
    i: np.ndarray,
    params: CLParams,
    j: np.ndarray | None = None,
    memory: LinkMemory | None = None,
) -> dict[str, np.ndarray]:
    """The :class:`~resloc.cl.detection.Evidence` fields of this stage for a whole step.

    Rows are every link of the step (a robot's rows all present); shapes as
    :func:`position_fix`, ``P_nb: (E, 3, 3)`` the claimed covariances, ``i: (E,)`` the
    observers (batch indices: the per-robot gate and ``min_peers`` are read at them).
    ``j: (E,)`` and the observers' ``memory``: links a sequence test holds out
    (:func:`resloc.cl.detection_sequence.held_out`) enter no reference.

    Returns
    -------
    dict
        ``fix_excluded (E,)``: the rows :func:`exclude_inconsistent` excludes;
        ``fix_statistic (E,)``: their final statistics; ``fix_residual (E, 2)``,
        ``fix_residual_cov (E, 2, 2)``: each row's residual against its reference and
        the residual's covariance (what the sequence test accumulates).
    """
    from resloc.cl.detection_sequence import held_out

    fix, C = position_fix(z, x_obs, P_obs, x_nb, weight_capped_covariance(P_nb, i), params.R)
    excluded, stat, residual, residual_cov = exclude_inconsistent(
        fix,
        C,
        i,
        at_robots(params.redundancy_gate, i),
        at_robots(params.redundancy_min_peers, i),
        excluded=held_out(params, memory, i, j),
        residuals=True,
    )
    out = {
        "fix_excluded": excluded,
        "fix_statistic": stat,
        "fix_residual": residual,
        "fix_residual_cov": residual_cov,
    }
    if params.redundancy_sequence and j is not None:
        from resloc.cl.detection_sequence import sequence_evidence

        out.update(sequence_evidence(residual, residual_cov, i, j, params, memory))
    return out


@dataclass
class FixContext:
    """What an attacker's copy of the detector needs to judge candidates on some rows of a
    step: every link of the victims that step, as the victim will see it.

    Attributes
    ----------
    z : ndarray, shape (E, 2)
        The readings of every link (the candidates' rows at their honest value).
    x_obs, P_obs, x_nb, P_nb : ndarray
        The victims' predicted estimates and the neighbours' broadcast (claimed) ones,
        shapes (E, 3), (E, 3, 3), (E, 3), (E, 3, 3).
    i : ndarray of int, shape (E,)
    params : CLParams
        The victim's.
    rows : ndarray of int, shape (n,)
        The rows the candidates are for.
    j : ndarray of int, shape (E,), optional
        The neighbours (with ``memory``: the links a sequence test holds out enter no
        reference, as in the victim's step).
    memory : LinkMemory, optional
        The victims' memory (read only).
    """

    z: np.ndarray
    x_obs: np.ndarray
    P_obs: np.ndarray
    x_nb: np.ndarray
    P_nb: np.ndarray
    i: np.ndarray
    params: CLParams
    rows: np.ndarray
    j: np.ndarray | None = None
    memory: LinkMemory | None = None

    def fields(self, candidates: np.ndarray) -> dict[str, np.ndarray]:
        """Evidence fields for ``candidates``, shape (G, n, 2), flattened to (G n, ...).

        Each of the ``G`` candidate sets replaces the candidates' rows in its own copy of
        the victims' links (the other rows at their values in :attr:`z`), and each copy is
        judged as the victims will judge the step: several lied-on rows of one victim
        together, the exclusion run over all of the victim's rows.
        """
        n = len(self.rows)
        candidates = np.asarray(candidates, float).reshape(-1, n, 2)
        G = len(candidates)
        victims = np.flatnonzero(np.isin(self.i, self.i[self.rows]))
        V = len(victims)
        where = np.searchsorted(victims, self.rows)  # the candidates' rows in the copy
        width = int(self.i.max()) + 1
        copy = np.repeat(np.arange(G), V)
        i = np.tile(self.i[victims], G)
        # Each copy's observers are distinct robots (ids offset); per-robot gains gathered
        # at the original ids.
        params = self.params
        gate = np.tile(at_robots(params.redundancy_gate, self.i[victims]) * np.ones(V), G)
        peers = np.tile(at_robots(params.redundancy_min_peers, self.i[victims]) * np.ones(V), G)
        group = i + copy * width
        # The other rows' fixes are the same in every copy: computed once, then the
        # candidates' fixes put in their places.
        x_obs, P_obs, x_nb = self.x_obs[victims], self.P_obs[victims], self.x_nb[victims]
        capped = weight_capped_covariance(self.P_nb[victims], self.i[victims])
        base_fix, base_C = position_fix(self.z[victims], x_obs, P_obs, x_nb, capped, params.R)
        cand_fix, cand_C = position_fix(
            candidates.reshape(-1, 2),
            np.tile(x_obs[where], (G, 1)),
            np.tile(P_obs[where], (G, 1, 1)),
            np.tile(x_nb[where], (G, 1)),
            np.tile(capped[where], (G, 1, 1)),
            params.R,
        )
        fix = np.tile(base_fix, (G, 1, 1))
        C = np.tile(base_C, (G, 1, 1, 1))
        fix[:, where] = cand_fix.reshape(G, n, 2)
        C[:, where] = cand_C.reshape(G, n, 2, 2)
        fix, C = fix.reshape(-1, 2), C.reshape(-1, 2, 2)
        held = None
        if self.j is not None:
            from resloc.cl.detection_sequence import held_out

            held = held_out(params, self.memory, self.i[victims], self.j[victims])
            held = None if held is None else np.tile(held, G)
        excluded, stat, residual, residual_cov = exclude_inconsistent(
            fix, C, group, gate, peers, excluded=held, residuals=True
        )
        pick = (np.arange(G)[:, None] * V + where[None]).ravel()
        out = {
            "fix_excluded": excluded[pick],
            "fix_statistic": stat[pick],
            "fix_residual": residual[pick],
            "fix_residual_cov": residual_cov[pick],
        }
        if params.redundancy_sequence and self.j is not None:
            from resloc.cl.detection_sequence import sequence_evidence

            seq = sequence_evidence(
                residual,
                residual_cov,
                i,
                np.tile(self.j[victims], G),
                params,
                self.memory,
                group=group,
            )
            out.update({k: v[pick] for k, v in seq.items()})
        return out


class RedundancyCheck:
    """Discard a link whose position fix disagrees with the robot's other fixes this step."""

    name: ClassVar[str] = "redundancy"
    compiled: ClassVar[bool] = True  # resloc.cl.kernels_redundancy_verdicts.fix_verdicts
    overrides: ClassVar[bool] = False

    def problem(self, options) -> str | None:
        """Why the scenario's ``[detector]`` ``options`` cannot run as set (names the fix)."""
        if getattr(options, "redundancy_cap_fusion", False) and not options.redundancy:
            return (
                "redundancy_cap_fusion: true caps claimed covariances as the redundancy "
                "stage does; set detector.redundancy = true or redundancy_cap_fusion = false"
            )
        return None

    def active(self, params: CLParams) -> bool:
        return bool(params.redundancy)

    def discard(
        self, evidence: Evidence, params: CLParams, memory: LinkMemory | None
    ) -> np.ndarray:
        if evidence.fix_excluded is None:
            raise ValueError(
                "detector redundancy (params.redundancy) needs the step's position fixes "
                "(Evidence.fix_excluded: resloc.cl.detection_redundancy.fix_evidence)"
            )
        out = evidence.fix_excluded.copy()
        if evidence.zone_substituted is not None:
            # A row zone trust substituted is fused as the partner's position fix, not as
            # the (distrusted) reading the fix above was computed from.
            out &= ~evidence.zone_substituted
        return out
