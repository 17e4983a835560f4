"""A robot's witness notes over the wire (``detector.witness``).

The notes a robot's correction of step ``t`` recorded (``RobotNode.witness_notes``: per
robot j it measured, ``u`` (2), ``Q`` (2x2), ``P_pos`` (2x2)) ride on its estimate frame of
step ``t + 1`` (the ESTIMATE's optional fields ``wj``, ``wn``; 8 + 80 bytes a note). The
estimate is broadcast every step whatever the trigger decides, so this is the simulator's
"one frame per robot and step", and the radio's routing of the estimate is the notes':
receiver r gets observer o's notes when r measured o this step and the channel draw
``channel_ok(r, o)`` let o's estimate through (jammed in the CDZ with it). At its correction
of step ``t + 1`` each robot hands the notes it got with this step's estimates to
``RobotNode.receive_witness`` (every step, even without a link to fuse), which updates its
statistic as the simulator's receiver and the correction's verdict reads it.

Notes are bad input like any frame from the network: the codec checks the fields' types,
shapes and finiteness; here the content is checked (ids of the team, distinct, not the
sender's own; ``Q`` and ``P_pos`` symmetric positive definite) and a sender's notes that
fail are dropped whole and counted (``witness_notes_malformed``), its estimate kept.
"""

from __future__ import annotations

import numpy as np

from resloc.runtime.messages import Kind, Message
from resloc.runtime.schema import encode_body

__all__ = ["WitnessingRobot", "notes_problem"]


def notes_problem(wj: np.ndarray, wn: np.ndarray, sender: int, robots: int) -> str | None:
    """Why the notes ``wj (K,)``, ``wn (K, 10)`` of ``sender`` cannot be judged, or None."""
    if len(wj) and (wj.min() < 0 or wj.max() >= robots):
        return "an id outside the team"
    if len(np.unique(wj)) != len(wj):
        return "two notes on one robot"
    if (wj == sender).any():
        return "a note on the sender itself"
    blocks = np.concatenate([wn[:, 2:6], wn[:, 6:10]]).reshape(-1, 2, 2)
    a, b, c, d = blocks[:, 0, 0], blocks[:, 0, 1], blocks[:, 1, 0], blocks[:, 1, 1]
    if (np.abs(b - c) > 1e-9 * (np.abs(a) + np.abs(d))).any():
        return "a covariance that is not symmetric"
    if ((a <= 0.0) | (a * d - b * c <= 0.0)).any():
        return "a covariance that is not positive definite"
    return None


class WitnessingRobot:
    """The witness side of :class:`~resloc.runtime.robot.RobotAgent` (its node, team and
    counters): notes sent on the estimate, taken from a neighbour's, delivered each step."""

    def notes_fields(self, body: dict) -> dict:
        """The estimate ``body`` with this robot's notes of the step before (counted)."""
        wj, wn = self.node.witness_notes()
        full = body | {"wj": wj, "wn": wn}
        self.counts["witness_notes_sent"] += len(wj)
        # the notes' share of the frame: the encoded body with them minus without them
        self.counts["witness_bytes_sent"] += len(encode_body(Kind.ESTIMATE, full)) - len(
            encode_body(Kind.ESTIMATE, body)
        )
        return full

    def take_notes(self, m: Message) -> None:
        """A neighbour's estimate with its notes: keep them for this step's delivery."""
        wj, wn = m.body["wj"], m.body["wn"]
        if notes_problem(wj, wn, m.sender, self.team.robots) is not None:
            self.counts["witness_notes_malformed"] += 1
            return
        self.notes_in[(m.sender, m.step)] = (wj, wn)

    def deliver_notes(self, measured: np.ndarray) -> None:
        """Before this step's correction: the notes that came with this step's estimates of
        the robots ``measured`` (its sensed links) go to the node's statistic."""
        senders = [int(s) for s in measured if (int(s), self.step) in self.notes_in]
        notes = [self.notes_in[(s, self.step)] for s in senders]
        self.counts["witness_frames_received"] += len(senders)
        self.counts["witness_notes_received"] += sum(len(j) for j, _ in notes)
        self.node.receive_witness(np.asarray(senders, np.int64), notes)
        for old in [key for key in self.notes_in if key[1] <= self.step]:
            del self.notes_in[old]
