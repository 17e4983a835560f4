"""The outvoted stage on the compiled path (:mod:`resloc.cl.kernels_outvoted`).

Against its numpy spec (:func:`~resloc.cl.detection_outvoted.reference_widen`): synthetic
notes on several robots, some persistently off (so robots widen, skip a step, decay), and
the default scenario (two trials batched, 34 robots) with the outvoted defence against
three compromised robots, their notes shielding their victims or not. Each step the
covariances handed to the correction, the stage's per-robot store (``S`` and the factor)
and, in the scenario, the corrected estimates must agree to 1e-9 with the same robots
widened, the compiled pass having run.
"""

from __future__ import annotations

import dataclasses
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from lockstep_helpers import default_world, start_states
from resloc.cl import LinkBatch, LinkMemory, correct, kernels, kernels_outvoted, predict
from resloc.cl.detection_outvoted import OUTVOTED_STATE, reference_widen, widen_outvoted
from resloc.cl.detection_witness import WitnessNotes
from resloc.cl.detection_witness_frames import PENDING, reference_record
from resloc.cl.params import CLParams
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters import make_filter
from resloc.world.attackers import AttackStep, make_attacker
from test_kernels_reciprocal import assert_matches_reference

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

DEFENCE = "zone+full+redundancy+sequence+cap+landmarks+witness+outvoted"


def _store(memory: LinkMemory) -> tuple[np.ndarray, np.ndarray]:
    state = memory.stage_statistic(OUTVOTED_STATE, width=2)
    return state.keys.copy(), state.values.copy()


