"""A robot's side of the pull protocol (``estimator.neighbour_estimate = "cached"``).

:class:`PullingRobot` is the part of :class:`~resloc.runtime.robot.RobotAgent` that asks its
neighbours for their estimates when its trigger fires, answers their requests with its
predicted estimate, and closes the step with what arrived; the correction itself is
:func:`~resloc.runtime.pull.pull_correction` (``docs/runtime.md``, "Estimates on the wire").
"""

from __future__ import annotations

import collections

import numpy as np

from resloc.runtime.messages import FLAG_DELIVERED, FLAG_HEARD, Kind, Message
from resloc.runtime.pull import PullOutcome, pull_correction
from resloc.runtime.schema import link_flags

__all__ = ["PullingRobot"]


class PullingRobot:
    """Pulled estimates, mixed into :class:`~resloc.runtime.robot.RobotAgent` (which owns
    the node, the bus, the counters, the phases and the report)."""

    def start_pull(self, x: np.ndarray, P: np.ndarray) -> None:
        """Cached neighbour estimates: remember the predicted estimate (the reply to any
        request of this step), answer the requests that waited for it, start the pulled
        correction (:func:`~resloc.runtime.pull.pull_correction`)."""
        self.snapshots[self.step] = (x, P)
        for old in [k for k in self.snapshots if k < self.step - self.options.max_age_steps]:
            del self.snapshots[old]
        waiting, self.deferred = self.deferred, []
        self.answer(waiting)
        s = self.sensors
        self.pulling = pull_correction(
            self.node,
            s["j"].astype(np.int64),
            s["z"],
            (*self.step_risks(), s["l2"]),
            self.team.link_params(s["z"]),
            single_round=self.realtime,
        )
        self.pull_round = -1
        self.pull_next(None)

    def pull_next(self, replies: dict | None) -> None:
        """Feed a round's replies to the correction; send its next requests, or close."""
        try:
            ask = next(self.pulling) if replies is None else self.pulling.send(replies)
        except StopIteration as stop:
            self.pulling = None
            self.pull_close(stop.value)
            return
        self.pull_round += 1
        self.asked, self.replies = ask, {}
        self.counts["requests_sent"] += len(ask)
        self.send(Kind.REQUEST, {"round": self.pull_round, "to": np.asarray(ask, np.int64)})
        self.wait(Kind.REPLY, self.pull_round)

    def pull_abandon(self) -> None:
        """Realtime overrun: close the correction without the replies still awaited."""
        while self.pulling is not None:
            try:
                self.unsent += len(self.pulling.send({}))
            except StopIteration as stop:
                self.pulling = None
                self.pull_close(stop.value, report=False)

    def pull_close(self, result: PullOutcome, report: bool = True) -> None:
        j = self.sensors["j"].astype(np.int64)
        flags = np.zeros(len(j), dtype=np.uint8)
        norm = np.full(len(j), np.nan)
        repairs = 0
        for rows, out in result.outcomes:
            flags[rows] |= FLAG_HEARD | link_flags(out)
            norm[rows] = out.norm
            repairs += int(out.repairs)
        lost = int((result.requested & ~result.answered).sum()) - self.unsent
        self.counts["requests_unanswered" if self.realtime else "unheard"] += lost
        self.counts["links_fired_after_the_round"] += result.not_asked
        self.counts["links_skipped_overrun"] += self.unsent
        self.unsent = 0
        self.counts["pull_rounds"] += result.rounds
        # a reply for a link never heard from before, which the detector then discarded
        self.counts["replies_unused"] += int(
            (result.answered & (flags & FLAG_DELIVERED == 0)).sum()
        )
        self.outcome = (j, flags, norm, repairs)
        if not self.realtime:  # lockstep: tell the radio this robot asks for nothing more
            self.send(Kind.REQUEST, {"round": self.pull_round + 1, "to": np.zeros(0, np.int64)})
        if report:
            self.phase = None
            self.finish_step()

    def cache_late_reply(self, m: Message) -> None:
        """A late reply from a neighbour never heard from becomes its cached estimate (the
        last estimate of j that i received), so the next steps decide that link locally
        instead of asking again every step; it is never fused, and a known link's newer
        cache is never replaced by it."""
        if self.node is None or not self.team.pull or m.step > self.step:
            return
        if m.step < self.step - self.options.max_age_steps:
            return
        zero, j = np.zeros(1, np.int64), np.array([m.sender], np.int64)
        known, _ = self.node.memory.lookup(zero, j)
        if not known[0]:
            self.node.memory.store(zero, j, m.body["x"][None], m.body["P"][None], np.zeros(1))
            self.counts["late_replies_cached"] += 1

    def answer(self, requests: list[Message]) -> None:
        """Reply to requests with this robot's predicted estimate of their step: one REPLY
        per (step, round) to all its requesters; a request for a step this robot has not
        reached yet waits for it; one for a step it no longer keeps is dropped."""
        groups: dict[tuple[int, int], list[int]] = collections.defaultdict(list)
        for m in requests:
            if m.step in self.snapshots:
                groups[(m.step, int(m.body["round"]))].append(m.sender)
            elif m.step > self.step:
                self.deferred.append(m)
            else:
                self.counts["requests_too_old"] += 1
        for (k, rnd), who in sorted(groups.items()):
            x, P = self.snapshots[k]
            body = {"round": rnd, "to": np.asarray(sorted(set(who)), np.int64), "x": x, "P": P}
            self.bus.send(self.bus.key("radio", "in"), Kind.REPLY, k, body, sender=self.id)
            self.counts["replies_sent"] += 1
