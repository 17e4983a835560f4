"""bench/compromised_bound.py's genie: it drops exactly the links whose neighbour is a
compromised robot (in every team of the batch), and nothing the compromised robots fuse."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from resloc.cl.links import LinkBatch
from resloc.world.attackers.base import AttackStep

BENCH = Path(__file__).resolve().parents[1] / "bench" / "compromised_bound.py"


def _genie():
    spec = importlib.util.spec_from_file_location("compromised_bound", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.DropBroadcasts


def test_the_genie_drops_exactly_the_compromised_robots_broadcasts():
    robots = 6  # two teams of 6 in the batch
    i = np.array([0, 5, 1, 7, 11, 6, 4])
    j = np.array([5, 0, 4, 11, 7, 5, 3])  # 11 is robot 5 of the second team
    E = len(i)
    z = np.tile([1.0, 0.1], (E, 1))
    x = np.zeros((2 * robots, 3))
    P = np.tile(np.eye(3), (2 * robots, 1, 1))
    channel = np.array([1, 1, 1, 1, 1, 0, 1], bool)  # one link already lost
    links = LinkBatch.from_predicted(
        i, j, z, x, P, channel, np.zeros(12), np.zeros(12), np.ones(12)
    )
    step = AttackStep(1, 0.1, x, i, j, z, np.zeros(E, bool), robots)
    genie = _genie()(np.array([5]))
    out = genie.attack(links, step, None, None)
    np.testing.assert_array_equal(out.channel_ok, [0, 1, 1, 0, 1, 0, 1])
    np.testing.assert_array_equal(genie.mark(None, step), [1, 0, 0, 1, 0, 1, 0])
    np.testing.assert_array_equal(out.z, links.z)  # nothing falsified
    assert genie.overrides == {"attack.kind": "stealthy"}  # the SDZ stays, nobody lies in it
