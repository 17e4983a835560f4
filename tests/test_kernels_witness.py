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

from lockstep_helpers import default_world, start_state, start_states
from resloc.cl import LinkBatch, LinkMemory, correct, kernels, kernels_witness, predict
from resloc.cl import kernels_rounds as rounds
from resloc.cl.backend import kernel_refusal
from resloc.cl.detection_witness import (
    STATE,
    WitnessNotes,
    reference_statistic,
    witness_state,
    witness_statistic,
)
from resloc.cl.detection_witness_frames import (
    PENDING,
    PENDING_WIDTH,
    delivered_store,
    put_store,
    record_witness,
    reference_delivered_store,
    reference_record,
)
from resloc.cl.detection_zone import inside_zone_map
from resloc.cl.params import CLParams, at_robots
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters import make_filter
from resloc.world.attackers import AttackStep, make_attacker
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
    """Every receiver's statistic on every robot, by the pair's key."""
    stat = memory.stage_statistic(STATE)
    return dict(zip(stat.keys.tolist(), stat.values.tolist(), strict=True))


def _pending(memory: LinkMemory):
    return memory.stage_statistic(PENDING, width=PENDING_WIDTH)


def lockstep(filt, params, steps: int, seed: int, attack: str = "lying notes", runs=None):
    """``steps`` steps through :data:`PATHS`; checks every step, yields the reference's
    outcome, memory and which rows come from a compromised robot. ``attack``: ``"lying
    notes"`` (the compromised robots' notes lie too: an adversary's notes hook), ``"honest
    notes"`` (their broadcasts lie, their notes are honest: no hook) or ``"none"`` (a
    clean run). ``runs``: a dict the compiled paths' :data:`WITNESS_RUNS` deltas are
    added to."""
    world = default_world(2, seed)
    N = world.n
    state = start_states(world, PATHS)
    adversary = make_attacker("compromised", robots=3, claimed_cov=0.01)
    runs = {} if runs is None else runs
    # the attackers aim at a threshold 4x the defence's: the stage convicts them
    fooled = replace(params, witness_h=4.0 * float(np.max(params.witness_h)))
    for k in range(steps):
        ws = world.step()
        step = AttackStep(k + 1, world.dt, ws.pose, ws.i, ws.j, ws.z, ws.attacked, N)
        if attack != "none":
            step = dataclasses.replace(step, attacked=adversary.mark(ws.attacked, step))
        res = {}
        for path, (x, P, memory) in state.items():
            with _path(path):
                xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
                links = LinkBatch.from_predicted(
                    ws.i, ws.j, ws.z, xp, Pp, ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2
                )
                if attack != "none":
                    links = adversary.attack(links, step, fooled, memory)
                if attack == "honest notes":
                    links.tamper.notes = None
                before = rounds.LOOP_RUNS.copy()
                counts = kernels_witness.WITNESS_RUNS.copy()
                res[path] = correct(filt, xp, Pp, links, params, memory)
                ran = rounds.LOOP_RUNS - before
                delta = {k: v - counts[k] for k, v in kernels_witness.WITNESS_RUNS.items()}
            if path != "numpy":
                assert ran == {path: 1}, f"expected the {path} loop, ran {dict(ran)}"
                took = delta["verdicts"]
                assert res[path][2].compiled and took == 1, "the compiled path did not run"
                # the step's one pass (kernels_witness_step), and with a notes hook the
                # compromised robots' oracle's passes inside the hook
                assert delta["steps"] == 1, "the witness step's pass did not run"
                assert delta["delivered"] >= 1, "the receivers' statistic was not compiled"
                for k, v in delta.items():
                    runs[k] = runs.get(k, 0) + v
            state[path] = (res[path][0], res[path][1], memory)
        assert_same_loops(res["rounds"], res["row_order"])
        assert_matches_reference(res["rounds"], res["numpy"])
        reference = _witness_states(state["numpy"][2])
        waiting = _pending(state["numpy"][2])
        for path in ("rounds", "row_order"):
            got = _witness_states(state[path][2])
            assert got.keys() == reference.keys()
            np.testing.assert_allclose(
                [got[r] for r in reference], list(reference.values()), rtol=0, atol=1e-9
            )
            # the notes waiting for the next frames (recorded in the pass, or by the spec)
            np.testing.assert_array_equal(_pending(state[path][2]).keys, waiting.keys)
            np.testing.assert_allclose(
                _pending(state[path][2]).values, waiting.values, rtol=1e-9, atol=1e-12
            )
        # the verdicts of the step: after the notes of the step before arrived
        h = at_robots(params.witness_h, ws.j)
        convicted = witness_state(state["numpy"][2], ws.i, ws.j) > h
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


