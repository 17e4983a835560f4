"""The compiled reciprocal range check (:mod:`resloc.cl.kernels_reciprocal`).

Each case runs the default scenario (two trials batched, 34 robots) under an attack through
four paths in lockstep, each with its own estimates, memory and attacker's view: the rounds,
the row-order loop, the numpy reference, and a run that switches between the compiled path
and the reference every few steps (the check's state is the same store in both). At every
step the compiled paths must have run, and all agree to 1e-9 with identical decisions and
the same reciprocal state. The attacks: the two-ended attacker on robot 5 (both readings of
its pairs falsified together, its oracle reading the victims' memory) or a compromised robot
whose broadcast lies and whose own readings are reported moved to match (the hook's
``reported`` partner readings), each with a one-ended liar beside it (robot 9's readings
of its neighbours lengthened 2 cm, ~2.8 sigma of ``d``: under the one-step gate, caught by
the sum). A short hold makes the held links come back within the run; the test asserts that links
were held and re-admitted.

The map's blame rule (``zone_trust_map`` without zone trust: a pair with one end inside the
map is not judged) has its case here; the check beside zone trust itself (whose withheld and
substituted rows keep no state) is run in lockstep through the zone crossing in
``tests/test_kernels_zone.py``."""

from __future__ import annotations

import dataclasses
from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world, start_states
from resloc.angles import wrap_angle
from resloc.cl import LinkBatch, LinkMemory, correct, kernels, predict
from resloc.cl import kernels_rounds as rounds
from resloc.cl.backend import kernel_refusal
from resloc.cl.detection_reciprocal import STATE_WIDTH, ReciprocalCheck, reciprocal_evidence
from resloc.cl.detection_zone import inside_zone_map, reciprocal_rows
from resloc.cl.kernels_detection import detector_state
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters import make_filter
from resloc.world.attackers import AttackStep, make_attacker
from test_kernels_redundancy import links_of_one_step
from test_kernels_round_options import _path
from test_kernels_rounds import assert_same_loops

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

FILTERS = {"ckf": make_filter("ckf"), "ukf": make_filter("ukf", 0.8, 2.0, 1.0)}
NAME = ReciprocalCheck.name
#: The one-ended liar (robot id in its team): its readings lengthened by BIAS (m).
ONE_ENDED, BIAS = 9, 0.02


def _params(defence: str, **changes):
    return replace(default_scenario().replace(**DEFENCES[defence]).cl_params(), **changes)


#: A disc over the middle of the default team (the scenario's danger zone is beside it).
MIDDLE = (-0.8, -0.9, 0.2)


def _mapped(defence: str, **changes):
    """``defence`` with the default scenario's zone map and :data:`MIDDLE` but zone trust
    off: only the reciprocal check's blame rule reads the map."""
    mapped = _params("zone+full+redundancy+sequence+reciprocal")
    assert mapped.zone_trust_map
    return _params(defence, zone_trust_map=(*mapped.zone_trust_map, MIDDLE), **changes)


#: name -> (filter, CLParams, attacker)
CASES = {
    "two-ended": ("ckf", _params("full+reciprocal", reciprocal_hold=6.0), "two_ended"),
    "two-ended-ukf-redundancy": (
        "ukf",
        _params("full+redundancy+sequence+reciprocal", reciprocal_hold=6.0),
        "two_ended",
    ),
    "compromised-reported": (
        "ckf",
        _params("full+redundancy+sequence+reciprocal", reciprocal_hold=6.0),
        "compromised",
    ),
    "two-ended-map": ("ckf", _mapped("full+reciprocal", reciprocal_hold=6.0), "two_ended"),
    # the check beside the gate alone: no other option's stage is on, so the loops must
    # still run their options' form (kernels_rounds.beyond_paper) or lose its verdicts
    "gate-reciprocal": (
        "ckf",
        replace(
            default_scenario()
            .replace(**{"detector.enabled": True, "detector.norm": "nis"})
            .cl_params(),
            reciprocal=True,
            reciprocal_hold=6.0,
        ),
        "two_ended",
    ),
}
#: Steps of each case: at their seeds the check holds a link from step 1 or 2 and re-admits
#: one by step 8, and the one-ended liar is caught from the first steps (the attackers, full
#: knowledge, search their lies through the numpy stages: up to ~0.35 s a step), so 30
#: steps see each several times and the switching path switch four times.
STEPS = 30


def _attacker(kind: str):
    if kind == "two_ended":
        return make_attacker("two_ended", size=0.5, target=5)
    return make_attacker("compromised", robots=1, claimed_cov=0.01)


