"""What the world process steps: the simulated world of ``resloc run`` or a recorded MRCLAM
dataset (the replay code of ``resloc mrclam``), both as a sequence of
:class:`~resloc.world.world.WorldStep`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from resloc.runtime.options import SwarmOptions
from resloc.runtime.team import TeamSetup
from resloc.world.world import World, WorldStep

__all__ = ["SimulatedSource", "make_source"]


class SimulatedSource:
    """The scenario's :class:`World` (one team), exactly as ``run_scenario`` builds it."""

    def __init__(self, team: TeamSetup) -> None:
        sc = team.scenario
        self.world = World(sc.world, 1, sc.run.seed, sc.trigger.lambda2)
        self.n = self.world.n
        self.steps = sc.run.steps
        self.seed = sc.run.seed
        self.dt = self.world.dt

    def initial_estimates(self) -> tuple[np.ndarray, np.ndarray]:
        """``x0: (N, 3)``, ``P0: (N, 3, 3)``: the simulator's seeded initial estimates."""
        return self.world.initial_estimates()

    def initial_pose(self) -> np.ndarray:
        return self.world.pose.copy()

    def true_pose(self, b: int) -> np.ndarray:
        return self.world.pose[b].copy()

    def step(self) -> WorldStep:
        return self.world.step()


def make_source(options: SwarmOptions, team: TeamSetup):
    """The world process's source of steps for ``options``."""
    if options.replay:
        from resloc.runtime.replay import ReplaySource

        return ReplaySource(Path(options.replay), team)
    return SimulatedSource(team)