def _assert_same_store(fast: LinkMemory, ref: LinkMemory) -> None:
    (kf, vf), (kr, vr) = _store(fast), _store(ref)
    np.testing.assert_array_equal(kf, kr)
    np.testing.assert_allclose(vf, vr, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(vf[:, 0] > 0.0, vr[:, 0] > 0.0)  # the same tests running
    np.testing.assert_array_equal(vf[:, 1] > 1.0, vr[:, 1] > 1.0)  # the same robots widened


def _widen_both(params, memories, links, P) -> np.ndarray:
    """The stage by the compiled pass (checked to have run) and by the spec, each on its own
    memory; returns the spec's covariances after checking the two agree."""
    before = dict(kernels_outvoted.OUTVOTED_RUNS)
    with kernels.use_backend("numba"):
        fast = widen_outvoted(params, memories[0], links, P)
    assert kernels_outvoted.OUTVOTED_RUNS["passes"] == before["passes"] + 1, "not compiled"
    with kernels.use_backend("numpy"):
        ref = reference_widen(params, memories[1], links, P)
    assert (fast is P) == (ref is P)  # the same decision: someone widened or nobody
    np.testing.assert_allclose(fast, ref, rtol=1e-9, atol=0.0)
    _assert_same_store(*memories)
    return ref


ROBOTS = 9


def _random_step(rng, offsets, sd_p):
    """Every ordered pair's note (observer i on robot j): robot j's broadcast is
    ``offsets[j]`` from where the observers see it; some frames lost."""
    i, j = (a.ravel() for a in np.meshgrid(np.arange(ROBOTS), np.arange(ROBOTS), indexing="ij"))
    keep = i != j
    i, j = i[keep], j[keep]
    E = len(i)
    sd_q = rng.uniform(0.01, 0.03, E)
    u = offsets[j] + sd_q[:, None] * rng.normal(size=(E, 2))
    Q = np.eye(2) * sd_q[:, None, None] ** 2
    P_pos = np.eye(2) * sd_p[j, None, None] ** 2
    notes = WitnessNotes(u, Q, P_pos, i, j, rng.random(E) > 0.05)
    links = SimpleNamespace(i=i, j=j, channel_ok=rng.random(E) > 0.1)
    return notes, links


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_compiled_stage_equals_the_spec_on_synthetic_notes(seed):
    rng = np.random.default_rng(seed)
    params = CLParams(witness=True, outvoted=True, witness_liars=2.0)
    offsets = np.zeros((ROBOTS, 2))
    offsets[:3] = rng.uniform(-0.04, 0.04, (3, 2))  # three robots persistently off
    sd_p = rng.uniform(0.001, 0.02, ROBOTS)
    memories = (LinkMemory(ROBOTS), LinkMemory(ROBOTS))
    widened = 0
    for _ in range(150):
        notes, links = _random_step(rng, offsets, sd_p)
        for memory in memories:
            reference_record(notes, memory)
        P = np.tile(np.eye(3) * 1e-4, (ROBOTS, 1, 1))
        P[:, :2, :2] = np.eye(2) * sd_p[:, None, None] ** 2
        P[:, 0, 1] = P[:, 1, 0] = 0.3 * sd_p**2
        out = _widen_both(params, memories, links, P)
        widened += int((out[:, 0, 0] > P[:, 0, 0]).sum())
    assert widened >= 5, "nobody widened: the case tests nothing"


def _params(**changes):
    return replace(default_scenario().replace(**DEFENCES[DEFENCE]).cl_params(), **changes)


def lockstep(filt, params, steps: int, seed: int, shield: str, fooled: float):
    """``steps`` steps of the default scenario by the compiled path and the numpy
    reference, each with its own estimates, memory and attacker's view; checks every step
    and yields the robots the reference widened. The attackers aim at a witness threshold
    ``fooled`` times the defence's (larger lies: their victims are pulled off)."""
    world = default_world(2, seed)
    N = world.n
    state = start_states(world, ("numba", "numpy"))
    adversary = make_attacker("compromised", robots=3, claimed_cov=0.01, shield=shield)
    aim = replace(params, witness_h=fooled * float(np.max(params.witness_h)))
    for k in range(steps):
        ws = world.step()
        step = AttackStep(k + 1, world.dt, ws.pose, ws.i, ws.j, ws.z, ws.attacked, N)
        step = dataclasses.replace(step, attacked=adversary.mark(ws.attacked, step))
        res, used = {}, {}
        for path, (x, P, memory) in state.items():
            with kernels.use_backend(path):
                xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
                links = LinkBatch.from_predicted(
                    ws.i, ws.j, ws.z, xp, Pp, ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2
                )
                links = adversary.attack(links, step, aim, memory)
                runs = dict(kernels_outvoted.OUTVOTED_RUNS)
                res[path] = correct(filt, xp, Pp, links, params, memory)
                passes = kernels_outvoted.OUTVOTED_RUNS["passes"] - runs["passes"]
            used[path] = _store(memory)[1][:, 1]
            assert passes == (path == "numba"), f"{path}: the compiled stage ran {passes} times"
            state[path] = (res[path][0], res[path][1], memory)
        assert_matches_reference(res["numba"], res["numpy"])
        _assert_same_store(state["numba"][2], state["numpy"][2])
        yield np.flatnonzero(used["numpy"] > 1.0)


@pytest.mark.parametrize(
    ("shield", "seed", "fooled", "changes", "steps"),
    [
        ("on", 4, 4.0, {}, 30),  # the defence's own sequence test (widened at steps 4-18)
        ("off", 4, 4.0, {}, 60),
        # one that fires sooner: its robots are widened from step 5 on, every step, so a
        # shorter run tests as much (the witness attacker's search is ~0.3 s a step)
        ("off", 7, 1.0, {"witness_k": 0.5, "witness_h": 3.0}, 30),
    ],
)
def test_compiled_outvoted_equals_the_reference_under_attack(shield, seed, fooled, changes, steps):
    params = _params(**changes)
    widenings = lockstep(make_filter("ckf"), params, steps, seed, shield, fooled)
    widened = sum(len(w) for w in widenings)
    assert widened > 0, "nobody widened: the case tests nothing"


def test_pending_keys_out_of_order_are_left_to_the_spec():
    """The pass finds each pending row's observer by a scan of the ascending keys: a store
    whose keys are not in order is refused (nothing written, the spec runs)."""
    rng = np.random.default_rng(3)
    params = CLParams(witness=True, outvoted=True, witness_liars=2.0)
    memories = (LinkMemory(ROBOTS), LinkMemory(ROBOTS))
    notes, links = _random_step(rng, np.zeros((ROBOTS, 2)), np.full(ROBOTS, 0.01))
    for memory in memories:
        reference_record(notes, memory)
    P = np.tile(np.eye(3) * 1e-4, (ROBOTS, 1, 1))
    _widen_both(params, memories, links, P)  # sorted: the pass runs (checked)
    for memory in memories:
        pending = memory.stage_statistic(PENDING)
        pending.keys, pending.values = pending.keys[::-1].copy(), pending.values[::-1].copy()
    before = dict(kernels_outvoted.OUTVOTED_RUNS)
    with kernels.use_backend("numba"):
        fast = widen_outvoted(params, memories[0], links, P)
    assert kernels_outvoted.OUTVOTED_RUNS["passes"] == before["passes"], "not refused"
    assert kernels_outvoted.OUTVOTED_RUNS["fallbacks"] == before["fallbacks"] + 1
    with kernels.use_backend("numpy"):
        ref = reference_widen(params, memories[1], links, P)
    np.testing.assert_array_equal(fast, ref)
    _assert_same_store(*memories)


def test_the_inputs_kept_per_memory_follow_its_store_and_params():
    """The glue keeps per memory the options, the output arrays and the stage store's
    arrays once checked (:class:`~resloc.cl.kernels_outvoted._Kept`): a store whose arrays
    are replaced (a checkpoint restored, a store written by the spec), a store the pass
    cannot write in place (strided values) and another ``params`` mid-run are each read
    afresh, equal to the spec's."""
    rng = np.random.default_rng(5)
    params = CLParams(witness=True, outvoted=True, witness_liars=2.0)
    offsets = np.zeros((ROBOTS, 2))
    offsets[:3] = rng.uniform(-0.04, 0.04, (3, 2))
    sd_p = rng.uniform(0.001, 0.02, ROBOTS)
    memories = (LinkMemory(ROBOTS), LinkMemory(ROBOTS))
    high = replace(params, witness_k=0.0, outvoted_cap=40.0)
    for k in range(60):
        notes, links = _random_step(rng, offsets, sd_p)
        for memory in memories:
            reference_record(notes, memory)
            state = memory.stage_statistic(OUTVOTED_STATE, width=2)
            if k in (20, 21) and len(state):  # new arrays: every test near its alarm
                values = state.values.copy()
                values[:, 0] = 2.0 * float(params.witness_h)
                values[:, 1] = 1.0
                state.keys, state.values = state.keys.copy(), values
            if k == 30 and len(state):  # strided values: the pass writes a copy
                wide = np.zeros((len(state), 4))
                wide[:, ::2] = state.values
                state.values = wide[:, ::2]
        P = np.tile(np.eye(3) * 1e-4, (ROBOTS, 1, 1))
        P[:, :2, :2] = np.eye(2) * sd_p[:, None, None] ** 2
        _widen_both(high if 40 <= k < 50 else params, memories, links, P)