def _with_one_ended_liar(links: LinkBatch, liar: np.ndarray) -> LinkBatch:
    """``links`` whose (Python) tamper hook also lengthens the rows ``liar`` by BIAS."""
    inner = links.tamper

    def tamper(rows, z_hat, S):
        out = links.z[rows].copy() if inner is None else inner(rows, z_hat, S)
        out[liar[rows], 0] += BIAS
        return out

    if inner is not None and hasattr(inner, "reported"):
        tamper.reported = inner.reported
    return dataclasses.replace(links, tamper=tamper)


def _store(memory: LinkMemory):
    return memory.stage_statistic(NAME, width=STATE_WIDTH)


def assert_same_reciprocal_state(a: LinkMemory, b: LinkMemory) -> None:
    """The same reciprocal state for every link either memory holds (a link the kernel
    inserted reads as the reference's 0)."""
    sa, sb = _store(a), _store(b)
    keys = np.union1d(sa.keys, sb.keys)
    i, j = keys // sa.n_nodes, keys % sa.n_nodes
    np.testing.assert_allclose(sa.get(i, j), sb.get(i, j), rtol=0, atol=1e-9)


def assert_matches_reference(fast, ref, tol: float = 1e-9) -> None:
    """The compiled correction ``fast`` equals the reference's ``ref`` to ``tol``
    (estimates, covariances, norms and thresholds: after tens of steps the estimates of the
    two paths differ by rounding, ~1e-12, and so do the norms) with identical decisions."""
    (xf, Pf, of), (xr, Pr, orf) = fast, ref
    assert of.compiled and not orf.compiled, "compared the wrong paths"
    d = xf - xr
    d[:, 2] = wrap_angle(d[:, 2])
    assert np.abs(d).max() <= tol
    assert np.abs(Pf - Pr).max() <= tol
    for name in ("norm", "threshold"):
        np.testing.assert_allclose(
            getattr(of, name), getattr(orf, name), rtol=tol, atol=tol, equal_nan=True
        )
    for name in ("detected", "triggered", "delivered", "fused", "repaired"):
        np.testing.assert_array_equal(getattr(of, name), getattr(orf, name), err_msg=name)


PATHS = ("rounds", "row_order", "numpy", "switching")