@pytest.mark.parametrize("path", PATHS)
def test_a_jammed_link_gives_no_note(path):
    """An observer whose copy of j's estimate was jammed this step (the link's
    ``channel_ok`` false) writes no note on j (a robot's process could not): after a
    correction the notes waiting for the next frames are those of the received links
    only, on the numpy reference and on the compiled paths (whose step pass ran and
    recorded the notes itself: the links were all noted the step before)."""
    params = _params()
    world = default_world(1, 4)
    x, P, memory = start_state(world)
    filt = make_filter("ckf")
    for k in range(2):  # every link received, then every third link jammed
        ws = world.step()
        ok = ws.channel_ok & (np.arange(len(ws.i)) % 3 != 0 if k else True)
        with _path(path):
            xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
            links = LinkBatch.from_predicted(
                ws.i, ws.j, ws.z, xp, Pp, ok, ws.risk_s, ws.risk_c, ws.lambda2
            )
            before = kernels_witness.WITNESS_RUNS.copy()
            x, P, out = correct(filt, xp, Pp, links, params, memory)
            runs = {k: v - before[k] for k, v in kernels_witness.WITNESS_RUNS.items()}
    if path != "numpy":
        assert out.compiled and runs["steps"] == 1, "the compiled witness pass did not run"
        assert runs["records"] == 1, "the pass did not record the notes itself"
    waiting = _pending(memory)
    noted = waiting.keys[waiting.values[:, 10] > 0.0]
    zoned = inside_zone_map(xp[ws.i, :2], params.zone_trust_map)  # (their notes unsent)
    keys = ws.i * world.B + ws.j
    np.testing.assert_array_equal(np.sort(noted), np.sort(keys[ok & ~zoned]))
    assert (ok & ~zoned).sum() > 10 and (~ok & ~zoned).sum() > 5  # the case tests something


@pytest.mark.parametrize(("attack", "seed"), [("honest notes", 3), ("none", 5), ("none", 6)])
def test_the_step_pass_records_the_notes_as_the_reference(attack, seed):
    """Without an adversary's notes hook the step's pass (kernels_witness_step) also makes
    the notes and records them: the two compiled paths equal the numpy reference (outcome,
    every receiver's statistic, the pending notes) through a clean run and through
    compromised robots whose broadcasts the stage convicts, the notes recorded by the pass
    in most steps (a step with a new link: by the spec)."""
    params = _params()
    runs: dict = {}
    discarded = steps = 0
    for out, _memory, convicted in lockstep(make_filter("ckf"), params, 30, seed, attack, runs):
        discarded += int((out.detected & convicted).sum())
        steps += 1
    assert runs["steps"] == 2 * steps  # (two compiled paths)
    assert runs["records"] >= steps, f"the pass recorded the notes {runs['records']} times"
    if attack == "honest notes":
        assert discarded > 0, "the stage convicted nobody: the case tests nothing"


# ---------------------------------------------------------------------------------------
# The compiled notes and statistic against the numpy spec.
# ---------------------------------------------------------------------------------------
def _random_notes(rng, robots: int, per_robot, lie=0.0, spread=1.0) -> WitnessNotes:
    """Notes on robots 0..robots-1 (``per_robot[j]`` each, rows shuffled), honest noise
    plus a common ``lie`` on robot 0 and, with ``spread`` > 1, a few notes far off."""
    j = np.repeat(np.arange(robots), per_robot)
    E = len(j)
    i = rng.integers(robots, robots + 20, E)
    A = rng.normal(0.0, 0.01, (E, 2, 2))
    Q = A @ np.swapaxes(A, -1, -2) + 1e-5 * np.eye(2)
    B = rng.normal(0.0, 0.005, (E, 2, 2))
    P = B @ np.swapaxes(B, -1, -2) + 1e-6 * np.eye(2)
    u = np.einsum("eab,eb->ea", np.linalg.cholesky(Q), rng.normal(size=(E, 2)))
    u[j == 0] += lie
    far = rng.random(E) < 0.15
    u[far] *= spread
    order = rng.permutation(E)
    sent = rng.random(E) > 0.05
    return WitnessNotes(u[order], Q[order], P[order], i[order], j[order], sent[order])


