"""A robot's end-of-step exchanges over the wire (step 3 of :mod:`resloc.runtime.robot`).

Gauge fusion acknowledges the robots it fused with their blocks ``L_i B_ij``; split CI names
them (ids only); factorized names the higher ids it fused, then sends each lower partner of
the step its pair message and closes its pairs with its higher partners' (a lost message:
the pair stays as this robot's updates left it, counted). The bodies are built and the
steps closed here; the waiting and sending are the agent's.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ExchangingRobot"]


class ExchangingRobot:
    """The end-of-step side of :class:`~resloc.runtime.robot.RobotAgent` (its node, team,
    the acknowledgements and pair messages it received, its counters)."""

    def ack_body(self) -> dict:
        """This step's ACK frame: gauge blocks ``L_i B_ij`` to the robots fused, or only their
        ids (split CI; factorized: the higher ids, which must hear of the pair)."""
        if not self.team.gauge:
            fused = self.node.delivery_acks()
            to = [j for j in fused if j > self.id] if self.team.factors else fused
            return {"to": np.asarray(to, dtype=np.int64)}
        acks = self.node.gauge_acks()
        to, ack = zip(*acks, strict=True) if acks else ((), ())
        return {
            "to": np.asarray(to, dtype=np.int64),
            "ack": np.asarray(ack, dtype=float).reshape(-1, 3, 3),
        }

    def close_acks(self) -> None:
        """Close the step with the acknowledgements received (a lost one: without it)."""
        if self.team.gauge:
            self.node.gauge_close([self.acks[s] for s in sorted(self.acks)])
        elif self.team.split:
            self.node.delivery_close(len(self.acks))

    def partners(self) -> list[int]:
        """Factorized: the step's partners, the robots this one fused or that named it."""
        return sorted(set(self.node.delivery_acks()) | set(self.acks))

    def pair_body(self) -> dict:
        """Factorized, round 1: this robot's pair message to each lower partner (the lower
        id keeps the pair's cross-covariance)."""
        lower = [p for p in self.partners() if p < self.id]
        pair = [self.node.factor_message(p) for p in lower]
        return {
            "to": np.asarray(lower, dtype=np.int64),
            "round": 1,
            "pair": np.asarray(pair, dtype=float).reshape(-1, 4, 3, 3),
        }

    def close_pairs(self) -> None:
        """Factorized: end the step's pairs with the higher partners' messages (a lower
        partner sends none; a lost message: the pair stays as this robot's updates left it,
        counted)."""
        higher = {p for p in self.partners() if p > self.id} | set(self.pair_messages)
        messages: dict[int, np.ndarray | None] = {p: None for p in self.partners() if p < self.id}
        for p in sorted(higher):
            if p in self.pair_messages:
                messages[p] = self.pair_messages[p]
            else:
                self.counts["pair_messages_missing"] += 1
        self.counts["pair_messages_received"] += len(self.pair_messages)
        self.node.factor_close(messages)
