"""The radio process: the paper's communication model applied to every robot-to-robot message.

Robots never address each other directly: each publishes its ESTIMATE, ACK and CONSENSUS
frames to the radio (``radio/in``), which decides per receiver whether the frame gets through
and forwards the original, still authenticated frame inside a DELIVERY. The decision uses the
step's channel draws that the world made (``CHANNEL``: the simulator's ``channel_ok`` of every
sensed link, which is range-limited and jammed in a CDZ at the zone's rate), so the wire and
the in-process simulator see the same channel:

* ESTIMATE from j reaches each robot i that sensed j this step if ``channel_ok(i, j)``;
* ACK from i to j (gauge fusion, split CI, factorized fusion's ids and pair messages)
  reaches j always, as in the simulator (default), or, with
  ``jam_acks``, only if ``channel_ok(j, i)`` (the link on which j is the receiver);
* CONSENSUS from c reaches every communication neighbour a of c: ``channel_ok(a, c)`` or
  ``channel_ok(c, a)`` (the simulator's undirected communication graph). The radio also tells
  each robot its communication neighbours (a link-layer neighbour table), which Metropolis
  consensus weights need.

Lockstep: the radio waits until every fed, alive robot has sent its frame of a phase, then
delivers the phase (one DELIVERY per robot, frames sorted by sender). Realtime: it forwards
each frame as soon as the step's channel is known, the frames queued together in one DELIVERY
per receiver. Per step it reports messages, bytes,
delivered copies and lost copies per sender and kind to the recorder (``STATS``).
"""

from __future__ import annotations

import collections
import time

import numpy as np

from resloc.runtime.messages import RADIO, ROBOT_TO_ROBOT, Kind, Message
from resloc.runtime.options import Mode, SwarmOptions
from resloc.runtime.process import EXIT_LOST, EXIT_OK, connect_bus
from resloc.runtime.team import team_setup
from resloc.runtime.transport import Bus

__all__ = ["StepChannel", "run_radio"]

#: Phase number of the realtime neighbour-table delivery.
NEIGHBOURS_PHASE = 0
#: Phase number of a realtime delivery of forwarded frames (of any kind and step).
FORWARDED_PHASE = 255


class StepChannel:
    """One step's links and channel outcomes, and the routing rules on them."""

    def __init__(self, i: np.ndarray, j: np.ndarray, ok: np.ndarray, fed: np.ndarray) -> None:
        self.fed = {int(b) for b in fed}
        self.ok = {(int(a), int(c)): bool(v) for a, c, v in zip(i, j, ok, strict=True)}
        self.observers: dict[int, list[int]] = collections.defaultdict(list)
        nb: dict[int, set[int]] = collections.defaultdict(set)
        for (a, c), good in self.ok.items():
            self.observers[c].append(a)
            if good and a != c and a in self.fed and c in self.fed:
                nb[a].add(c)
                nb[c].add(a)
        self.neighbours = {b: sorted(nb[b]) for b in self.fed}

    def route(self, msg: Message, jam_acks: bool) -> tuple[list[int], int]:
        """Receivers of ``msg`` and the number of copies the channel lost."""
        s = msg.sender
        if msg.kind is Kind.ESTIMATE:
            want = [a for a in self.observers.get(s, ()) if a in self.fed]
            got = [a for a in want if self.ok[(a, s)]]
        elif msg.kind is Kind.ACK:
            want = sorted({int(d) for d in msg.body["to"]} & self.fed)
            got = [d for d in want if self.ok.get((d, s), False)] if jam_acks else want
        elif msg.kind is Kind.REQUEST:  # i asks j on the link (i, j): that link's draw
            want = sorted({int(d) for d in msg.body["to"]} & self.fed)
            got = [d for d in want if self.ok.get((s, d), False)]
        elif msg.kind is Kind.REPLY:  # j answers i on the same link, with the same draw
            want = sorted({int(d) for d in msg.body["to"]} & self.fed)
            got = [d for d in want if self.ok.get((d, s), False)]
        else:
            want = got = list(self.neighbours.get(s, ()))
        return got, len(want) - len(got)