def _both(notes, params, robots=None):
    with kernels.use_backend("numba"):
        before = kernels_witness.WITNESS_RUNS["statistics"]
        fast = witness_statistic(notes, params, robots)
        assert kernels_witness.WITNESS_RUNS["statistics"] == before + 1, "not compiled"
    ref = reference_statistic(notes, params, robots)
    np.testing.assert_array_equal(fast[0], ref[0])
    np.testing.assert_array_equal(fast[2], ref[2])
    np.testing.assert_allclose(fast[1], ref[1], rtol=1e-9, atol=1e-12)
    return ref


@pytest.mark.parametrize("liars", [0, 1, 2, 3, 4])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_compiled_statistic_equals_the_spec_on_random_notes(liars, seed):
    rng = np.random.default_rng(seed)
    params = CLParams(witness=True, witness_liars=float(liars), witness_h=30.0)
    counts = rng.integers(0, 14, 9)
    counts[:3] = (liars, liars + 1, 1)  # at most f notes, f + 1, a single note
    notes = _random_notes(rng, 9, counts, lie=0.03, spread=float(rng.choice([1.0, 30.0])))
    _, T, judged = _both(notes, params)
    assert judged.any() and (T[judged] > 0.0).all()
    _both(notes, params, robots=np.array([0, 4, 7]))


def test_the_compiled_statistic_equals_the_spec_on_adversarial_notes():
    rng = np.random.default_rng(9)
    params = CLParams(witness=True, witness_liars=2.0, witness_h=30.0)
    notes = _random_notes(rng, 4, np.array([8, 8, 5, 3]))
    u = notes.u.copy()
    on = [np.flatnonzero(notes.j == r) for r in range(4)]
    u[on[0]] = np.where(np.arange(len(on[0]))[:, None] % 2, 1.0, -1.0)  # no consistent set
    u[on[1][:2]] += 0.5  # two far liars (droppable)
    u[on[2]] = u[on[2][0]]  # equal notes (ties between sets)
    P = notes.P_pos.copy()
    P[on[3]] = P[on[3][0]]  # equal claimed traces (argmax ties)
    sent = np.ones(len(u), bool)
    adversarial = WitnessNotes(u, notes.Q, P, notes.i, notes.j, sent)
    ids, T, _ = _both(adversarial, params)
    half_h = 0.5 * params.witness_h
    assert T[list(ids).index(0)] == half_h  # the "no consistent set" rule
    # a per-robot f (per-robot arrays of the gains)
    per_robot = CLParams(witness=True, witness_liars=np.array([0.0, 1.0, 3.0, 2.0]))
    _both(adversarial, per_robot)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_chunked_enumeration_equals_the_spec_and_stops_exactly(seed):
    """The enumeration's sets judged SET_CHUNK at a time (kernels_witness_statistic._chunk): every
    group's smallest statistic equals the spec's over sizes whose levels span several
    chunks, with a nan note (the one-by-one path), and a stop at ``enough`` gives a value at
    most ``enough`` exactly when the spec's smallest is (else the smallest itself)."""
    from resloc.cl.detection_witness import consistency_gates, reference_groups
    from resloc.cl.kernels_witness_statistic import SET_CHUNK, group_statistics

    rng = np.random.default_rng(seed)
    params = CLParams(witness=True, witness_liars=3.0, witness_h=30.0)
    counts = np.array([4, 5, 6, 7, 9, 11, 13, 16])  # C(m, 2), C(m, 3): 1 to 35 chunks
    notes = _random_notes(rng, len(counts), counts, lie=0.02, spread=20.0)
    notes.sent[:] = True
    u = notes.u.copy()
    u[np.flatnonzero(notes.j == 3)[2]] = np.nan  # a nan note: no stop, nan propagates
    notes = WitnessNotes(u, notes.Q, notes.P_pos, notes.i, notes.j, notes.sent)
    rows = np.argsort(notes.j, kind="stable")
    ids, start, count = np.unique(notes.j[rows], return_index=True, return_counts=True)
    T_ref, judged_ref = reference_groups(notes, params, rows, start, count, ids)
    assert max(count) * (max(count) - 1) * (max(count) - 2) // 6 > 30 * SET_CHUNK
    G = len(ids)
    f = np.full(G, 3, np.int64)
    half_h = np.full(G, 0.5 * params.witness_h)
    gates = consistency_gates(params.witness_false_alarm, 16)
    args = (notes.u[rows], notes.Q[rows], notes.P_pos[rows], start, count, f, half_h, gates)
    with kernels.use_backend("numba"):
        for enough in (np.full(G, -np.inf), T_ref - 1e-6, T_ref + 1e-6, T_ref * 0.5 + 1.0):
            T, judged = np.zeros(G), np.zeros(G, np.bool_)
            group_statistics(*args, enough, T, judged)
            assert group_statistics.signatures, "not compiled"
            np.testing.assert_array_equal(judged, judged_ref)
            stops = judged & np.isfinite(T_ref) & (T_ref <= enough) & (ids != 3)
            assert (T[stops] <= enough[stops]).all()
            np.testing.assert_allclose(T[~stops], T_ref[~stops], rtol=1e-9, atol=1e-12)
        assert (T_ref[judged_ref] < half_h[judged_ref]).sum() >= 4  # real minima compared


