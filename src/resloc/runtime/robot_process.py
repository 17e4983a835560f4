"""A robot process's loop: the bus's messages to the robots it hosts
(:class:`~resloc.runtime.robot.RobotAgent`), until the world ends the run or is lost."""

from __future__ import annotations

import time

from resloc.errors import ConfigError
from resloc.runtime.messages import Kind, load_or_create_key
from resloc.runtime.options import SwarmOptions
from resloc.runtime.process import EXIT_LOST, EXIT_OK, connect_bus
from resloc.runtime.robot import RobotAgent
from resloc.runtime.team import team_setup

__all__ = ["run_robots"]


def run_robots(options: SwarmOptions, ids: list[int]) -> int:
    """Run robots ``ids`` in this process until the world ends the run."""
    team = team_setup(options)
    bad = [i for i in ids if not 0 <= i < team.robots]
    if bad:
        raise ConfigError(f"--id {bad[0]}: the team has robots 0..{team.robots - 1}")
    key = load_or_create_key(options.key_file)
    bus = connect_bus(options, ids[0])
    try:
        agents = {i: RobotAgent(i, team, options, bus, key) for i in ids}
        for i in ids:
            for leaf in ("start", "sensors", "inbox"):
                bus.subscribe(bus.key("robot", i, leaf))
        bus.subscribe(bus.key("control", "end"))
        bus.watch_liveliness(bus.key("alive", "world"))
        for i in ids:
            bus.declare_alive(bus.key("alive", "robot", i))
        world_seen = False
        while True:
            deadline = min(
                (a.deadline for a in agents.values() if a.phase and a.realtime), default=None
            )
            wait = 0.5 if deadline is None else max(0.0, deadline - time.monotonic())
            item = bus.get(wait)
            now = time.monotonic()
            if item is not None:
                tag, key_expr, payload = item
                if tag == "alive":
                    if payload:
                        world_seen = True
                    elif world_seen:
                        print(f"robot {ids}: world process lost; stopping", flush=True)
                        return EXIT_LOST
                else:
                    msg = bus.open(item)
                    if msg is not None:
                        if msg.kind is Kind.CONTROL and msg.body["cmd"] == "end":
                            return EXIT_OK
                        parts = key_expr.split("/")
                        agent = agents.get(int(parts[-2])) if parts[-2].isdigit() else None
                        if agent is not None:
                            if msg.kind is Kind.START:
                                agent.on_start(msg)
                            elif msg.kind is Kind.SENSORS:
                                agent.on_sensors(msg)
                            elif msg.kind is Kind.DELIVERY:
                                agent.on_delivery(msg)
            for a in agents.values():
                a.tick(now)
    finally:
        bus.close()
