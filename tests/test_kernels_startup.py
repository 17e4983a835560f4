"""The start-up floor on the compiled path (:mod:`resloc.cl.kernels_startup`) and its end.

Against its numpy spec (:func:`~resloc.cl.detection_startup.reference_floor`), with the
schedules of the two named defences that use it (a constant floor dropped after 10
corrections; 5 then a decay by 0.8): synthetic covariances and observers, and the default
scenario (two trials batched, 34 robots) against three compromised robots. Every step the
covariances handed to the correction, the robots raised and the stage's store (counts and
factors, what the attacker reads) must agree to 1e-9, the compiled pass having run, through
the constant window, the decay and past the end. Past the end the stage is over
(:func:`~resloc.cl.detection_startup.floor_over`): skipping it must change neither the
covariances nor the factors the attacker reads, and a robot not seen yet keeps its floor.
"""

from __future__ import annotations

import copy
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from lockstep_helpers import default_world, start_states
from resloc.cl import LinkBatch, LinkMemory, correct, kernels, kernels_startup, predict
from resloc.cl.detection_startup import (
    STARTUP_STATE,
    applied_startup_factors,
    claims_floored,
    floor_over,
    reference_floor,
    startup_floor,
    startup_floor_schedule,
)
from resloc.cl.params import CLParams
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters import make_filter
from resloc.world.attackers import AttackStep, make_attacker
from test_kernels_reciprocal import assert_matches_reference

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

CHAIN = "zone+full+redundancy+sequence+cap+landmarks+witness+outvoted"
DEFENCE_NAMES = (f"{CHAIN}+startup", f"{CHAIN}+startup-decay")


def _defence_params(name: str) -> CLParams:
    return default_scenario().replace(**DEFENCES[name]).cl_params()


def _store(memory: LinkMemory) -> tuple[np.ndarray, np.ndarray]:
    state = memory.stage_statistic(STARTUP_STATE, width=2)
    return state.keys.copy(), state.values.copy()


def _assert_same_store(fast: LinkMemory, ref: LinkMemory) -> None:
    (kf, vf), (kr, vr) = _store(fast), _store(ref)
    np.testing.assert_array_equal(kf, kr)
    np.testing.assert_array_equal(vf[:, 0], vr[:, 0])  # the counts, exactly
    np.testing.assert_allclose(vf[:, 1], vr[:, 1], rtol=1e-9, atol=0.0)
    np.testing.assert_array_equal(vf[:, 1] > 1.0, vr[:, 1] > 1.0)  # the same robots raised


def _phase(params: CLParams, counts: np.ndarray) -> set:
    """The phases of the schedule the stored counts (corrections before the next) are in."""
    floor = startup_floor_schedule(params, counts)
    phases = set()
    phases |= {"constant"} if (counts < params.startup_steps).any() else set()
    phases |= {"decay"} if ((counts >= params.startup_steps) & (floor > 0.0)).any() else set()
    phases |= {"ended"} if (floor == 0.0).any() else set()
    return phases


def _floor_both(params, memories, links, P):
    """The stage by the compiled pass (checked to have run, or to have found the stage over)
    and by the numpy backend, each on its own memory; returns the spec's covariances and
    what the compiled side did, after checking the two agree."""
    before = dict(kernels_startup.STARTUP_RUNS)
    with kernels.use_backend("numba"):
        fast = startup_floor(params, memories[0], links, P)
    runs = {k: kernels_startup.STARTUP_RUNS[k] - before[k] for k in before}
    with kernels.use_backend("numpy"):
        ref = startup_floor(params, memories[1], links, P)
    assert (fast is P) == (ref is P)  # the same decision: someone raised or nobody
    np.testing.assert_allclose(fast, ref, rtol=1e-9, atol=0.0)
    _assert_same_store(*memories)
    B = len(P)
    np.testing.assert_allclose(
        applied_startup_factors(memories[0], B), applied_startup_factors(memories[1], B), 1e-9
    )
    return ref, runs


ROBOTS = 9