def test_the_compiled_notes_and_cusum_equal_the_spec():
    from resloc.cl.detection_witness import witness_cusum, witness_notes
    from resloc.cl.kernels_witness_notes import fast_notes
    from resloc.cl.kernels_witness_statistic import cusum_of

    rng = np.random.default_rng(3)
    E = 50
    z = np.c_[rng.uniform(0.1, 3.0, E), rng.uniform(-np.pi, np.pi, E)]
    x_obs = np.c_[rng.normal(size=(E, 2)), rng.uniform(-np.pi, np.pi, E)]
    A = rng.normal(0.0, 0.05, (E, 3, 3))
    P_obs = A @ np.swapaxes(A, -1, -2) + 1e-6 * np.eye(3)
    x_nb = x_obs + np.c_[rng.normal(size=(E, 2)), np.zeros(E)]
    x_nb[0, :2] = x_obs[0, :2]  # a neighbour at the observer's position (r = 0)
    R = np.diag([0.01**2, 0.02**2])
    with kernels.use_backend("numba"):
        u, Q = fast_notes(z, x_obs, P_obs, x_nb, R)
    u0, Q0 = witness_notes(z, x_obs, P_obs, x_nb, R)
    np.testing.assert_allclose(u, u0, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(Q, Q0, rtol=1e-9, atol=1e-15)
    S = rng.uniform(0.0, 80.0, E)
    T = rng.exponential(10.0, E)
    judged = rng.random(E) < 0.7
    k, h = np.full(E, 4.0), np.full(E, 40.0)
    out = np.empty(E)
    cusum_of(S, T, judged, k, h, out)
    np.testing.assert_allclose(out, witness_cusum(S, T, judged, k, h), rtol=0, atol=1e-12)


def test_the_receivers_statistics_compiled_equal_the_spec():
    """Each receiver's groups (its own notes and the frames that got through) judged by the
    compiled twin and by the numpy spec: equal, and the jammed frames change them."""
    from resloc.cl.detection_witness import reference_groups, witness_cusum
    from resloc.cl.detection_witness_frames import received_groups, received_state
    from resloc.cl.memory import LinkStatistic

    rng = np.random.default_rng(11)
    params = CLParams(witness=True, witness_liars=2.0, witness_h=30.0)
    n = 12
    pairs = np.array([(a, b) for a in range(n) for b in range(n) if a != b])
    keep = rng.random(len(pairs)) < 0.8  # who observes whom
    i, j = pairs[keep].T
    E = len(i)
    A = rng.normal(0.0, 0.01, (E, 2, 2))
    Q = A @ np.swapaxes(A, -1, -2) + 1e-5 * np.eye(2)
    u = rng.normal(0.0, 0.01, (E, 2)) + np.where((j == 0)[:, None], 0.05, 0.0)
    P = np.tile(1e-5 * np.eye(2), (E, 1, 1))
    notes = WitnessNotes(u, Q, P, i, j, rng.random(E) > 0.05)
    state = LinkStatistic(n)
    low = rng.random(E) < 0.5  # half the pairs at 0 (their sets need no enumeration)
    state.set(i, j, np.where(low, 0.0, rng.uniform(0.0, 50.0, E)))
    results = []
    for ok in (np.ones(E, bool), rng.random(E) > 0.3):
        # the definition: every group's sets enumerated, then the CUSUM
        recv, on, rows, start, count = received_groups(notes, i, j, ok)
        T, judged = reference_groups(notes, params, rows, start, count, on)
        k, h = params.witness_k, params.witness_h
        plain = witness_cusum(state.get(recv, on), T, judged, k, h)
        with kernels.use_backend("numba"):
            before = kernels_witness.WITNESS_RUNS["statistics"]
            fast = received_state(notes, params, state, i, j, ok)
            assert kernels_witness.WITNESS_RUNS["statistics"] == before + 1, "not compiled"
        with kernels.use_backend("numpy"):
            ref = received_state(notes, params, state, i, j, ok)
        for a, b in zip(fast[:2], ref[:2], strict=True):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_allclose(fast[2], ref[2], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(ref[2], plain, rtol=1e-12, atol=1e-12)
        assert (plain == 0.0).sum() > 0.2 * len(plain)  # pairs the shortcut settles
        results.append(ref)
    assert len(results[0][0]) > len(np.unique(j))  # one group per receiver and robot
    assert not np.array_equal(results[0][2][: len(results[1][2])], results[1][2])


def _record_random_notes(rng, params, memory, n: int) -> None:
    """A step's notes of a team of ``n`` (most observers see most robots; robot 0 lied to
    by a common offset, a few notes far off) kept in ``memory`` for the next frames."""
    pairs = np.array([(a, b) for a in range(n) for b in range(n) if a != b])
    i, j = pairs[rng.random(len(pairs)) < 0.8].T
    E = len(i)
    A = rng.normal(0.0, 0.01, (E, 2, 2))
    Q = A @ np.swapaxes(A, -1, -2) + 1e-5 * np.eye(2)
    u = rng.normal(0.0, 0.01, (E, 2)) + np.where((j == 0)[:, None], 0.05, 0.0)
    u[rng.random(E) < 0.05] *= 30.0
    B = rng.normal(0.0, 0.003, (E, 2, 2))
    P = B @ np.swapaxes(B, -1, -2) + 1e-6 * np.eye(2)
    notes = WitnessNotes(u, Q, P, i, j, rng.random(E) > 0.05)
    record_witness(notes, params, memory)


@pytest.mark.parametrize("robots", [None, np.array([0, 3, 5])])
def test_the_delivered_statistic_compiled_equals_the_spec(robots):
    """The receivers' statistic after the frames (grouping, whole sets, skip rule, the
    enumeration of distinct sets, the CUSUM, the silent pairs' decay) by the compiled pass
    and by the numpy spec, over steps (duplicate links, jammed frames, a claim that is not
    a number): the same pairs, values to 1e-9, the same convictions."""
    rng = np.random.default_rng(5)
    params = CLParams(witness=True, witness_liars=2.0, witness_h=30.0, witness_k=4.0)
    n = 11
    memory = LinkMemory(n)
    enumerated = skipped = convicted = 0
    for step in range(8):
        _record_random_notes(rng, params, memory, n)
        if step == 5:  # a claim that is not a number: every set enumerated
            pending = memory.stage_statistic(PENDING, width=PENDING_WIDTH)
            pending.values[3, 6] = np.nan
        i, j = rng.integers(0, n, (2, 90))
        i, j = i[i != j], j[i != j]
        i, j = np.r_[i, i[:5]], np.r_[j, j[:5]]  # duplicate links
        ok = rng.random(len(i)) < 0.75
        with kernels.use_backend("numpy"):
            ref = reference_delivered_store(params, memory, i, j, ok, robots)
        runs = kernels_witness.WITNESS_RUNS.copy()
        with kernels.use_backend("numba"):
            fast = delivered_store(params, memory, i, j, ok, robots)
        assert kernels_witness.WITNESS_RUNS["delivered"] == runs["delivered"] + 1, "not compiled"
        enumerated += kernels_witness.WITNESS_RUNS["enumerated"] - runs["enumerated"]
        np.testing.assert_array_equal(fast.keys, ref.keys)
        np.testing.assert_allclose(fast.values, ref.values, rtol=1e-9, atol=1e-9)
        np.testing.assert_array_equal(fast.values > 30.0, ref.values > 30.0)
        skipped += int((ref.values == 0.0).sum())
        convicted += int((ref.values > 30.0).sum())
        if robots is not None:
            assert np.isin(ref.keys % n, robots).all()
        put_store(memory, ref)
    assert enumerated > 0 and skipped > 0 and convicted > 0, "the case tests nothing"


def test_the_notes_recorded_in_place_equal_the_spec():
    """The pending store after recording each step's notes, in place (compiled) and by the
    numpy spec: equal, the compiled record ran once every link was stored, and a step with
    a new link falls back to the spec (which inserts it)."""
    rng = np.random.default_rng(8)
    params = CLParams(witness=True)
    n = 9
    pairs = np.array([(a, b) for a in range(n) for b in range(n) if a != b])
    memories = {"fast": LinkMemory(n), "numpy": LinkMemory(n)}
    ran = []
    first = rng.random(len(pairs)) < 0.5
    more = first | (rng.random(len(pairs)) < 0.5)
    for step in range(6):
        i, j = pairs[first if step < 4 else more].T  # new links at step 4
        E = len(i)
        notes = WitnessNotes(
            rng.normal(size=(E, 2)),
            rng.normal(size=(E, 2, 2)),
            rng.normal(size=(E, 2, 2)),
            i,
            j,
            rng.random(E) < (1.0 if step in (0, 4) else 0.8),  # a link stored once sent
        )
        before = kernels_witness.WITNESS_RUNS["records"]
        with kernels.use_backend("numba"):
            record_witness(notes, params, memories["fast"])
        ran.append(kernels_witness.WITNESS_RUNS["records"] - before)
        reference_record(notes, memories["numpy"])
        fast, ref = (m.stage_statistic(PENDING, width=PENDING_WIDTH) for m in memories.values())
        np.testing.assert_array_equal(fast.keys, ref.keys)
        np.testing.assert_array_equal(fast.values, ref.values)
    assert ran == [0, 1, 1, 1, 0, 1], f"the compiled record ran {ran}"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_step_pass_equals_the_spec(seed):
    """The step's pass (kernels_witness_step: delivery, verdict, notes, record) against the
    numpy spec's functions called one by one (``deliver_witness``, ``witness_state``,
    ``step_notes``, ``reference_record``) over steps of a team of 10: robot 0 lies by a
    common offset (convicted), observers inside the zone-trust map (their notes not sent),
    a reading that is not a number, the claims per link or at neighbour rows, a new link
    (recorded by the spec)."""
    import copy

    from resloc.cl.detection_witness import step_notes
    from resloc.cl.detection_witness_frames import deliver_witness
    from resloc.cl.kernels_witness import WitnessInputs, witness_verdict

    rng = np.random.default_rng(seed)
    n = 10
    params = CLParams(
        witness=True,
        witness_liars=2.0,
        witness_h=30.0,
        zone_trust=True,
        zone_trust_map=((0.0, 0.0, 0.7),),
    )
    pairs = np.array([(a, b) for a in range(n) for b in range(n) if a != b])
    first = rng.random(len(pairs)) < 0.8
    # a fifth of the links jammed, two patterns in turn (a link noted at one step is
    # jammed at the next: the pass must not record it)
    jam = rng.random((2, len(pairs))) < 0.2
    jam[1] &= ~jam[0]  # (disjoint: every link is noted by step 2)
    memory = LinkMemory(n)
    counted = {"in pass": 0, "zoned": 0, "convicted": 0, "unsent": 0, "jammed": 0}
    for step in range(7):
        i, j = pairs[first | (step == 5)].T  # new links at step 5
        ok = ~jam[step % 2][first | (step == 5)]
        E = len(i)
        pos = rng.uniform(-2.0, 2.0, (n, 2))
        x = np.c_[pos + rng.normal(0.0, 0.02, (n, 2)), rng.uniform(-np.pi, np.pi, n)]
        A = rng.normal(0.0, 0.03, (n, 3, 3))
        P = A @ np.swapaxes(A, -1, -2) + 1e-4 * np.eye(3)
        rel = pos[j] - pos[i]
        z = np.c_[np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0]) - x[i, 2]]
        z += rng.normal(0.0, 0.01, (E, 2))
        if step == 3:
            z[4, 0] = np.nan  # (its note is not sent)
        x_nb = x.copy()
        x_nb[0, :2] += 0.3  # robot 0's broadcast lies
        risk = np.zeros(n)
        links = LinkBatch.from_predicted(i, j, z, x_nb, P, ok, risk, risk, risk)
        if step % 2:  # the claims per link (read: no neighbour rows)
            links = replace(links, P_nb=P[j].copy(), x_nb=x_nb[j].copy())
        spec = copy.deepcopy(memory)
        before = kernels_witness.WITNESS_RUNS.copy()
        with kernels.use_backend("numba"):
            verdict = witness_verdict(params, memory, x, P, links, WitnessInputs.of(links))
            verdict.record(params, memory)
        after = kernels_witness.WITNESS_RUNS
        assert after["steps"] == before["steps"] + 1, "the step's pass did not run"
        counted["in pass"] += after["records"] - before["records"]
        with kernels.use_backend("numpy"):
            deliver_witness(params, spec, links)
            discard = witness_state(spec, i, j) > params.witness_h
            notes = step_notes(z, x[i], P[i], x_nb[j], P[j], i, j, params, ok)
            reference_record(notes, spec)
        np.testing.assert_array_equal(verdict.discard, discard)
        for name, width in ((STATE, None), (PENDING, PENDING_WIDTH)):
            got, ref = memory.stage_statistic(name, width), spec.stage_statistic(name, width)
            np.testing.assert_array_equal(got.keys, ref.keys)
            np.testing.assert_allclose(got.values, ref.values, rtol=1e-9, atol=1e-12)
        counted["zoned"] += int((np.hypot(x[i, 0], x[i, 1]) < 0.7).sum())
        counted["unsent"] += int((~notes.sent).sum())
        counted["jammed"] += int((~ok).sum())
        counted["convicted"] += int(discard.sum())
    # (steps 0, 1 and 5: the spec inserts; a link first noted later, its observer inside
    # the map or its frame jammed before, too)
    assert counted["in pass"] >= 3, counted
    assert min(counted.values()) > 0, f"the case tests nothing: {counted}"