def lockstep(filt, params, steps: int, seed: int, kind: str):
    """``steps`` steps of the default scenario through :data:`PATHS` under the attack
    ``kind``; checks every step and yields the reference's outcome and memory and the
    one-ended liar's rows."""
    world = default_world(2, seed)
    N = world.n
    state = start_states(world, PATHS)
    adversary = _attacker(kind)
    for k in range(steps):
        ws = world.step()
        step = AttackStep(k + 1, world.dt, ws.pose, ws.i, ws.j, ws.z, ws.attacked, N)
        step = dataclasses.replace(step, attacked=adversary.mark(ws.attacked, step))
        liar = ws.i % N == ONE_ENDED
        res = {}
        for path, (x, P, memory) in state.items():
            run = path
            if path == "switching":  # 7 steps compiled, 7 steps numpy, ...
                run = "rounds" if (k // 7) % 2 == 0 else "numpy"
            with _path(run):
                xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
                links = LinkBatch.from_predicted(
                    ws.i, ws.j, ws.z, xp, Pp, ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2
                )
                links = _with_one_ended_liar(adversary.attack(links, step, params, memory), liar)
                before = rounds.LOOP_RUNS.copy()
                res[path] = correct(filt, xp, Pp, links, params, memory)
                ran = rounds.LOOP_RUNS - before
            if run != "numpy":
                assert ran == {run: 1}, f"expected the {run} loop, ran {dict(ran)}"
                assert res[path][2].compiled, "the compiled path did not run"
            state[path] = (res[path][0], res[path][1], memory)
        assert_same_loops(res["rounds"], res["row_order"])
        assert_matches_reference(res["rounds"], res["numpy"])
        for got, want in zip(res["switching"][:2], res["numpy"][:2], strict=True):
            assert np.abs(got - want).max() <= 1e-9
        np.testing.assert_array_equal(res["switching"][2].detected, res["numpy"][2].detected)
        memories = {path: s[2] for path, s in state.items()}
        for path in ("rounds", "row_order", "switching"):
            assert_same_reciprocal_state(memories[path], memories["numpy"])
        # pairs the map leaves alone (one end's estimate inside it, at the prediction)
        inside = inside_zone_map(xp[:, :2], params.zone_trust_map)
        yield res["numpy"][2], memories["numpy"], liar, int((inside[ws.i] != inside[ws.j]).sum())


@pytest.mark.parametrize("case", list(CASES))
def test_compiled_reciprocal_check_equals_the_reference(case: str) -> None:
    name, params, kind = CASES[case]
    links = links_of_one_step()
    assert kernel_refusal(FILTERS[name], params, links) is None
    tampered = dataclasses.replace(links, tamper=lambda rows, z_hat, S: links.z[rows])
    assert kernel_refusal(FILTERS[name], params, tampered) is None  # a Python hook too
    detected = fused = 0
    liar_detected = liar_rows = 0
    ever_held = released = False
    holds: dict[int, float] = {}
    left_to_map = 0
    for out, memory, liar, straddling in lockstep(
        FILTERS[name], params, STEPS, 41 + list(CASES).index(case), kind
    ):
        detected += int(out.detected.sum())
        fused += int(out.fused.sum())
        liar_detected += int(out.detected[liar].sum())
        liar_rows += int(liar.sum())
        left_to_map += straddling
        store = _store(memory)
        now = dict(zip(store.keys.tolist(), store.values[:, 2].tolist(), strict=True))
        ever_held |= any(h > 0 for h in now.values())
        released |= any(h == 1.0 and now.get(key, 0.0) == 0.0 for key, h in holds.items())
        holds = now
    assert fused > 0 and detected > 0
    assert ever_held, "the check never held a link out"
    assert released, "no held link was re-admitted"
    if params.zone_trust_map:
        assert left_to_map > 0, "no pair was left to the map"
    assert liar_detected > 0.2 * liar_rows, "the check did not catch the one-ended liar"


def _step_with_one_ended_liars():
    """One step of the default world (seed 8): ``(world, x, li, lj, z)``, every fifth
    reading lengthened past the reciprocal check's one-step gate."""
    links = links_of_one_step(8)
    world = default_world(1, 8)
    x, _ = world.initial_estimates()
    li, lj = links.i.astype(np.int64), links.j.astype(np.int64)
    z = links.z.copy()
    z[::5, 0] += 0.05  # over the one-step gate
    return world, x, li, lj, z


def test_the_pre_pass_equals_reciprocal_evidence_with_and_without_a_map() -> None:
    """The verdict and state of :func:`~resloc.cl.kernels_reciprocal.reciprocal_verdict`
    are the numpy stage's on a step with one-ended liars (over the gate, under it, and
    held links), with the map's blame rule and without; the map changes the verdict."""
    from resloc.cl.kernels_reciprocal import reciprocal_verdict

    world, x, li, lj, z = _step_with_one_ended_liars()
    z[1::7, 0] += 0.015  # under the one-step gate
    partner = z[reciprocal_rows(li, lj)]
    partner[reciprocal_rows(li, lj) < 0] = np.nan
    x_nb = x[lj]
    nb = np.arange(len(li), dtype=np.int64)
    verdicts = []
    for params in (_params("full+reciprocal"), _mapped("full+reciprocal")):
        ref_memory, memory = LinkMemory(world.B), LinkMemory(world.B)
        held = np.zeros((len(li), STATE_WIDTH))
        held[3::11] = [0.01, 1e-4, 2.0]  # links on hold, and a sum near its gate
        held[4::11] = [0.05, 1e-4, 0.0]
        _store(ref_memory).set(li, lj, held)
        _store(memory).set(li, lj, held)
        ev = reciprocal_evidence(z, partner, li, lj, params, ref_memory, x[li], x_nb)
        detection = detector_state(params, memory, li, lj).kernel
        verdict = reciprocal_verdict(params, memory, li, lj, z, partner, x, x_nb, nb, detection)
        np.testing.assert_array_equal(verdict.discard, ev["reciprocal_discard"])
        state = _store(memory).get(li, lj)
        np.testing.assert_allclose(state, ev["reciprocal_state"], rtol=0, atol=1e-15)
        verdicts.append(verdict.discard)
        verdict.undo()
        # the transmitted estimates read by index (the simulator's form: each robot's
        # place in the map tested once for all its rows)
        by_index = reciprocal_verdict(params, memory, li, lj, z, partner, x, x, lj, detection)
        np.testing.assert_array_equal(by_index.discard, ev["reciprocal_discard"])
        by_index.undo()
        np.testing.assert_array_equal(_store(memory).get(li, lj), held)
        # the partner readings found in the batch (none given): the same verdict
        found = reciprocal_verdict(params, memory, li, lj, z, None, x, x_nb, nb, detection)
        np.testing.assert_array_equal(found.discard, ev["reciprocal_discard"])
        np.testing.assert_allclose(
            _store(memory).get(li, lj), ev["reciprocal_state"], rtol=0, atol=1e-15
        )
        found.undo()
        # each observer's neighbours descending (the scan instead of the binary search)
        o = np.lexsort((-lj, li))
        ev = reciprocal_evidence(
            z[o], partner[o], li[o], lj[o], params, ref_memory, x[li[o]], x_nb[o]
        )
        detection = detector_state(params, memory, li[o], lj[o]).kernel
        found = reciprocal_verdict(
            params, memory, li[o], lj[o], z[o], None, x, x_nb[o], nb, detection
        )
        np.testing.assert_array_equal(found.discard, ev["reciprocal_discard"])
        found.undo()
    unsorted = np.r_[1 : len(li), 0]
    assert (
        reciprocal_verdict(
            params, memory, li[unsorted], lj[unsorted], z, None, x, x_nb, nb, detection
        )
        is None
    )
    assert verdicts[0].any() and not verdicts[0].all()
    inside = inside_zone_map(x[li, :2], _mapped("full+reciprocal").zone_trust_map)
    assert (inside != inside_zone_map(x_nb[:, :2], _mapped("full+reciprocal").zone_trust_map)).any()
    assert not np.array_equal(verdicts[0], verdicts[1]), "the map changed nothing"


def test_zone_trust_with_the_check_runs_compiled() -> None:
    params = replace(_params("zone+full+redundancy+sequence+reciprocal"))
    assert kernel_refusal(FILTERS["ckf"], params, links_of_one_step()) is None


def test_partner_rows_are_the_reference_rows() -> None:
    """``kernels_reciprocal.partner_rows`` (the reverse link's row: a table of every pair
    for a team's ids, else a binary search in the partner's rows, or a scan where an
    observer's neighbours do not ascend) is ``reciprocal_rows``, with reverses missing;
    rows not sorted by observer are refused."""
    from resloc.cl.kernels_reciprocal import partner_rows

    links = links_of_one_step()
    keep = np.ones(len(links), bool)
    keep[::7] = False  # some pairs lose one direction
    li = links.i[keep].astype(np.int64)
    lj = links.j[keep].astype(np.int64)
    E = len(li)
    want = reciprocal_rows(li, lj)
    assert (want >= 0).any() and (want < 0).any()
    swapped = np.arange(E)  # each observer's first two neighbours swapped: not ascending
    starts = np.flatnonzero(np.r_[True, li[1:] != li[:-1]])
    for s in starts:
        if s + 1 < E and li[s + 1] == li[s]:
            swapped[[s, s + 1]] = swapped[[s + 1, s]]
    for offset in (0, 3 * E, 10**6):  # the table; the searches (ids far beyond E)
        for order in (np.arange(E), swapped):
            got = np.full(E, -7, np.int64)
            assert partner_rows(li[order] + offset, lj[order] + offset, got)
            np.testing.assert_array_equal(got, reciprocal_rows(li[order], lj[order]))
    assert not partner_rows(li[::-1].copy(), lj[::-1].copy(), np.empty(E, np.int64))


def test_the_pre_pass_ors_its_verdict_into_the_redundancy_stages() -> None:
    """Given another pre-pass's discards (``other``: the redundancy stage's), the verdict
    is ORed into that array in place (no second array, no ``|`` a step): the union of the
    two, and the same state as alone."""
    from resloc.cl.kernels_reciprocal import reciprocal_verdict

    world, x, li, lj, z = _step_with_one_ended_liars()
    x_nb = x[lj]
    nb = np.arange(len(li), dtype=np.int64)
    params = _params("full+reciprocal")
    memory = LinkMemory(world.B)
    detection = detector_state(params, memory, li, lj).kernel
    alone = reciprocal_verdict(params, memory, li, lj, z, None, x, x_nb, nb, detection)
    state = _store(memory).get(li, lj).copy()
    alone.undo()
    other = np.zeros(len(li), dtype=np.bool_)
    other[1::3] = True  # the redundancy stage's discards
    before = other.copy()
    both = reciprocal_verdict(params, memory, li, lj, z, None, x, x_nb, nb, detection, other)
    assert both.discard is other
    assert alone.discard.any() and (before & ~alone.discard).any()
    np.testing.assert_array_equal(other, before | alone.discard)
    np.testing.assert_array_equal(_store(memory).get(li, lj), state)
