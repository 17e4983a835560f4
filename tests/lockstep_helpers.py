"""The start of the lockstep tests (``tests/test_kernels_*.py``, ``tests/test_engine.py``):
the default scenario's world and, for every path compared (a compiled loop, the numpy
reference, ...), its own estimates and link memory."""

from __future__ import annotations

import numpy as np

from resloc.cl import LinkBatch, LinkMemory, correct, predict
from resloc.experiments.config import Scenario, default_scenario
from resloc.world.world import World


def default_world(
    trials: int, seed: int, start: int = 0, scenario: Scenario | None = None
) -> World:
    """The world of ``scenario`` (default: the default scenario) with ``trials`` trials,
    stepped ``start`` times alone (e.g. to the zone's edge, ``test_kernels_zone.START``)."""
    sc = default_scenario() if scenario is None else scenario
    world = World(sc.world, trials, seed, sc.trigger.lambda2)
    for _ in range(start):
        world.step()
    return world


def start_states(
    world: World, paths, fusion=None, **init
) -> dict[str, tuple[np.ndarray, np.ndarray, LinkMemory]]:
    """Per path: copies of the world's initial estimates ``x0`` ``(B, 3)``, ``P0``
    ``(B, 3, 3)`` (drawn once, shared by the paths) and a link memory of its own, with the
    fusion method's state when ``fusion`` (a strategy) is given:
    ``fusion.init(memory, x0, P0, world.n, **init)``."""
    x0, P0 = world.initial_estimates()
    states = {}
    for path in paths:
        memory = LinkMemory(world.B)
        if fusion is not None:
            fusion.init(memory, x0, P0, world.n, **init)
        states[path] = (x0.copy(), P0.copy(), memory)
    return states


def start_state(world: World, fusion=None, **init) -> tuple[np.ndarray, np.ndarray, LinkMemory]:
    """One path's start (:func:`start_states`)."""
    return start_states(world, (None,), fusion, **init)[None]


def runner_step(filt, x, P, ws, dt: float, params, fusion, memory, channel_ok=None):
    """One step of one path as the runner makes it: the filter's prediction and the fusion
    method's, the links (``ws``: a world step; ``channel_ok`` ``(E,)``, default the
    world's) with the fields the method's transmissions carry, the correction, the
    method's exchange. Returns the correction's ``(x, P, outcome)``."""
    xp, Pp = predict(filt, x, P, ws.u_meas, dt, params)
    Pp = fusion.predict(memory, x, ws.u_meas, dt, params, Pp)
    links = LinkBatch(
        ws.i, ws.j, ws.z, xp[ws.j], Pp[ws.j], ws.channel_ok if channel_ok is None else channel_ok,
        ws.risk_s, ws.risk_c, ws.lambda2, **fusion.link_fields(memory, ws.j),
    )  # fmt: skip
    result = correct(filt, xp, Pp, links, params, memory)
    fusion.exchange(memory, ws.i, ws.j)
    return result