def _random_step(rng, sd):
    """Some of the ordered pairs as links (so a robot is not an observer at every step) and
    covariances around ``sd`` (m), one robot far wider than any floor."""
    i, j = (a.ravel() for a in np.meshgrid(np.arange(ROBOTS), np.arange(ROBOTS), indexing="ij"))
    keep = (i != j) & (rng.random(i.shape) < 0.4)
    links = SimpleNamespace(i=i[keep], j=j[keep])
    s = sd * rng.uniform(0.5, 2.0, (ROBOTS, 2))
    s[ROBOTS - 1] = 0.05  # 50 mm: never raised
    P = np.tile(np.eye(3) * 1e-4, (ROBOTS, 1, 1))
    P[:, 0, 0], P[:, 1, 1] = s[:, 0] ** 2, s[:, 1] ** 2
    P[:, 0, 1] = P[:, 1, 0] = 0.3 * s[:, 0] * s[:, 1]
    return links, P


@pytest.mark.parametrize("name", DEFENCE_NAMES)
@pytest.mark.parametrize("seed", [0, 1])
def test_the_compiled_stage_equals_the_spec_through_every_phase(name, seed):
    rng = np.random.default_rng(seed)
    params = _defence_params(name)
    memories = (LinkMemory(ROBOTS), LinkMemory(ROBOTS))
    phases, raised, passes, over = set(), 0, 0, 0
    for _ in range(120):
        links, P = _random_step(rng, 0.002)
        out, runs = _floor_both(params, memories, links, P)
        phases |= _phase(params, _store(memories[1])[1][:, 0])
        raised += int((out[:, 0, 0] > P[:, 0, 0]).sum())
        passes += runs["passes"]
        over += runs["over"]
        assert runs["fallbacks"] <= 1  # only a step with an observer never stored
    assert phases == {"constant", "decay", "ended"} - ({"decay"} if "decay" not in name else set())
    assert raised >= 20, "nobody raised: the case tests nothing"
    assert passes >= params.startup_steps - 1, "the compiled pass hardly ran"
    assert over == 1  # found over once, then skipped without a call
    assert floor_over(params, memories[0].stage_statistic(STARTUP_STATE, width=2))


def lockstep(filt, params, steps: int, seed: int):
    """``steps`` steps of the default scenario by the compiled path and the numpy
    reference, each with its own estimates, memory and attacker's view; checks every step
    and yields the compiled stage's runs of the step and the reference's store."""
    world = default_world(2, seed)
    N = world.n
    state = start_states(world, ("numba", "numpy"))
    adversary = make_attacker("compromised", robots=3, claimed_cov=0.01)
    for k in range(steps):
        ws = world.step()
        step = AttackStep(k + 1, world.dt, ws.pose, ws.i, ws.j, ws.z, ws.attacked, N)
        step = dataclasses.replace(step, attacked=adversary.mark(ws.attacked, step))
        res = {}
        for path, (x, P, memory) in state.items():
            with kernels.use_backend(path):
                xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
                links = LinkBatch.from_predicted(
                    ws.i, ws.j, ws.z, xp, Pp, ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2
                )
                links = adversary.attack(links, step, params, memory)
                before = dict(kernels_startup.STARTUP_RUNS)
                res[path] = correct(filt, xp, Pp, links, params, memory)
                runs = {k: kernels_startup.STARTUP_RUNS[k] - before[k] for k in before}
            if path == "numpy":
                assert not any(runs.values()), "the numpy backend ran the compiled stage"
            else:
                fast_runs = runs
            state[path] = (res[path][0], res[path][1], memory)
        assert_matches_reference(res["numba"], res["numpy"])
        _assert_same_store(state["numba"][2], state["numpy"][2])
        yield fast_runs, _store(state["numpy"][2])[1]


@pytest.mark.parametrize("name", DEFENCE_NAMES)
def test_compiled_startup_equals_the_reference_in_the_scenario(name):
    params = _defence_params(name)
    phases, raised, passes, over = set(), 0, 0, 0
    for k, (runs, values) in enumerate(lockstep(make_filter("ckf"), params, 34, seed=4)):
        phases |= _phase(params, values[:, 0])
        raised += int((values[:, 1] > 1.0).sum())
        passes += runs["passes"]
        over += runs["over"]
        assert runs["fallbacks"] == (k == 0)  # the first step inserts (the spec)
    expected = {"constant", "ended"} | ({"decay"} if "decay" in name else set())
    assert phases == expected
    assert raised > 0, "nobody raised: the case tests nothing"
    assert passes >= 9 and over == 1  # compiled every step until over, then skipped