class Radio:
    def __init__(self, options: SwarmOptions, bus: Bus) -> None:
        self.options = options
        self.bus = bus
        self.team = team_setup(options)
        self.realtime = options.mode is Mode.REALTIME
        phases = [(Kind.ESTIMATE, 0)]
        if self.team.acks:
            phases += [(Kind.ACK, 0)]
        if self.team.factors:  # the pair messages
            phases += [(Kind.ACK, 1)]
        if self.team.gauge:
            phases += [(Kind.CONSENSUS, r) for r in range(self.team.gauge_rounds)]
        self.phases = phases
        # Pulled estimates (cached): per step, the robots still correcting and the round.
        self.pull = self.team.pull
        self.pull_state: dict[int, dict] = {}
        self.sync = collections.Counter()
        self.channels: dict[int, StepChannel] = {}
        self.pending: dict[tuple[int, Kind, int], dict[int, Message]] = {}
        self.next_phase: dict[int, int] = {}
        self.waiting: dict[int, list[Message]] = collections.defaultdict(list)
        self.alive: set[int] = set()
        self.stats: dict[int, collections.Counter] = collections.defaultdict(collections.Counter)
        self.dropped_unknown_step = 0
        self.outbox: dict[int, list[Message]] = collections.defaultdict(list)
        self.ended = False
        self.world_seen = False

    # ------------------------------------------------------------------ inbox
    def handle(self, item) -> None:
        tag, key, payload = item
        if tag == "alive":
            who = key.split("/alive/", 1)[1]
            if who.startswith("robot/"):
                b = int(who.split("/")[1])
                (self.alive.add if payload else self.alive.discard)(b)
                if not payload and not self.realtime:
                    for k in list(self.next_phase):
                        self.try_deliver(k)
            return
        msg = self.bus.open(item)
        if msg is None:
            return
        if msg.kind is Kind.CHANNEL:
            self.on_channel(msg)
        elif msg.kind in ROBOT_TO_ROBOT and msg.sender < self.team.robots:
            self.on_robot_message(msg)
        elif msg.kind is Kind.CONTROL and msg.body["cmd"] == "end":
            self.ended = True

    def on_channel(self, msg: Message) -> None:
        b = msg.body
        k = msg.step
        ch = StepChannel(b["i"], b["j"], b["ok"].astype(bool), b["fed"])
        self.channels[k] = ch
        self.next_phase[k] = 0
        if self.realtime:
            if self.team.gauge:
                for r in sorted(ch.fed):
                    self._deliver(r, k, NEIGHBOURS_PHASE, 0, [])
            for m in self.waiting.pop(k, []):
                self.forward(m)
            horizon = k - self.options.max_age_steps - 3
            for old in [s for s in self.channels if s < horizon]:
                del self.channels[old]
                self.next_phase.pop(old, None)
                self.flush_stats(old)
        else:
            self.try_deliver(k)

    def on_robot_message(self, msg: Message) -> None:
        k = msg.step
        if msg.kind is Kind.REQUEST and not len(msg.body["to"]):
            # lockstep's "this robot asks for nothing more": a barrier, not a radio message
            self.sync["frames"] += 1
            self.sync["bytes"] += len(msg.raw)
        else:
            c = self.stats[k]
            c[(msg.sender, int(msg.kind), "msgs")] += 1
            c[(msg.sender, int(msg.kind), "bytes")] += len(msg.raw)
        if self.realtime:
            if k in self.channels:
                self.forward(msg)
            elif not self.channels or k > max(self.channels):
                self.waiting[k].append(msg)
            else:
                self.dropped_unknown_step += 1
            return
        rnd = int(msg.body["round"]) if "round" in msg.body else 0
        self.pending.setdefault((k, msg.kind, rnd), {})[msg.sender] = msg
        self.try_deliver(k)

    # ------------------------------------------------------------------ delivery
    def _deliver(self, to: int, k: int, phase: int, rnd: int, frames: list[bytes]) -> None:
        ch = self.channels[k]
        self.bus.send(
            self.bus.key("robot", to, "inbox"),
            Kind.DELIVERY,
            k,
            {
                "to": to,
                "phase": phase,
                "round": rnd,
                "nb": np.asarray(ch.neighbours.get(to, []), dtype=np.int64),
                "msgs": frames,
            },
        )

    def _count(self, k: int, msg: Message, got: list[int], lost: int) -> None:
        c = self.stats[k]
        c[(msg.sender, int(msg.kind), "copies")] += len(got)
        c[(msg.sender, int(msg.kind), "lost")] += lost

    def forward(self, msg: Message) -> None:
        """Realtime: route one frame into the receivers' outboxes (sent by :meth:`flush`)."""
        got, lost = self.channels[msg.step].route(msg, self.options.jam_acks)
        self._count(msg.step, msg, got, lost)
        for r in got:
            self.outbox[r].append(msg)

    def flush(self) -> None:
        """Realtime: one DELIVERY per receiver with every frame routed to it since the last
        flush (called whenever the radio's inbox is empty: batching without waiting)."""
        for r, msgs in self.outbox.items():
            if msgs:
                k = max(m.step for m in msgs)
                if k in self.channels:
                    self._deliver(r, k, FORWARDED_PHASE, 0, [m.raw for m in msgs])
        self.outbox.clear()

    def try_deliver(self, k: int) -> None:
        """Lockstep: deliver every complete phase of step ``k``, in order."""
        ch = self.channels.get(k)
        if ch is None:
            return
        if self.pull:
            self.try_pull(k, ch)
            return
        while self.next_phase.get(k, len(self.phases)) < len(self.phases):
            kind, rnd = self.phases[self.next_phase[k]]
            got = self.pending.get((k, kind, rnd), {})
            expected = ch.fed & self.alive
            if not expected <= set(got):
                return
            inbox: dict[int, list[Message]] = {b: [] for b in expected}
            for s in sorted(got):
                msg = got[s]
                to, lost = ch.route(msg, self.options.jam_acks)
                to = [r for r in to if r in expected]
                self._count(k, msg, to, lost)
                for r in to:
                    inbox[r].append(msg)
            for r in sorted(expected):
                self._deliver(r, k, int(kind), rnd, [m.raw for m in inbox[r]])
            self.pending.pop((k, kind, rnd), None)
            self.next_phase[k] += 1
        self.flush_stats(k)
        self.channels.pop(k, None)
        self.next_phase.pop(k, None)

    def try_pull(self, k: int, ch: StepChannel) -> None:
        """Lockstep, pulled estimates: request rounds until every robot asks for nothing.

        Round r: every robot still correcting sends its REQUEST (an empty one: it is done);
        the radio delivers each request that got through to its target, waits for the
        REPLY of every robot that received one, and delivers the replies to every requester
        of the round (an empty delivery tells a requester that its requests were lost)."""
        st = self.pull_state.setdefault(
            k, {"active": set(ch.fed), "round": 0, "reply": False, "ask": set(), "answer": set()}
        )
        while True:
            r = st["round"]
            if not st["reply"]:
                got = self.pending.get((k, Kind.REQUEST, r), {})
                if not st["active"] & self.alive <= set(got):
                    return
                inbox: dict[int, list[Message]] = collections.defaultdict(list)
                st["ask"] = set()
                for s in sorted(got):
                    msg = got[s]
                    if not len(msg.body["to"]):
                        st["active"].discard(s)
                        continue
                    st["ask"].add(s)
                    to, lost = ch.route(msg, self.options.jam_acks)
                    to = [t for t in to if t in self.alive]
                    self._count(k, msg, to, lost)
                    for t in to:
                        inbox[t].append(msg)
                self.pending.pop((k, Kind.REQUEST, r), None)
                st["active"] &= self.alive
                if not st["ask"]:
                    break  # nobody asks for anything: the step's correction is over
                for t in sorted(inbox):
                    self._deliver(t, k, int(Kind.REQUEST), r, [m.raw for m in inbox[t]])
                st["answer"], st["reply"] = set(inbox), True
            got = self.pending.get((k, Kind.REPLY, r), {})
            if not st["answer"] & self.alive <= set(got):
                return
            replies: dict[int, list[Message]] = {q: [] for q in st["ask"] & self.alive}
            for s in sorted(got):
                msg = got[s]
                to, lost = ch.route(msg, self.options.jam_acks)
                to = [q for q in to if q in replies]
                self._count(k, msg, to, lost)
                for q in to:
                    replies[q].append(msg)
            for q in sorted(replies):
                self._deliver(q, k, int(Kind.REPLY), r, [m.raw for m in replies[q]])
            self.pending.pop((k, Kind.REPLY, r), None)
            st["round"], st["reply"] = r + 1, False
        self.pull_state.pop(k, None)
        self.flush_stats(k)
        self.channels.pop(k, None)
        self.next_phase.pop(k, None)

    def flush_stats(self, k: int) -> None:
        c = self.stats.pop(k, None)
        if c is None:
            return
        keys = sorted({(s, kind) for s, kind, _ in c})
        col = {
            f: np.array([c[(s, kd, f)] for s, kd in keys], dtype=np.int64)
            for f in ("msgs", "bytes", "copies", "lost")
        }
        self.bus.send(
            self.bus.key("recorder", "stats"),
            Kind.STATS,
            k,
            {
                "robot": np.array([s for s, _ in keys], dtype=np.int64),
                "kind": np.array([kd for _, kd in keys], dtype=np.int64),
                "msgs": col["msgs"],
                "bytes": col["bytes"],
                "copies": col["copies"],
                "jammed": col["lost"],
                "cnt": self.bus.verifier.counts()
                | {
                    "unknown_step": self.dropped_unknown_step,
                    "sync_frames": self.sync["frames"],
                    "sync_bytes": self.sync["bytes"],
                    "cpu_ms": int(1000 * time.process_time()),
                },
            },
        )

    def run(self) -> int:
        bus = self.bus
        bus.subscribe(bus.key("radio", "*"))
        bus.subscribe(bus.key("control", "end"))
        bus.watch_liveliness(bus.key("alive", "robot", "*"))
        bus.watch_liveliness(bus.key("alive", "world"))
        bus.declare_alive(bus.key("alive", "radio"))
        while not self.ended:
            item = bus.get(0.5)
            while item is not None:
                if item[0] == "alive" and item[1].endswith("/alive/world"):
                    self.world_seen = self.world_seen or item[2]
                    if not item[2] and self.world_seen:
                        print("radio: world process lost; stopping", flush=True)
                        return EXIT_LOST
                else:
                    self.handle(item)
                item = bus.get(0)  # drain what is queued, then deliver it in batches
            if self.realtime:
                self.flush()
        for k in sorted(self.stats):
            self.flush_stats(k)
        time.sleep(0.1)
        return EXIT_OK


def run_radio(options: SwarmOptions) -> int:
    """Run the radio process until the world ends the run."""
    bus = connect_bus(options, RADIO)
    try:
        return Radio(options, bus).run()
    finally:
        bus.close()
