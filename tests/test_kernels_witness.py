"""The witness stage on the compiled path (:mod:`resloc.cl.kernels_witness`).

The lockstep case runs the default scenario (two trials batched, 34 robots) with the best
defence and the witness through three paths, each with its own estimates, memory and
attacker's view: the rounds, the row-order loop and the numpy reference. Three compromised
robots lie; their oracle believes the witness threshold is four times what the defence
uses, so they send lies (and lying notes) the stage convicts: the verdicts then discard
rows, which the compiled paths must reproduce (1e-9, identical decisions, the same witness
statistic), having actually run.
"""

from __future__ import annotations

import dataclasses
from dataclasses import replace

import numpy as np
import pytest

from resloc.cl import LinkBatch, LinkMemory, correct, kernels, kernels_witness, predict
from resloc.cl import kernels_rounds as rounds
from resloc.cl.backend import kernel_refusal
from resloc.cl.detection_witness import STATE, witness_state
from resloc.cl.params import at_robots
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters import make_filter
from resloc.world.attackers import AttackStep, make_attacker
from resloc.world.world import World
from test_kernels_reciprocal import assert_matches_reference
from test_kernels_redundancy import links_of_one_step
from test_kernels_round_options import _path
from test_kernels_rounds import assert_same_loops

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

DEFENCE = "zone+full+redundancy+sequence+cap+landmarks+witness"
PATHS = ("rounds", "row_order", "numpy")


def _params(**changes):
    return replace(default_scenario().replace(**DEFENCES[DEFENCE]).cl_params(), **changes)


def _witness_states(memory: LinkMemory) -> dict[int, float]:
    stat = memory.stage_statistic(STATE)
    return dict(zip((stat.keys // stat.n_nodes).tolist(), stat.values.tolist(), strict=True))


def lockstep(filt, params, steps: int, seed: int):
    """``steps`` steps through :data:`PATHS`; checks every step, yields the reference's
    outcome, memory and which rows come from a compromised robot."""
    sc = default_scenario()
    world = World(sc.world, 2, seed, sc.trigger.lambda2)
    N = world.n
    x0, P0 = world.initial_estimates()
    state = {path: (x0.copy(), P0.copy(), LinkMemory(world.B)) for path in PATHS}
    adversary = make_attacker("compromised", robots=3, claimed_cov=0.01)
    # the attackers aim at a threshold 4x the defence's: the stage convicts them
    fooled = replace(params, witness_h=4.0 * float(np.max(params.witness_h)))
    for k in range(steps):
        ws = world.step()
        step = AttackStep(k + 1, world.dt, ws.pose, ws.i, ws.j, ws.z, ws.attacked, N)
        step = dataclasses.replace(step, attacked=adversary.mark(ws.attacked, step))
        h = at_robots(params.witness_h, ws.j)
        convicted = witness_state(state["numpy"][2], ws.j) > h  # before the step: discarded
        res = {}
        for path, (x, P, memory) in state.items():
            with _path(path):
                xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
                links = LinkBatch.from_predicted(
                    ws.i, ws.j, ws.z, xp, Pp, ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2
                )
                links = adversary.attack(links, step, fooled, memory)
                before = rounds.LOOP_RUNS.copy()
                runs = kernels_witness.WITNESS_RUNS["verdicts"]
                res[path] = correct(filt, xp, Pp, links, params, memory)
                ran = rounds.LOOP_RUNS - before
                took = kernels_witness.WITNESS_RUNS["verdicts"] - runs
            if path != "numpy":
                assert ran == {path: 1}, f"expected the {path} loop, ran {dict(ran)}"
                assert res[path][2].compiled and took == 1, "the compiled path did not run"
            state[path] = (res[path][0], res[path][1], memory)
        assert_same_loops(res["rounds"], res["row_order"])
        assert_matches_reference(res["rounds"], res["numpy"])
        reference = _witness_states(state["numpy"][2])
        for path in ("rounds", "row_order"):
            got = _witness_states(state[path][2])
            assert got.keys() == reference.keys()
            np.testing.assert_allclose(
                [got[r] for r in reference], list(reference.values()), rtol=0, atol=1e-9
            )
        yield res["numpy"][2], state["numpy"][2], convicted


def test_the_stage_runs_compiled():
    params = _params()
    links = links_of_one_step()
    assert kernel_refusal(make_filter("ckf"), params, links) is None
    tampered = dataclasses.replace(links, tamper=lambda rows, z_hat, S: links.z[rows])
    assert kernel_refusal(make_filter("ckf"), params, tampered) is None  # a Python hook too


def test_compiled_witness_equals_the_reference_through_convictions():
    params = _params()
    discarded = 0
    for out, _memory, convicted in lockstep(make_filter("ckf"), params, 40, 7):
        assert out.detected[convicted].all()  # (no recovery re-admits a convicted robot here)
        discarded += int(convicted.sum())
    assert discarded > 0, "the stage convicted nobody: the case tests nothing"
