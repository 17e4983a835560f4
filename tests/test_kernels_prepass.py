"""The defences' passes before the link loop in one call (:mod:`resloc.cl.kernels_prepass`).

* Whole corrections of the defence chains that run it (the claims capped and weakened as
  landmarks, zone's readings, the redundancy and reciprocal pre-passes) equal the numpy
  reference step after step, every decision and every stage's state, and the one-pass call
  ran on every compiled step; a chain it does not cover (a tamper hook) takes the stages'
  own dispatch.
* :func:`~resloc.cl.kernels_prepass.prepass_rows` gives the stage-by-stage kernels' results
  to the bit; rows not sorted by observer write nothing.
* The stores' values saved by the kernel in the buffers kept from step to step are what
  ``undo`` puts back."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from lockstep_helpers import default_world, start_states
from resloc.cl import LinkBatch, LinkMemory, correct, kernels, predict
from resloc.cl import kernels_rounds as rounds
from resloc.cl.detection_reciprocal import STATE_WIDTH, ReciprocalCheck
from resloc.cl.detection_sequence import WIDTH, RedundancySequence
from resloc.cl.kernels_detection import detector_state
from resloc.filters import make_filter
from test_kernels_round_options import _path
from test_kernels_zone import START, _params, assert_same_correction, assert_same_stage_state

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

if kernels.HAVE_NUMBA:
    from resloc.cl import kernels_prepass

CHAINS = [
    "zone+full+redundancy+sequence",
    "zone+full+redundancy+sequence+cap",
    "zone+full+redundancy+sequence+cap+landmarks",
    "zone+full+redundancy+sequence+reciprocal",
    "full+redundancy+sequence+reciprocal",
    "full+redundancy",
]
STEPS = 25


def _steps(params, steps: int, seed: int, tampered: bool = False):
    """``steps`` steps of the default scenario (two trials, from the zone's edge) through the
    compiled rounds and the reference; yields how many one-pass calls each compiled step
    made and the reference's outcome, after checking the step."""
    filt = make_filter("ckf")
    world = default_world(2, seed, start=START)
    state = start_states(world, ("rounds", "numpy"))
    for _ in range(steps):
        ws = world.step()
        res, runs = {}, 0
        for path, (x, P, memory) in state.items():
            with _path(path):
                xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
                z = ws.z.copy()
                tamper = None
                if tampered:  # a Python hook: 5 cm more on robot 5's readings

                    def tamper(rows, z_hat, S, z=z, lied=ws.j == 5):
                        out = z[rows].copy()
                        out[lied[rows], 0] += 0.05
                        return out

                links = LinkBatch(
                    ws.i, ws.j, z, xp[ws.j].copy(), Pp[ws.j].copy(), ws.channel_ok,
                    ws.risk_s, ws.risk_c, ws.lambda2, tamper=tamper,
                )  # fmt: skip
                before = kernels_prepass.PREPASS_RUNS["compiled"]
                loops = rounds.LOOP_RUNS.copy()
                res[path] = correct(filt, xp, Pp, links, params, memory)
                if path == "rounds":
                    runs = kernels_prepass.PREPASS_RUNS["compiled"] - before
                    assert rounds.LOOP_RUNS - loops == {"rounds": 1}
                    assert res[path][2].compiled, "the compiled path did not run"
            state[path] = (res[path][0], res[path][1], memory)
        assert_same_correction(res["rounds"], res["numpy"])
        assert_same_stage_state(state["rounds"][2], state["numpy"][2])
        yield runs, res["numpy"][2]


@pytest.mark.parametrize("chain", CHAINS)
def test_the_chains_in_one_pass_equal_the_reference(chain: str) -> None:
    params = _params(chain)
    runs, detected = [], 0
    for n, outcome in _steps(params, STEPS, 7 + CHAINS.index(chain)):
        runs.append(n)
        detected += int(outcome.detected.sum())
    assert runs == [1] * STEPS, "the one-pass call did not run on every step"
    assert detected > 0  # the stages decided something


def test_a_tamper_hook_takes_the_stages_own_dispatch() -> None:
    params = _params("zone+full+redundancy+sequence+cap+landmarks")
    runs = [n for n, _ in _steps(params, 4, 3, tampered=True)]
    assert runs == [0] * 4


def _one_step(chain: str, seed: int = 11):
    """A step's inputs at the zone's edge, after 30 compiled steps of the chain on the
    memory: ``(params, memory, links, inputs)``, ``inputs`` as :func:`prepass` takes them
    after ``params`` and ``memory`` (but the detection)."""
    params = _params(chain)
    filt = make_filter("ckf")
    world = default_world(2, seed, start=START)
    x, P = world.initial_estimates()
    memory = LinkMemory(world.B)
    with kernels.use_backend("numba"):
        for step in range(31):
            ws = world.step()
            x, P = predict(filt, x, P, ws.u_meas, world.dt, params)
            links = LinkBatch(
                ws.i, ws.j, np.ascontiguousarray(ws.z), x[ws.j].copy(), P[ws.j].copy(),
                ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2,
            )  # fmt: skip
            if step < 30:
                x, P, _ = correct(filt, x, P, links, params, memory)
    li, lj = ws.i.astype(np.int64), ws.j.astype(np.int64)
    rows = np.arange(len(li), dtype=np.int64)
    return params, memory, links, (li, lj, links.z, x, P, links.x_nb, links.P_nb, rows)


def _stage_by_stage(params, memory, links, inputs):
    """The stages' own kernels, in the dispatch's order: the claims, zone's readings, the
    redundancy pre-pass, the reciprocal one (the stores' values written in place)."""
    from resloc.cl.kernels_claims import claimed_links
    from resloc.cl.kernels_reciprocal import reciprocal_verdict
    from resloc.cl.kernels_redundancy import redundancy_verdict
    from resloc.cl.kernels_zone import zone_rows

    li, lj, z, x, P, _, _, nb = inputs
    index, x_c, P_c = claimed_links(params, links).neighbour_rows()
    assert index is None
    detect = detector_state(params, memory, li, lj).kernel
    fixes = redundancy_verdict(params, memory, li, lj, z, x, P, x_c, P_c, nb, detect)
    _, z_rec, _ = zone_rows(li, lj, z)
    if params.reciprocal:
        reciprocal_verdict(params, memory, li, lj, z, z_rec, x, x_c, nb, detect, fixes.discard)
    return x_c, P_c, nb, z_rec, fixes.discard


def _prepass(params, memory, inputs, x=None):
    li, lj, z, x0, P, x_nb, P_nb, nb = inputs
    detect = detector_state(params, memory, li, lj).kernel
    x = x0 if x is None else x
    return kernels_prepass.prepass(params, memory, li, lj, z, x, P, x_nb, P_nb, nb, detect)


@pytest.mark.parametrize(
    "chain",
    [
        "zone+full+redundancy+sequence+cap",  # (the redundancy's factors from the cap's order)
        "zone+full+redundancy+sequence+cap+landmarks",
        "zone+full+redundancy+sequence+reciprocal",
    ],
)
def test_the_one_pass_call_is_the_stages_kernels_to_the_bit(chain: str) -> None:
    params, memory, links, inputs = _one_step(chain)
    other = copy.deepcopy(memory)
    want = _stage_by_stage(params, other, links, inputs)
    x_c, P_c, rows, zone, fixes, paired = _prepass(params, memory, inputs)
    assert (paired is None) == (not params.reciprocal)
    for a, b in zip((x_c, P_c, rows, zone.kernel.z_reciprocal, fixes.discard), want, strict=True):
        np.testing.assert_array_equal(a, b)
    assert fixes.discard.any()
    if "+cap" in chain:  # claims changed
        assert not np.array_equal(P_c, links.P_nb)
    for name, width in STORES:
        np.testing.assert_array_equal(
            memory.stage_statistic(name, width=width).values,
            other.stage_statistic(name, width=width).values,
        )


STORES = ((RedundancySequence.name, WIDTH), (ReciprocalCheck.name, STATE_WIDTH))


def test_rows_not_sorted_write_nothing() -> None:
    params, memory, _, inputs = _one_step("zone+full+redundancy+sequence+reciprocal")
    li, lj, z, x, P, x_nb, P_nb, nb = inputs
    order = np.arange(len(li))[::-1].copy()
    inputs = (
        li[order],
        lj[order],
        z[order].copy(),
        x,
        P,
        x_nb[order].copy(),
        P_nb[order].copy(),
        nb,
    )
    stores = [memory.stage_statistic(n, width=w) for n, w in STORES]
    before = [s.values.copy() for s in stores]
    assert _prepass(params, memory, inputs) is None
    for store, values in zip(stores, before, strict=True):
        np.testing.assert_array_equal(store.values, values)


def test_undo_puts_back_the_values_the_kernel_saved() -> None:
    """Steps on one memory (from the second on, the kernel saves the stores' values into
    the buffers kept, no numpy copy): ``undo`` after each gives the values before it."""
    params, memory, _, inputs = _one_step("zone+full+redundancy+sequence+reciprocal")
    stores = [memory.stage_statistic(n, width=w) for n, w in STORES]
    kept = verdicts = None
    for step in range(3):
        before = [s.values.copy() for s in stores]
        _, _, _, _, fixes, paired = _prepass(params, memory, inputs, inputs[3] + 0.05 * step)
        buffers = [fixes.state.saved[0][4], paired.state.saved[0][4]]
        for store, values in zip(stores, before, strict=True):
            assert not np.array_equal(store.values, values), "the pass wrote no state"
        if kept is not None:  # the steady state: the buffers kept, not this step's copies,
            # and the verdicts on them (the same records)
            assert all(b is k for b, k in zip(buffers, kept, strict=True))
            assert fixes is verdicts[0] and paired is verdicts[1]
        kept, verdicts = buffers, (fixes, paired)
        paired.undo()
        fixes.undo()
        for store, values in zip(stores, before, strict=True):
            np.testing.assert_array_equal(store.values, values)


def test_a_finished_memory_is_not_kept_by_the_passes_outputs() -> None:
    """The outputs and the stores' buffers are kept per memory from step to step, weakly:
    a run's memory (and the arrays kept for it) goes when the run lets it go."""
    import gc
    import weakref

    params, memory, _, inputs = _one_step("zone+full+redundancy+sequence+reciprocal")
    assert _prepass(params, memory, inputs) is not None
    assert memory in kernels_prepass._OUTPUTS and memory in kernels_prepass._BUFFERS
    gone = weakref.ref(memory)
    del memory
    gc.collect()
    assert gone() is None