def test_skipping_the_ended_stage_changes_nothing_the_step_or_the_attacker_reads():
    """Beside a memory where the spec runs every step (never skipped), the stage skipped
    once over gives the same covariances and factors; only the counts stop. The robots'
    covariances (0.05-0.2 mm) are below the decaying floor's last values: a robot is raised
    at its last correction with a floor, and its factor must still fall back to 1."""
    params = _defence_params(DEFENCE_NAMES[1])
    rng = np.random.default_rng(3)
    skipped = 0
    for backend in ("numba", "numpy"):
        skipping, every = LinkMemory(ROBOTS), LinkMemory(ROBOTS)
        every_state = every.stage_statistic(STARTUP_STATE, width=2)
        for _ in range(80):
            links, P = _random_step(rng, 0.0001)
            with kernels.use_backend(backend):
                used = startup_floor(params, skipping, links, P)
            full = reference_floor(params, every_state, links, P)
            assert (used is P) == (full is P)
            np.testing.assert_allclose(used, full, rtol=1e-12, atol=0.0)
            np.testing.assert_allclose(
                applied_startup_factors(skipping, ROBOTS),
                applied_startup_factors(every, ROBOTS),
                rtol=1e-12,  # the compiled pass's pow (C's) and numpy's differ by an ulp
                atol=0.0,
            )
        counts = _store(skipping)[1][:, 0]
        skipped += int((counts < _store(every)[1][:, 0]).any())
    assert skipped == 2, "the stage never ended: the case tests nothing"


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_a_robot_not_seen_yet_keeps_its_floor_after_the_others_end(backend):
    """The stage is over only when every robot id has been through its floor: robot 3
    observes for the first time after robots 0-2 ended theirs, and is raised."""
    params = CLParams(startup_steps=3, startup_floor_std=0.01)
    memory = LinkMemory(4)
    P = np.tile(np.eye(3) * 0.002**2, (4, 1, 1))
    early = SimpleNamespace(i=np.array([0, 1, 2]), j=np.array([1, 2, 0]))
    with kernels.use_backend(backend):
        for _ in range(6):
            assert (startup_floor(params, memory, early, P) is P) == (_ >= 3)
        late = SimpleNamespace(i=np.array([0, 3]), j=np.array([3, 0]))
        used = startup_floor(params, memory, late, P)
    assert used[3, 0, 0] == pytest.approx(0.01**2)  # (10 mm)^2: raised
    assert (used[:3] == P[:3]).all()
    assert applied_startup_factors(memory, 4) == pytest.approx([1.0, 1.0, 1.0, 25.0])


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_the_over_record_is_read_with_the_params_of_the_step(backend):
    """The stage found over is kept per memory with the ``params`` it was found under: the
    same schedule in another ``params`` object still skips (no pass), a longer one raises
    the robots again, as the spec does on that store."""
    params = CLParams(startup_steps=3, startup_floor_std=0.01)
    memory = LinkMemory(3)
    P = np.tile(np.eye(3) * 0.002**2, (3, 1, 1))
    links = SimpleNamespace(i=np.array([0, 1, 2]), j=np.array([1, 2, 0]))
    with kernels.use_backend(backend):
        for _ in range(5):
            startup_floor(params, memory, links, P)
        assert not claims_floored(dataclasses.replace(params, startup_claims=True), memory)
        before = dict(kernels_startup.STARTUP_RUNS)
        same = dataclasses.replace(params, lockout_share=0.5)  # another object, same schedule
        assert startup_floor(same, memory, links, P) is P
        assert kernels_startup.STARTUP_RUNS == before, "an ended stage ran again"
        longer = dataclasses.replace(params, startup_steps=8)
        state = memory.stage_statistic(STARTUP_STATE, width=2)
        spec = reference_floor(longer, copy.deepcopy(state), links, P)
        used = startup_floor(longer, memory, links, P)
    assert used[:, 0, 0] == pytest.approx([0.01**2] * 3)  # (10 mm)^2: raised again
    np.testing.assert_allclose(used, spec, rtol=1e-12, atol=0.0)