@pytest.mark.parametrize(
    "chain",
    [
        "zone+full+redundancy+sequence+cap+landmarks+witness",
        "zone+full+redundancy+sequence+cap+landmarks+witness+outvoted+startup-decay+lockout",
    ],
)
@pytest.mark.parametrize("by_index", [False, True])
def test_the_witness_chains_run_the_one_pass_prepass_as_the_reference(chain, by_index):
    """With the witness stage on (no tamper hook) the claims, zone's readings and the
    pre-passes run in one compiled call (kernels_prepass) on every compiled step: the
    corrections, decisions and every stage's state equal the numpy reference's; the
    neighbours' broadcasts per link or by index (the simulator's form, which the witness
    pass reads without gathering them on the batch)."""
    from test_kernels_prepass import _steps
    from test_kernels_zone import _params as chain_params

    params = chain_params(chain)
    original = LinkBatch.__init__

    def by_rows(self, i, j, z, x_nb, P_nb, *rest, **extras):
        # the links as the simulator makes them (LinkBatch.from_predicted): the test's
        # per-link copies made rows of the batch's estimates, read by index
        original(self, i, j, z, x_nb, P_nb, *rest, **extras)
        if self.neighbours is None:
            from resloc.cl.links import NeighbourStates

            B = int(max(np.max(i), np.max(j))) + 1
            xs, Ps = np.zeros((B, 3)), np.tile(np.eye(3), (B, 1, 1))
            xs[j], Ps[j] = x_nb, P_nb
            self.__dict__["_x_nb"] = self.__dict__["_P_nb"] = None
            self.neighbours = NeighbourStates(np.asarray(j), xs, Ps)

    steps = kernels_witness.WITNESS_RUNS["steps"]
    if by_index:
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(LinkBatch, "__init__", by_rows)
            runs = [n for n, _ in _steps(params, 12, 5)]
    else:
        runs = [n for n, _ in _steps(params, 12, 5)]
    assert runs == [1] * 12, "the one-pass call did not run on every step"
    assert kernels_witness.WITNESS_RUNS["steps"] - steps == 12, "the step's pass did not run"
