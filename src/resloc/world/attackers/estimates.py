"""Attackers that are not measurement lies: a compromised robot's estimates, and replay."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

__all__ = ["CompromisedRobot", "Replay"]


class CompromisedRobot:
    """A compromised robot that broadcasts false estimates of itself.

    Robot ``target`` (in every team) keeps localizing honestly but every estimate it sends
    is moved sideways by an offset ramping at ``speed`` m/s up to ``max_offset`` m, in its
    own heading's left direction; its neighbours' measurements of it stay honest. This is
    the threat the paper's sensing model leaves out: the lie arrives through the radio.
    Not tuned to the detector: a slow ramp is what a neighbour's innovation cannot tell
    from the robot's own drift (the victims' filters follow it).
    """

    name: ClassVar[str] = "compromised"
    summary: ClassVar[str] = (
        "robot 5 broadcasts its estimate moved sideways by an offset ramping at 0.05 m/s "
        "to 0.5 m (its sensors and its neighbours' sensors stay honest)"
    )
    overrides: ClassVar[dict] = {"attack.kind": "stealthy"}
    target: ClassVar[int] = 5
    speed: ClassVar[float] = 0.05
    max_offset: ClassVar[float] = 0.5

    def mark(self, sdz_attacked, step):
        return step.j % step.robots == self.target

    def attack(self, links, step, params, memory):
        rows = np.flatnonzero(links.j % step.robots == self.target)
        if not rows.size:
            return links
        offset = min(self.max_offset, self.speed * step.k * step.dt)
        x_nb = links.x_nb.copy()
        heading = x_nb[rows, 2]
        x_nb[rows, 0] -= offset * np.sin(heading)
        x_nb[rows, 1] += offset * np.cos(heading)
        return dataclasses.replace(links, x_nb=x_nb, tamper=None)


class Replay:
    """Replay: each SDZ link's honest measurement from 1 s earlier (the world's
    ``attack.kind = "replay"``, ``replay_delay = 30`` steps)."""

    name: ClassVar[str] = "replay"
    summary: ClassVar[str] = "each SDZ link's honest measurement from 1 s (30 steps) earlier"
    overrides: ClassVar[dict] = {"attack.kind": "replay", "attack.replay_delay": 30}

    def mark(self, sdz_attacked, step):
        return sdz_attacked

    def attack(self, links, step, params, memory):
        return dataclasses.replace(links, tamper=None)
