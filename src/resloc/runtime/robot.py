"""Robot processes: one :class:`~resloc.cl.node.RobotNode` per robot, fed over the wire.

A robot process hosts one robot (``resloc robot --id I``, as on a robot's own computer) or K
of them (``resloc swarm --robots-per-process K``); each robot is an independent
:class:`RobotAgent` with its own node, its own verifier for robot-to-robot frames and its own
counters. A step of robot i:

1. ``SENSORS(k)``: ``node.predict(u, dt)``; publish its predicted estimate (``ESTIMATE``).
2. Neighbours' estimates arrive (through the radio). ``node.correct`` on the sensed links
   whose neighbour estimate arrived: the detector, the event trigger and the fusion are the
   node's (the library's). A link whose estimate was lost (jammed, out of range) cannot be
   evaluated and is counted as ``unheard``.
3. Gauge fusion: publish the acknowledgements ``node.gauge_acks()`` (one ACK frame to all the
   robots it fused), close the step with the acknowledgements received
   (``node.gauge_close``), then ``gauge_rounds`` consensus exchanges
   (``node.gauge_message`` / ``node.gauge_mix``) with the communication neighbours. Split
   CI: one ACK frame naming ``node.delivery_acks()``, then ``node.delivery_close`` with the
   number of robots that named this one (its estimates carry ``node.independent``).
   Factorized: its estimates carry ``node.factor_for(j)`` for each robot j it measured; one
   ACK frame naming the higher ids it fused, then one ACK frame of round 1 with
   ``node.factor_message(p)`` for each lower partner p of the step (a robot it fused or that
   named it), then ``node.factor_close`` with the messages of its higher partners.
4. Publish ``REPORT(k)``: corrected estimate, reported covariance, per-link decisions,
   counters.

Lockstep: each phase waits for the radio's delivery of the phase. Realtime: each phase waits
at most its window (a fraction of dt) and goes on with what arrived; an estimate from an
earlier step is used while at most ``max_age_steps`` old, dropped (and counted) beyond.
A lost acknowledgement: the step closes without it, so the gauge covariance misses that
neighbour's share of the leak (``docs/runtime.md``); the estimates never depend on it.
"""

from __future__ import annotations

import collections
import time

import numpy as np

from resloc.cl.node import RobotNode
from resloc.runtime.exchange_agent import ExchangingRobot
from resloc.runtime.messages import FLAG_HEARD, Kind, Message, Verifier
from resloc.runtime.options import Mode, SwarmOptions
from resloc.runtime.pull_agent import PullingRobot
from resloc.runtime.radio import NEIGHBOURS_PHASE
from resloc.runtime.schema import link_flags
from resloc.runtime.team import TeamSetup
from resloc.runtime.transport import Bus
from resloc.runtime.witness_agent import WitnessingRobot

__all__ = ["RobotAgent"]


