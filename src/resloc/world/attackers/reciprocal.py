"""The two-ended attacker: both readings of a pair falsified together, against the
reciprocal range check (:mod:`resloc.cl.detection_reciprocal`).

The reciprocal check compares ``r_ij`` with ``r_ji``; a lie on one end shows in full. An
attacker that controls *both* ends of a pair (both robots' sensors inside a danger zone, or a
compromised robot that lies about its own readings while the sensors of the robots that see
it are falsified) moves both ranges by the same amount: their difference stays honest and the
check sees nothing. What the check still limits is the *difference* of the two lies, and this
attacker spends that too:

1. **Common part.** Every controlled link whose reverse link is also controlled gets the same
   range lie as its partner: the largest fraction of ``size`` that the whole detector of
   *both* victims accepts (the acceptance oracle, :func:`largest_accepted_along`, with every
   stage but the reciprocal check, which a common lie leaves at the honest difference), the
   pair's smaller one.
2. **Slack.** Then one end of each pair (the observer with the smaller batch index), and every
   controlled link whose partner reading is honest or absent, is pushed further along the
   lie by the largest extra the victim's detector accepts with the partner fixed: the
   reciprocal check's one-step gate and the room left in its sum (and every other stage's).
   The extra may be negative: a sum at its gate would be tripped by the next honest
   difference, and the attacker, which knows both honest readings, pulls it back instead
   of losing the pair to a hold. The other end of the pair is checked again with the final
   readings (it sees the same difference); an extra it would reject is halved until it
   passes.

Everything the victims use is known to it (parameters, predictions, innovation covariances,
every sequence test's state, the map). It is a range bias by design: ranges are what the
reciprocal check compares; bearings, which it does not compare, are the other attackers'
(``rotation``, ``translation``, ``displaced``).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from resloc.angles import wrap_angle
from resloc.cl.detection_zone import reciprocal_rows
from resloc.cl.params import at_robots
from resloc.world.attackers.base import SensingLie
from resloc.world.attackers.oracle import accepted, fix_context, largest_accepted_along
from resloc.world.attackers.sensing import MAX_RANGE_LIE

__all__ = ["TwoEnded"]

#: Halvings of a spent slack the pair's other end rejects.
HALVINGS = 8


class TwoEnded(SensingLie):
    name: ClassVar[str] = "two_ended"
    template: ClassVar[str] = (
        "both readings of a pair falsified together (target {target:g}; -1: every SDZ link, "
        "both ends in a zone where they are): the same +range lie on both ends, the largest "
        "both victims' detectors accept (up to {size:g} m), plus the reciprocal check's "
        "slack (its one-step gate and the room in its sum) spent on one end"
    )
    defaults: ClassVar[dict] = {"size": MAX_RANGE_LIE, "target": -1}
    grid: ClassVar[tuple] = ({"size": 0.5}, {"size": MAX_RANGE_LIE}, {"target": 5})

    def mark(self, sdz_attacked, step):
        if self.target < 0:
            return sdz_attacked
        rid_i, rid_j = step.i % step.robots, step.j % step.robots
        return (rid_i == self.target) | (rid_j == self.target)

    def lie(self, rows, z, z_hat, step):
        return np.broadcast_to([self.size, 0.0], (len(rows), 2)).copy()

    def attack(self, links, step, params, memory):
        def tamper(rows: np.ndarray, z_hat: np.ndarray, S: np.ndarray) -> np.ndarray:
            out = links.z[rows].copy()
            hit = np.flatnonzero(step.attacked[rows])
            if not hit.size:
                return out
            r = rows[hit]
            sent = self._both_ends(links, r, out[hit], z_hat[hit], S[hit], params, memory, step)
            sent[:, 0] = np.abs(sent[:, 0])
            sent[:, 1] = wrap_angle(sent[:, 1])
            out[hit] = sent
            return out

        return dataclasses.replace(links, tamper=tamper)

    def _both_ends(self, links, r, z, z_hat, S, params, memory, step) -> np.ndarray:
        """The readings sent on the controlled rows ``r`` (indices into ``links``), shape
        (n, 2): the common part, then the slack."""
        n = len(r)
        lie = self.lie(r, z, z_hat, step)
        i, j = links.i[r], links.j[r]
        reverse = reciprocal_rows(links.i, links.j)[r]
        where = np.full(len(links), -1)
        where[r] = np.arange(n)
        partner = np.where(reverse >= 0, where[np.maximum(reverse, 0)], -1)  # in r, or -1
        paired = partner >= 0
        base = np.asarray(links.z, float).copy()

        def judge_all(sent: np.ndarray) -> np.ndarray:
            full = base.copy()
            full[r] = sent
            context = fix_context(links, r, params, memory=memory, z=full)
            return accepted(sent, z_hat, S, i, j, params, memory, context=context)

        # 1. The common part: both ends of a pair move together, so their difference stays
        #    honest; its size is what the victims' other stages accept (the reciprocal
        #    check's room is the slack's, step 2: with its sum at the gate the honest
        #    difference alone may fail it, and only the slack can pull it back).
        others = dataclasses.replace(params, reciprocal=False)
        a = largest_accepted_along(
            lambda frac: z[None] + frac[..., None] * lie[None],
            z_hat,
            S,
            i,
            j,
            others,
            memory,
            context=fix_context(links, r, others, memory=memory),
        )
        alone = reverse < 0  # no partner reading: the reciprocal check cannot judge it
        a = np.where(paired, np.minimum(a, a[np.maximum(partner, 0)]), np.where(alone, a, 0.0))
        sent = z + a[:, None] * lie
        # 2. The slack: one end of each pair (the smaller observer) and every lone row is
        #    moved by an extra in [-size, size] along the lie, the largest the victim's
        #    whole detector accepts with the partner fixed (a negative extra where the sum
        #    is at its gate and the honest difference would trip it).
        spend = ~alone & (~paired | (i < np.where(paired, i[np.maximum(partner, 0)], i)))
        rows = np.flatnonzero(spend)
        if not rows.size:
            return sent
        full = base.copy()
        full[r] = sent
        start = sent[rows]
        # The search spans the one-step gate's width on both sides of the honest
        # difference, so its first grid already lands in the accepted interval.
        difference = start[:, 0] - full[reverse[rows], 0]
        gate = at_robots(params.reciprocal_gate, i[rows])
        reach = np.abs(difference) + 2.0 * np.sqrt(gate * 2.0 * params.range_std**2)
        unit = lie[rows] / np.maximum(np.abs(lie[rows, 0]), 1e-12)[:, None]
        extra = unit * reach[:, None]
        frac = largest_accepted_along(
            lambda f: start[None] + (2.0 * f[..., None] - 1.0) * extra[None],
            z_hat[rows],
            S[rows],
            i[rows],
            j[rows],
            params,
            memory,
            context=fix_context(links, r[rows], params, memory=memory, z=full),
        )
        # nothing accepted (frac 0): send the common part alone
        e = np.where(frac > 0.0, 2.0 * frac - 1.0, 0.0)
        for _ in range(HALVINGS):
            trial = sent.copy()
            trial[rows] = start + e[:, None] * extra
            ok = judge_all(trial)
            # a spent slack the pair's other end (or the spender itself, judged with
            # everything told together) rejects is halved
            bad_rows = ~ok[rows] | (paired[rows] & ~ok[np.maximum(partner[rows], 0)])
            bad_rows &= e != 0.0
            if not bad_rows.any():
                return trial
            e = np.where(bad_rows, 0.5 * e, e)
            e = np.where(bad_rows & (np.abs(e) < 1e-6), 0.0, e)
        trial = sent.copy()
        trial[rows] = start + e[:, None] * extra
        return trial
