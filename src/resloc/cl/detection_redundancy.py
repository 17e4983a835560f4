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
(:class:`FixContext`). The fixes and the capped claims are computed in
:mod:`resloc.cl.detection_redundancy_fixes`, the leave-one-out test and the exclusion in
:mod:`resloc.cl.detection_redundancy_exclusion`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from resloc.cl.detection_redundancy_exclusion import exclude_inconsistent
from resloc.cl.detection_redundancy_fixes import position_fix, weight_capped_covariance
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams, at_robots

if TYPE_CHECKING:
    from resloc.cl.detection import Evidence

__all__ = ["FixContext", "RedundancyCheck", "fix_evidence"]


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
