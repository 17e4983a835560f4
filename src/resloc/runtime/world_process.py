"""The world process: the same :class:`~resloc.world.world.World` as ``resloc run`` (or an
MRCLAM replay), publishing each robot's sensor data on its own key expression.

Per step ``k`` it publishes ``TRUTH`` (recorder), ``CHANNEL`` (radio: the step's sensed links
and the channel draws of the paper's communication model) and one ``SENSORS`` per fed robot
(odometry, its range/bearing measurements, ``Ds``, ``Dc``, ``lambda2``). In lockstep mode it
then waits for the ``REPORT`` of every fed robot that is still alive; in realtime mode it
keeps to the wall clock (``dt`` per step) and waits for nobody.

Robots come and go: a robot whose liveliness token disappears is dropped from the next steps;
a robot whose token (re)appears gets a ``START`` (a re-joining robot: its true pose plus
noise of ``rejoin_std``, with that covariance, the "large covariance" of a lost robot) and is
fed from the step after its ``ready``. Losing the radio or the recorder ends the run.
"""

from __future__ import annotations

import time

import numpy as np

from resloc.runtime.messages import WORLD, Kind
from resloc.runtime.options import Mode, SwarmOptions
from resloc.runtime.process import EXIT_LOST, EXIT_OK, connect_bus
from resloc.runtime.sources import make_source
from resloc.runtime.team import team_setup
from resloc.runtime.transport import Bus

__all__ = ["run_world"]


