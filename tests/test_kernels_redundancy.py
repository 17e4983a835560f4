"""The compiled redundancy stage and its sequence test (:mod:`resloc.cl.kernels_redundancy`).

Each case runs the default scenario (two trials batched, 34 robots) with a compromised robot
(a slow lead on its broadcast position, a jump now and then, a claimed covariance 100 times
too small) through four paths in lockstep, each with its own estimates and memory: the
rounds, the row-order loop, the numpy reference, and a run that switches between the
compiled path and the reference every few steps (the sequence test's state is the same
store in both). At every step the compiled paths must have run, and all agree to 1e-9 with
identical decisions and the same sequence-test state."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world, start_states
from resloc.cl import LinkBatch, LinkMemory, correct, kernels, predict
from resloc.cl import kernels_rounds as rounds
from resloc.cl.backend import kernel_refusal
from resloc.cl.detection_redundancy import fix_evidence
from resloc.cl.detection_redundancy_fixes import capped_claims
from resloc.cl.detection_sequence import WIDTH
from resloc.cl.kernels_detection import detector_state
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters import make_filter
from test_engine import assert_equivalent
from test_kernels_round_options import _path
from test_kernels_rounds import assert_same_loops

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

FILTERS = {"ckf": make_filter("ckf"), "ukf": make_filter("ukf", 0.8, 2.0, 1.0)}
#: The compromised robot (batch index: one in each of the two trials).
LIARS = (5, 17 + 9)
SEQUENCE = "redundancy_sequence"


def _params(defence: str, **changes):
    return replace(default_scenario().replace(**DEFENCES[defence]).cl_params(), **changes)


#: name -> (filter, CLParams, a Python tamper hook on the liars' readings too)
CASES = {
    "sequence": ("ckf", _params("full+redundancy+sequence"), False),
    # a shorter hold and a discount: re-admissions within the run
    "sequence-rejoin-ukf": (
        "ukf",
        _params(
            "full+redundancy+sequence",
            redundancy_sequence_hold=6.0,
            redundancy_sequence_forget=0.97,
        ),
        False,
    ),
    "sequence-cap-tamper": (
        "ckf",
        _params("full+redundancy+sequence", redundancy_cap_fusion=True),
        True,
    ),
    "redundancy-ci": ("ckf", _params("full+redundancy", fusion="ci"), False),
    # the redundancy stages beside the gate alone: no other option's stage is on, so the
    # loops must still run their options' form (kernels_rounds.beyond_paper)
    "gate-redundancy-sequence": (
        "ckf",
        replace(
            default_scenario()
            .replace(
                **{
                    "detector.enabled": True,
                    "detector.norm": "nis",
                    "detector.redundancy": True,
                    "detector.redundancy_sequence": True,
                }
            )
            .cl_params()
        ),
        False,
    ),
}


def _lie(k: int, rows: np.ndarray, x_nb: np.ndarray, P_nb: np.ndarray) -> None:
    """The compromised robots' broadcast at step ``k``: a lead growing 2 mm a step along x,
    0.4 m more every tenth step, claimed covariance x0.01."""
    x_nb[rows, 0] += 0.002 * k + (0.4 if k % 10 == 3 else 0.0)
    P_nb[rows] *= 0.01


def _tamper(z: np.ndarray, lied: np.ndarray):
    """A Python hook (no compiled form) adding 0.15 m to the liars' own readings."""

    def tamper(rows, z_hat, S):
        out = z[rows].copy()
        out[lied[rows], 0] += 0.15
        return out

    return tamper


def _stored(memory: LinkMemory) -> tuple[np.ndarray, np.ndarray]:
    store = memory.stage_statistic(SEQUENCE, width=WIDTH)
    return store.keys, store.values


def assert_same_sequence_state(a: LinkMemory, b: LinkMemory) -> None:
    """The same sequence-test state for every link either memory holds (a link the kernel
    inserted reads as the reference's 0)."""
    sa = a.stage_statistic(SEQUENCE, width=WIDTH)
    sb = b.stage_statistic(SEQUENCE, width=WIDTH)
    keys = np.union1d(sa.keys, sb.keys)
    i, j = keys // sa.n_nodes, keys % sa.n_nodes
    np.testing.assert_allclose(sa.get(i, j), sb.get(i, j), rtol=0, atol=1e-9)


PATHS = ("rounds", "row_order", "numpy", "switching")