class RobotAgent(PullingRobot, WitnessingRobot, ExchangingRobot):
    """One robot's side of the protocol around its :class:`RobotNode`."""

    def __init__(self, rid: int, team: TeamSetup, options: SwarmOptions, bus: Bus, key: bytes):
        self.id = rid
        self.team = team
        self.options = options
        self.bus = bus
        self.realtime = options.mode is Mode.REALTIME
        self.filt = team.make_filter()
        self.risk_zones = team.risk_zones
        self.node: RobotNode | None = None
        self.inner = Verifier(key, options.max_age_s)  # robot-to-robot frames, own replay state
        self.counts: collections.Counter = collections.Counter()
        self.step = 0
        self.phase: tuple[Kind, int] | None = None  # what this robot waits for
        self.deadline = 0.0
        self.sensors: dict | None = None
        self.tables: dict[int, list[int]] = {}  # communication neighbours per step
        # per neighbour, its recent estimates by step (a lagging robot must not see a
        # neighbour's newer estimate replace the one of the step it is closing)
        self.estimates: dict[int, dict[int, tuple[np.ndarray, np.ndarray]]] = {}
        # (neighbour, step) -> the neighbour's reading of this robot that step (zone trust)
        self.reciprocal: dict[tuple[int, int], np.ndarray] = {}
        # (neighbour, step) -> the independent part its estimate carried (split CI)
        self.independent: dict[tuple[int, int], np.ndarray] = {}
        # (neighbour, step) -> the factor it keeps for this robot (factorized)
        self.factors_in: dict[tuple[int, int], np.ndarray] = {}
        # (neighbour, step) -> the witness notes its estimate carried (ids, rows)
        self.notes_in: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self.acks: dict[int, np.ndarray] = {}
        self.pair_messages: dict[int, np.ndarray] = {}  # higher partner -> its message
        self.consensus: dict[int, dict[int, tuple[np.ndarray, int]]] = {}
        self.outcome: tuple[np.ndarray, np.ndarray, np.ndarray, int] | None = None
        self.cpu0 = 0.0
        # Pulled estimates (neighbour_estimate = "cached"): this robot's predicted estimate
        # per recent step (what it replies with), requests it cannot answer yet, and its own
        # correction's request rounds.
        self.snapshots: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.deferred: list[Message] = []
        self.pulling = None
        self.pull_round = -1
        self.asked: list[int] = []
        self.replies: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.unsent = 0  # requests an overrun never sent

    # ------------------------------------------------------------------ start
    def on_start(self, msg: Message) -> None:
        b = msg.body
        team = self.team
        self.node = RobotNode(
            self.id,
            self.filt,
            team.params,
            b["x"],
            b["P"],
            n_ids=team.robots,
            team_size=team.team_size,
        )
        self.phase = None
        self.estimates.clear()
        self.realtime = bool(b["rt"])  # the run's mode, whatever this process was told
        self.warm_up()
        self.cpu0 = time.process_time()  # CPU of the run itself, not of the start-up
        if b["rejoin"]:
            self.counts["rejoined"] += 1
        self.step = msg.step
        self.bus.send(
            self.bus.key("control", "world"),
            Kind.CONTROL,
            msg.step,
            {"cmd": "ready", "arg": "", "n": self.id},
            sender=self.id,
        )

    @property
    def neighbours(self) -> list[int]:
        """This step's communication neighbours (the radio's neighbour table)."""
        return self.tables.get(self.step, [])

    def warm_up(self) -> None:
        """Load the compiled kernels and declare the publishers before the first step (the
        first correction in a fresh process takes ~0.1-0.5 s: in realtime, several steps)."""
        team = self.team
        scratch = RobotNode(
            self.id,
            self.filt,
            team.params,
            np.zeros(3),
            np.eye(3) * 0.01,
            n_ids=team.robots,
            team_size=team.team_size,
        )
        scratch.predict(np.array([0.1, 0.0]), team.dt)
        other = (self.id + 1) % team.robots
        scratch.correct(
            np.array([other]),
            np.array([[1.0, 0.0]]),
            np.array([[1.0, 0.0, 0.0]]),
            np.eye(3)[None] * 0.01,
            np.ones(1, dtype=bool),
            0.0,
            0.0,
            1.0,
            P_nb_ind=np.eye(3)[None] * 0.005 if team.split else None,
            factor_nb=np.zeros((1, 3, 3)) if team.factors else None,
        )
        for key in (self.bus.key("radio", "in"), self.bus.key("report", self.id)):
            self.bus.declare(key)

    # ------------------------------------------------------------------ phases
    def on_sensors(self, msg: Message) -> None:
        if self.node is None:
            return
        if self.phase is not None:  # realtime: a new step before this one finished
            self.counts["overrun"] += 1
            self.finish_step()
        b = msg.body
        self.step = msg.step
        self.sensors = b
        self.acks.clear()
        self.pair_messages.clear()
        self.consensus.clear()
        keep = self.step - self.options.max_age_steps - 2
        for store in (self.reciprocal, self.independent, self.factors_in, self.notes_in):
            for old in [key for key in store if key[1] < keep]:
                del store[old]
        self.node.predict(b["u"], self.team.dt)
        x, P = self.node.estimate
        if self.team.pull:
            self.start_pull(x, P)
            return
        body = {"x": x, "P": P}
        if self.team.readings:  # the receivers' reverse-link measurements
            body |= {"rj": b["j"], "rz": b["z"]}
        if self.team.split:
            body["Pi"] = self.node.independent
        if self.team.factors:  # sigma_ji for each robot j that may fuse this estimate
            fj = b["j"].astype(np.int64)
            body |= {"fj": fj, "fs": [self.node.factor_for(int(j)) for j in fj]}
        if self.team.witness:  # the notes of the step before ride on this step's estimate
            body = self.notes_fields(body)
        self.send(Kind.ESTIMATE, body)
        self.wait(Kind.ESTIMATE, 0)

    def wait(self, kind: Kind, rnd: int) -> None:
        self.phase = (kind, rnd)
        if self.realtime:
            windows = self.options.windows
            frac = (
                self.options.reply_window
                if kind is Kind.REPLY
                else windows[0]
                if kind is Kind.ESTIMATE
                else windows[1]
                if kind is Kind.ACK
                else (windows[2])
            )
            self.deadline = time.monotonic() + frac * self.team.dt

    def send(self, kind: Kind, body: dict) -> None:
        self.bus.send(self.bus.key("radio", "in"), kind, self.step, body, sender=self.id)

    def on_delivery(self, msg: Message) -> None:
        """Frames the radio delivered to this robot (each verified here, as received)."""
        body = msg.body
        if body["phase"] in (NEIGHBOURS_PHASE, int(Kind.ESTIMATE)):  # the neighbour table
            self.tables[msg.step] = [int(v) for v in body["nb"]]
            for old in [k for k in self.tables if k < msg.step - 2]:
                del self.tables[old]
        requests = []
        for frame in body["msgs"]:
            inner = self.inner.open(frame, self.bus.key("radio", "in"))
            if inner is None or inner.sender >= self.team.robots or inner.sender == self.id:
                self.counts["rejected_inner"] += 1
                continue
            # how long robot-to-robot frames take to arrive (sender's clock to this one's)
            self.counts[f"age_ms_sum_{inner.kind.name.lower()}"] += int(
                1000 * (time.time() - inner.timestamp)
            )
            self.counts[f"age_n_{inner.kind.name.lower()}"] += 1
            if inner.kind is Kind.REQUEST:
                if self.id in inner.body["to"] and self.node is not None:
                    requests.append(inner)
                continue
            self.take(inner)
        if requests:
            self.answer(requests)
        if not self.realtime and self.phase == (body["phase"], body["round"]):
            if msg.step == self.step:
                self.advance()
        elif self.realtime and self.phase is not None and self.complete():
            self.advance()

    def take(self, m: Message) -> None:
        if m.kind is Kind.REPLY:
            if self.id not in m.body["to"]:
                return
            if (
                self.phase != (Kind.REPLY, int(m.body["round"]))
                or m.step != self.step
                or m.sender not in self.asked
            ):
                self.counts["replies_late"] += 1  # the round closed without it: not fused
                self.cache_late_reply(m)
                return
            self.replies[m.sender] = (m.body["x"], m.body["P"])
        elif m.kind is Kind.ESTIMATE:
            hist = self.estimates.setdefault(m.sender, {})
            hist[m.step] = (m.body["x"], m.body["P"])
            keep = m.step - self.options.max_age_steps - 2
            for old in [k for k in hist if k < keep]:
                del hist[old]
            if "Pi" in m.body:
                self.independent[(m.sender, m.step)] = m.body["Pi"]
            if "fj" in m.body:
                mine = np.flatnonzero(m.body["fj"] == self.id)
                if len(mine):  # the factor the sender keeps for this robot
                    self.factors_in[(m.sender, m.step)] = m.body["fs"][mine[0]]
            if "wj" in m.body:
                self.take_notes(m)
            if "rj" in m.body:
                mine = np.flatnonzero(m.body["rj"] == self.id)
                if len(mine):  # the sender measured this robot: the reverse link's reading
                    self.reciprocal[(m.sender, m.step)] = m.body["rz"][mine[0]]
        elif m.kind is Kind.ACK:
            if (
                m.step != self.step
                or self.phase is None
                or self.phase[0]
                not in (
                    Kind.ESTIMATE,
                    Kind.ACK,
                )
            ):
                self.counts["acks_late"] += 1  # the step closed without it
                return
            mine = m.body["to"] == self.id
            if not mine.any():
                return
            form = "gauge" if "ack" in m.body else "pair" if "pair" in m.body else "ids"
            if form not in self.team_ack_forms:  # a key holder's frame of the wrong form
                self.counts["acks_malformed"] += 1
            elif form == "gauge":
                self.acks[m.sender] = m.body["ack"][mine].sum(axis=0)
            elif form == "pair":  # factorized: a higher partner's pair message
                self.pair_messages[m.sender] = m.body["pair"][np.flatnonzero(mine)[0]]
            else:  # the sender fused this robot's estimate
                self.acks[m.sender] = None
        elif m.kind is Kind.CONSENSUS:
            rnd = int(m.body["round"])
            if (
                m.step != self.step
                or self.phase is None
                or (self.phase[0] is Kind.CONSENSUS and rnd < self.phase[1])
            ):
                self.counts["consensus_late"] += 1
                return
            self.consensus.setdefault(rnd, {})[m.sender] = (m.body["m"], int(m.body["deg"]))

    @property
    def team_ack_forms(self) -> frozenset[str]:
        """The ACK frames this team's fusion sends: gauge blocks, ids, or ids and pairs."""
        if self.team.gauge:
            return frozenset({"gauge"})
        return frozenset({"ids", "pair"}) if self.team.factors else frozenset({"ids"})

    def complete(self) -> bool:
        """Realtime: everything this phase can expect has arrived (go on before the window
        closes)."""
        kind, _ = self.phase
        if kind is Kind.REPLY:
            return set(self.asked) <= set(self.replies)
        if kind is Kind.ESTIMATE:
            need = {int(j) for j in self.sensors["j"]}
            return all(self.step in self.estimates.get(j, {}) for j in need)
        if kind is Kind.CONSENSUS:
            return set(self.neighbours) <= set(self.consensus.get(self.phase[1], {}))
        return False  # acknowledgements: their number is unknown to the receiver

    def tick(self, now: float) -> None:
        if self.realtime and self.phase is not None and now >= self.deadline:
            self.advance()

    def advance(self) -> None:
        kind, rnd = self.phase
        if kind is Kind.REPLY:
            self.phase = None
            self.pull_next(self.replies)
        elif kind is Kind.ESTIMATE:
            self.correct()
            if not self.team.acks:
                self.phase = None
                self.finish_step()
                return
            self.send(Kind.ACK, self.ack_body())
            self.wait(Kind.ACK, 0)
        elif kind is Kind.ACK and rnd == 0:
            self.close_acks()
            self.counts["acks_received"] += len(self.acks)
            if self.team.gauge:
                self.start_round(0)
            elif self.team.factors:
                self.send(Kind.ACK, self.pair_body())
                self.wait(Kind.ACK, 1)
            else:
                self.phase = None
                self.finish_step()
        elif kind is Kind.ACK:
            self.close_pairs()
            self.phase = None
            self.finish_step()
        elif kind is Kind.CONSENSUS:
            mine = self.consensus.pop(rnd, {})
            got = [s for s in sorted(mine) if s in self.neighbours]
            self.node.gauge_mix([mine[s][0] for s in got], [mine[s][1] for s in got])
            self.counts["consensus_missing"] += len(set(self.neighbours) - set(got))
            if rnd + 1 < self.team.gauge_rounds:
                self.start_round(rnd + 1)
            else:
                self.phase = None
                self.finish_step()

    def start_round(self, rnd: int) -> None:
        self.wait(Kind.CONSENSUS, rnd)
        self.send(
            Kind.CONSENSUS,
            {"round": rnd, "m": self.node.gauge_message(), "deg": len(self.neighbours)},
        )

    def correct(self) -> None:
        s = self.sensors
        j = s["j"].astype(np.int64)
        heard = np.zeros(len(j), dtype=bool)
        # Lockstep uses this step's estimates only (as the simulator); realtime also late ones.
        max_age = self.options.max_age_steps if self.realtime else 0
        x_nb = np.zeros((len(j), 3))
        P_nb = np.zeros((len(j), 3, 3))
        # A reading describes its own step: a late estimate's is not this step's geometry.
        z_reciprocal = np.full((len(j), 2), np.nan)
        P_nb_ind = np.zeros((len(j), 3, 3))
        factor_nb = np.zeros((len(j), 3, 3))
        for e, nb in enumerate(j):
            steps = [k for k in self.estimates.get(int(nb), {}) if k <= self.step]
            if not steps:
                continue
            newest = max(steps)
            age = self.step - newest
            if age > max_age:
                if self.realtime:
                    self.counts["estimates_stale_dropped"] += 1
                continue
            if age > 0:
                self.counts["estimates_late_used"] += 1
            heard[e] = True
            x_nb[e], P_nb[e] = self.estimates[int(nb)][newest]
            if self.team.split:
                P_nb_ind[e] = self.independent.get((int(nb), newest), 0.0)
            if self.team.factors:
                factor = self.factors_in.get((int(nb), newest))
                if factor is None:  # the sender did not measure this robot: no factor
                    # came, the cross-covariance is taken as zero (counted)
                    self.counts["factors_missing"] += 1
                else:
                    factor_nb[e] = factor
            if age == 0 and (int(nb), self.step) in self.reciprocal:
                z_reciprocal[e] = self.reciprocal[(int(nb), self.step)]
        self.counts["unheard"] += int((~heard).sum())
        if self.team.witness:
            self.deliver_notes(j)
        risk_s, risk_c = self.step_risks()
        flags = np.where(heard, FLAG_HEARD, 0).astype(np.uint8)
        norm = np.full(len(j), np.nan)
        repairs = 0
        for rows, params in self.team.link_params(s["z"]):
            h = rows[heard[rows]]
            if not len(h):
                continue
            self.node.params = params
            out = self.node.correct(
                j[h],
                s["z"][h],
                x_nb[h],
                P_nb[h],
                np.ones(len(h), dtype=bool),
                risk_s,
                risk_c,
                s["l2"],
                P_nb_ind=P_nb_ind[h] if self.team.split else None,
                factor_nb=factor_nb[h] if self.team.factors else None,
                z_reciprocal=z_reciprocal[h] if self.team.readings else None,
            )
            flags[h] |= link_flags(out)
            norm[h] = out.norm
            repairs += int(out.repairs)
        self.node.params = self.team.params
        self.outcome = (j, flags, norm, repairs)

    def step_risks(self) -> tuple[float, float]:
        """``Ds(i)``, ``Dc(i)`` for this step's trigger: the world's (at the true position) or,
        with ``trigger.risk_source = "estimated"``, at this robot's predicted estimate."""
        risk_s, risk_c = self.sensors["rs"], self.sensors["rc"]
        if self.risk_zones is None:
            return risk_s, risk_c
        sdz, cdz = self.risk_zones
        p = self.node.x[:, :2]
        return (
            float(sdz.risk(p)[0]) if sdz else risk_s,
            float(cdz.risk(p)[0]) if cdz else risk_c,
        )

    def finish_step(self) -> None:
        """Report the step (realtime overrun: first close what is still open)."""
        if self.pulling is not None:
            self.pull_abandon()
        if self.phase is not None:
            kind, _ = self.phase
            if kind is Kind.ESTIMATE:
                self.correct()
            elif kind is Kind.ACK and self.phase[1] == 0:
                self.close_acks()
                if self.team.factors:
                    self.close_pairs()
            elif kind is Kind.ACK:
                self.close_pairs()
            self.phase = None
        j, flags, norm, repairs = self.outcome
        self.bus.send(
            self.bus.key("report", self.id),
            Kind.REPORT,
            self.step,
            {
                "robot": self.id,
                "x": self.node.x[0],
                "P": self.node.covariance,
                "j": j,
                "flags": flags,
                "norm": norm,
                "rep": repairs,
                "cnt": dict(self.counts)
                | {f"inner_{k}": v for k, v in self.inner.counts().items()}
                | {"cpu_ms_process": int(1000 * (time.process_time() - self.cpu0))},
            },
            sender=self.id,
        )