class WorldProcess:
    """State of the world process between inbox items."""

    def __init__(self, options: SwarmOptions, bus: Bus) -> None:
        self.options = options
        self.bus = bus
        self.team = team_setup(options)
        self.source = make_source(options, self.team)
        self.n = self.source.n
        self.alive: set[str] = set()
        self.active: set[int] = set()  # robots fed (they acknowledged their START)
        self.pending_start: dict[int, float] = {}  # robot -> last START sent (monotonic)
        self.reports: set[int] = set()
        self.fed: set[int] = set()
        self.step = 0
        self.stop_reason = ""
        self.rng = np.random.default_rng([self.source.seed, 0x5EED])
        self.x0, self.P0 = self.source.initial_estimates()

    # ------------------------------------------------------------------ events
    def handle(self, item) -> None:
        tag, key, payload = item
        if tag == "alive":
            self._on_alive(key.split("/alive/", 1)[1], payload)
            return
        msg = self.bus.open(item)
        if msg is None:
            return
        if msg.kind is Kind.REPORT and msg.step == self.step:
            self.reports.add(int(msg.body["robot"]))
        elif msg.kind is Kind.CONTROL:
            cmd = msg.body["cmd"]
            if cmd == "ready" and msg.body["n"] in self.pending_start:
                del self.pending_start[msg.body["n"]]
                self.active.add(int(msg.body["n"]))
            elif cmd == "stop":
                self.stop_reason = "interrupted (stop requested)"

    def _on_alive(self, who: str, up: bool) -> None:
        if up:
            self.alive.add(who)
        else:
            self.alive.discard(who)
        if who.startswith("robot/"):
            b = int(who.split("/")[1])
            if not up:
                self.active.discard(b)
                self.pending_start.pop(b, None)
            elif self.step > 0 and b not in self.active and 0 <= b < self.n:
                self._start(b, rejoin=True)
        elif not up and who in ("radio", "recorder") and not self.stop_reason:
            self.stop_reason = f"{who} process lost at step {self.step}"

    def _start(self, b: int, rejoin: bool) -> None:
        if rejoin:
            pos, head = self.options.rejoin_std
            std = np.array([pos, pos, head])
            x = self.source.true_pose(b) + self.rng.normal(size=3) * std
            P = np.diag(std**2)
        else:
            x, P = self.x0[b], self.P0[b]
        self.bus.send(
            self.bus.key("robot", b, "start"),
            Kind.START,
            self.step,
            {
                "robot": b,
                "x": x,
                "P": P,
                "rejoin": rejoin,
                "rt": self.options.mode is Mode.REALTIME,
            },
        )
        self.pending_start[b] = time.monotonic()

    def pump(self, timeout: float) -> None:
        item = self.bus.get(timeout)
        while item is not None:
            self.handle(item)
            item = self.bus.get(0)

    def robots_alive(self) -> set[int]:
        return {int(w.split("/")[1]) for w in self.alive if w.startswith("robot/")}

    # ------------------------------------------------------------------ phases
    def wait_for_team(self) -> bool:
        deadline = time.monotonic() + self.options.startup_timeout_s
        need = {"radio", "recorder", *(f"robot/{b}" for b in range(self.n))}
        while not need <= self.alive:
            if time.monotonic() > deadline or self.stop_reason:
                missing = sorted(need - self.alive)
                self.stop_reason = self.stop_reason or f"start-up timed out waiting for {missing}"
                return False
            self.pump(0.1)
        for b in range(self.n):
            self._start(b, rejoin=False)
        while self.pending_start:
            if time.monotonic() > deadline or self.stop_reason:
                self.stop_reason = self.stop_reason or "start-up timed out waiting for ready"
                return False
            self.pump(0.1)
            now = time.monotonic()
            for b, sent in list(self.pending_start.items()):
                if now - sent > 1.0:  # START lost in a race with the subscription: resend
                    self._start(b, rejoin=False)
        return True

    def publish_step(self) -> None:
        ws = self.source.step()
        self.step = ws.k
        fed = np.array(sorted(self.active), dtype=np.int64)
        bus, k = self.bus, ws.k
        bus.send(
            bus.key("recorder", "truth"),
            Kind.TRUTH,
            k,
            {"pose": ws.pose, "i": ws.i, "j": ws.j, "att": ws.attacked, "fed": fed},
        )
        bus.send(
            bus.key("radio", "channel"),
            Kind.CHANNEL,
            k,
            {"i": ws.i, "j": ws.j, "ok": ws.channel_ok, "fed": fed},
        )
        for b in fed:
            rows = ws.i == b
            bus.send(
                bus.key("robot", int(b), "sensors"),
                Kind.SENSORS,
                k,
                {
                    "u": ws.u_meas[b],
                    "l2": float(ws.lambda2[b]),
                    "rs": float(ws.risk_s[b]),
                    "rc": float(ws.risk_c[b]),
                    "j": ws.j[rows],
                    "z": ws.z[rows],
                },
            )
        self.fed = set(fed.tolist())
        self.reports = set()

    def wait_lockstep(self) -> None:
        deadline = time.monotonic() + self.options.barrier_timeout_s
        while not self.stop_reason:
            waiting = (self.fed & self.robots_alive()) - self.reports
            if not waiting:
                return
            if time.monotonic() > deadline:
                print(
                    f"world: step {self.step}: no report from robots {sorted(waiting)} within "
                    f"{self.options.barrier_timeout_s:g} s; going on without them",
                    flush=True,
                )
                self.active -= waiting
                return
            self.pump(0.05)

    def run(self) -> int:
        bus = self.bus
        bus.subscribe(bus.key("report", "*"))
        bus.subscribe(bus.key("control", "world"))
        bus.watch_liveliness(bus.key("alive", "**"))
        bus.declare_alive(bus.key("alive", "world"))
        if not self.wait_for_team():
            return self.end()
        e = np.zeros(0, dtype=np.int64)
        bus.send(
            bus.key("recorder", "truth"),
            Kind.TRUTH,
            0,
            {"pose": self.source.initial_pose(), "i": e, "j": e, "att": e, "fed": e},
        )
        realtime = self.options.mode is Mode.REALTIME
        t0 = time.monotonic()
        for k in range(1, self.source.steps + 1):
            if self.stop_reason:
                break
            self.publish_step()
            if realtime:
                while not self.stop_reason:
                    left = t0 + k * self.team.dt - time.monotonic()
                    if left <= 0:
                        break
                    self.pump(left)
            else:
                self.wait_lockstep()
            bus.send(
                bus.key("control", "progress"),
                Kind.CONTROL,
                k,
                {"cmd": "progress", "arg": "", "n": k},
            )
        if realtime and not self.stop_reason:  # let the last step's messages land
            end = time.monotonic() + 2.0 * self.team.dt + 0.5
            while time.monotonic() < end and self.reports < (self.fed & self.robots_alive()):
                self.pump(0.02)
        return self.end()

    def end(self) -> int:
        reason = self.stop_reason or "complete"
        self.bus.send(
            self.bus.key("control", "end"),
            Kind.CONTROL,
            self.step,
            {"cmd": "end", "arg": reason, "n": self.step},
        )
        time.sleep(0.2)  # let the end notice leave before the session closes
        return EXIT_OK if reason == "complete" or reason.startswith("interrupted") else EXIT_LOST


def run_world(options: SwarmOptions) -> int:
    """Run the world process to the end of the run; returns its exit code."""
    bus = connect_bus(options, WORLD)
    try:
        return WorldProcess(options, bus).run()
    finally:
        bus.close()