def lockstep(filt, params, steps: int, seed: int, tampered: bool):
    """``steps`` steps of the default scenario through :data:`PATHS`; checks every step and
    yields the reference's outcome, memory and the liars' rows."""
    world = default_world(2, seed)
    state = start_states(world, PATHS)
    for k in range(steps):
        ws = world.step()
        lied = np.isin(ws.j, LIARS)
        res = {}
        for path, (x, P, memory) in state.items():
            run = path
            if path == "switching":  # 7 steps compiled, 7 steps numpy, ...
                run = "rounds" if (k // 7) % 2 == 0 else "numpy"
            with _path(run):
                xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
                x_nb, P_nb = xp[ws.j].copy(), Pp[ws.j].copy()
                _lie(k, lied, x_nb, P_nb)
                links = LinkBatch(
                    ws.i, ws.j, ws.z, x_nb, P_nb, ws.channel_ok, ws.risk_s, ws.risk_c,
                    ws.lambda2, tamper=_tamper(ws.z, lied) if tampered else None,
                )  # fmt: skip
                before = rounds.LOOP_RUNS.copy()
                res[path] = correct(filt, xp, Pp, links, params, memory)
                ran = rounds.LOOP_RUNS - before
            if run != "numpy":
                assert ran == {run: 1}, f"expected the {run} loop, ran {dict(ran)}"
                assert res[path][2].compiled, "the compiled path did not run"
            state[path] = (res[path][0], res[path][1], memory)
        assert_same_loops(res["rounds"], res["row_order"])
        assert_equivalent(res["rounds"], res["numpy"])
        for got, want in zip(res["switching"][:2], res["numpy"][:2], strict=True):
            assert np.abs(got - want).max() <= 1e-9
        np.testing.assert_array_equal(res["switching"][2].detected, res["numpy"][2].detected)
        memories = {path: s[2] for path, s in state.items()}
        for path in ("rounds", "row_order", "switching"):
            assert_same_sequence_state(memories[path], memories["numpy"])
        yield res["numpy"][2], memories["numpy"], lied


@pytest.mark.parametrize("case", list(CASES))
def test_compiled_redundancy_equals_the_reference(case: str) -> None:
    name, params, tampered = CASES[case]
    assert kernel_refusal(FILTERS[name], params, links_of_one_step()) is None
    detected = fused = held = 0
    liar_detected = liar_rows = 0
    released = False
    for k, (out, memory, lied) in enumerate(
        lockstep(FILTERS[name], params, 60, 31 + list(CASES).index(case), tampered)
    ):
        detected += int(out.detected.sum())
        fused += int(out.fused.sum())
        liar_detected += int(out.detected[lied].sum())
        liar_rows += int(lied.sum())
        if params.redundancy_sequence:
            values = _stored(memory)[1]
            now = int((values[:, 5] > 0).sum())
            released |= k > 0 and now < held
            held = now
    assert fused > 0 and detected > 0
    assert liar_detected > 0.5 * liar_rows, "the stages did not catch the liar"
    if params.redundancy_sequence:
        assert held > 0, "the sequence test never held a link out"
        if params.redundancy_sequence_hold < 10:
            assert released, "no held link was re-admitted"


def links_of_one_step(seed: int = 4) -> LinkBatch:
    """The links of the default scenario's first step (one trial), at the initial estimates:
    what a kernel refusal is asked about (shared by the kernel tests)."""
    world = default_world(1, seed)
    x, P = world.initial_estimates()
    ws = world.step()
    return LinkBatch(
        ws.i, ws.j, ws.z, x[ws.j], P[ws.j], ws.channel_ok, ws.risk_s, ws.risk_c, ws.lambda2
    )


def test_the_pre_pass_equals_fix_evidence_and_sees_a_changed_input() -> None:
    """The verdict of :func:`~resloc.cl.kernels_redundancy.redundancy_verdict` is the numpy
    stages' (exclusion or hold) on a step with a liar; with the liar's jump removed it is a
    different one (the twin reads what the spec reads)."""
    from resloc.cl.kernels_redundancy import redundancy_verdict

    params = _params("full+redundancy+sequence")
    world = default_world(1, 8)
    x, P = world.initial_estimates()
    ws = world.step()
    li, lj = ws.i.astype(np.int64), ws.j.astype(np.int64)
    verdicts = []
    for jump in (0.4, 0.0):
        x_nb, P_nb = x[ws.j].copy(), P[ws.j].copy()
        x_nb[ws.j == LIARS[0], 0] += jump
        P_nb[ws.j == LIARS[0]] *= 0.01
        ref_memory, memory = LinkMemory(world.B), LinkMemory(world.B)
        ev = fix_evidence(ws.z, x[ws.i], P[ws.i], x_nb, P_nb, ws.i, params, ws.j, ref_memory)
        spec = ev["fix_excluded"] | ev["sequence_discard"]
        nb = np.arange(len(li), dtype=np.int64)
        detection = detector_state(params, memory, li, lj).kernel
        verdict = redundancy_verdict(params, memory, li, lj, ws.z, x, P, x_nb, P_nb, nb, detection)
        np.testing.assert_array_equal(verdict.discard, spec)
        state = memory.stage_statistic(SEQUENCE, width=WIDTH).get(ws.i, ws.j)
        np.testing.assert_allclose(state, ev["sequence_state"], rtol=0, atol=1e-12)
        verdicts.append(verdict.discard)
    assert verdicts[0][ws.j == LIARS[0]].any()
    assert not np.array_equal(verdicts[0], verdicts[1])


def test_the_pre_pass_fixes_in_blocks_equal_fix_evidence_out_of_the_polynomials_range() -> None:
    """The pre-pass computes its rows' fixes by blocks of ``FIX_BLOCK`` rows in SIMD lanes
    (``_fixes_of_block``), the sine and cosine of ``theta_i + b`` by branch-free
    polynomials and, out of their range, by libm. Over five steps of two teams (more rows
    than two blocks, observers' rows across a block's edge), with the headings of every
    third robot far out of that range and a liar, its verdicts and sequence-test state equal
    :func:`fix_evidence`'s."""
    from resloc.cl.kernels_lanes import SINCOS_LANES_MAX
    from resloc.cl.kernels_redundancy import redundancy_verdict
    from resloc.cl.kernels_redundancy_fixes import FIX_BLOCK

    params = _params("full+redundancy+sequence")
    world = default_world(2, 8)
    x, P = world.initial_estimates()
    # ~1e10 turns (the same directions to ~1e-5 rad), far beyond the polynomials' range
    x[::3, 2] += 2.0 * np.pi * 1e10
    crossing = 0
    for _ in range(5):
        ws = world.step()
        ref_memory, memory = LinkMemory(world.B), LinkMemory(world.B)
        li, lj = ws.i.astype(np.int64), ws.j.astype(np.int64)
        assert len(li) > 2 * FIX_BLOCK
        crossing += sum(li[k * FIX_BLOCK - 1] == li[k * FIX_BLOCK] for k in (1, 2))
        assert (np.abs(x[li, 2] + ws.z[:, 1]) > SINCOS_LANES_MAX).any()
        x_nb, P_nb = x[ws.j].copy(), P[ws.j].copy()
        x_nb[ws.j == LIARS[0], 0] += 0.4
        ev = fix_evidence(ws.z, x[ws.i], P[ws.i], x_nb, P_nb, ws.i, params, ws.j, ref_memory)
        nb = np.arange(len(li), dtype=np.int64)
        detection = detector_state(params, memory, li, lj).kernel
        verdict = redundancy_verdict(params, memory, li, lj, ws.z, x, P, x_nb, P_nb, nb, detection)
        np.testing.assert_array_equal(verdict.discard, ev["fix_excluded"] | ev["sequence_discard"])
        state = memory.stage_statistic(SEQUENCE, width=WIDTH).get(ws.i, ws.j)
        np.testing.assert_allclose(state, ev["sequence_state"], rtol=0, atol=1e-12)
        assert verdict.discard[ws.j == LIARS[0]].any()
    assert crossing > 0  # an observer's rows in two blocks


def test_capped_claims_twin() -> None:
    from resloc.cl.kernels_claims import CLAIMS_UNSORTED, claimed_covariances
    from resloc.cl.kernels_redundancy_fixes import claim_scales

    links = links_of_one_step()
    P_nb = links.P_nb.copy()
    P_nb[::3] *= np.linspace(0.01, 3.0, len(P_nb[::3]))[:, None, None]
    li = links.i.astype(np.int64)
    nb = np.arange(len(li), dtype=np.int64)
    scale = np.empty(len(li))
    assert claim_scales(li, P_nb, nb, scale, np.empty(len(li)))
    out = np.empty_like(P_nb)
    x_nb, no_map = np.ascontiguousarray(links.x_nb), np.zeros((0, 3))
    args = (x_nb, P_nb, nb, True, no_map, 10.0, out, scale, np.empty(len(li)))
    assert claimed_covariances(li, *args) == 0  # capped, no map
    np.testing.assert_array_equal(out, capped_claims(P_nb, links.i))
    assert not claim_scales(li[::-1].copy(), P_nb, nb, scale, np.empty(len(li)))
    assert claimed_covariances(li[::-1].copy(), *args) == CLAIMS_UNSORTED


def test_the_attack_suite_runs_the_redundancy_defence_compiled(monkeypatch) -> None:
    """The adversary suite's compromised robot (a Python tamper hook, claimed covariance
    x0.01) against ``full+redundancy+sequence`` with claims capped: every correction of the
    run is compiled, and the run's metrics are the reference's."""
    import resloc.experiments.lockstep as lockstep
    from resloc.experiments.runner import run_scenario
    from resloc.world.attackers import make_attacker

    ran = []

    def counted(*args, **kwargs):
        out = correct(*args, **kwargs)
        ran.append(out[2].compiled)
        return out

    monkeypatch.setattr(lockstep, "correct", counted)
    adversary = make_attacker("compromised", robots=6, claimed_cov=0.01)
    scenario = default_scenario().replace(
        **DEFENCES["full+redundancy+sequence"],
        **adversary.overrides,
        **{"detector.redundancy_cap_fusion": True, "run.filters": ["ckf"]},
        **{"run.steps": 12, "run.trials": 1, "run.dead_reckoning": False},
    )
    results = {}
    for backend in ("numba", "numpy"):
        ran.clear()
        with kernels.use_backend(backend):
            result = run_scenario(
                scenario, adversary=make_attacker("compromised", robots=6, claimed_cov=0.01)
            )
        assert ran and all(ran) == (backend == "numba") and any(ran) == (backend == "numba")
        results[backend] = result.estimators["ckf"]
    for name in ("msle", "nees"):
        np.testing.assert_allclose(
            results["numba"].series[name], results["numpy"].series[name], rtol=1e-9, atol=1e-9
        )
    assert results["numba"].totals["tp"] > 0, "the defence caught nothing"
