"""The compiled zone-aware trust (:mod:`resloc.cl.kernels_zone`).

Each case runs the default scenario (two trials batched, 34 robots, its attacks inside the
sensing danger zones) with zone trust on through the compiled loops and the numpy reference
in lockstep from the zone's edge on, each path with its own estimates and memory: the
rounds, the row-order loop and the reference (the EKF: the row-order loop and the
reference). At every step the
compiled paths must have run (no fallback), and all agree to 1e-9 with identical decisions,
the same per-row zone verdicts as the reference's (withheld, substituted by the partner's
position fix, judged as usual) and the same state of every stage (CUSUMs, robot CUSUM,
recovery, the redundancy sequence test). Over the run, some robots must be inside the map
with a trusted partner reading and some without one."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world, start_states
from resloc.angles import wrap_angle
from resloc.cl import (
    LinkBatch,
    LinkMemory,
    correct,
    kernels,
    kernels_zone,
    kernels_zone_verdicts,
    predict,
)
from resloc.cl import kernels_rounds as rounds
from resloc.cl.backend import kernel_refusal
from resloc.cl.detection_recovery import RejectionRecovery
from resloc.cl.detection_zone import ZoneTrust, materialize_with_reciprocal
from resloc.cl.memory import LinkStatistic
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES
from resloc.filters import make_filter
from test_kernels_redundancy import links_of_one_step
from test_kernels_round_options import _path

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

FILTERS = {
    "ckf": make_filter("ckf"),
    "ukf": make_filter("ukf", 0.8, 2.0, 1.0),
    "ekf": make_filter("ekf"),
}
STEPS = 60
#: The team reaches the zone after about 170 steps; from 270 on, 5-11 of its 17 robots
#: are inside it at a time.
START = 270


def _params(defence: str, overrides: dict | None = None, **changes):
    sc = default_scenario().replace(**DEFENCES[defence], **(overrides or {}))
    return replace(sc.cl_params(), **changes)


#: A tight NIS gate and an early recovery: re-admissions with an inflated covariance, many
#: of them of substituted rows (the fix again from ``f P_i``).
STRICT = dict(rho=1.0, recovery_after=1.0, recovery_gate=6.0)

#: name -> (filter, CLParams, a Python tamper hook on the readings)
CASES = {
    "zone+full+redundancy+sequence": (
        "ckf",
        _params("zone+full+redundancy+sequence"),
        False,
    ),
    "zone+full+redundancy+sequence+cap-ukf": (
        "ukf",
        _params("zone+full+redundancy+sequence+cap"),
        False,
    ),
    "zone+full-shifted": ("ckf", _params("zone+full@shifted"), False),
    "zone+full-shrunk-ukf": ("ukf", _params("zone+full@shrunk"), False),
    # a shifted and shrunk map with a margin, a Python hook that lies on the readings (and
    # on what the partners report), a tight gate with early re-admissions
    "zone-map-error-tamper": (
        "ckf",
        _params(
            "zone+full+redundancy+sequence",
            {
                "detector.zone_trust_shift": [0.3, -0.2],
                "detector.zone_trust_scale": 0.8,
                "detector.zone_trust_margin": 0.1,
            },
        ),
        True,
    ),
    "zone-strict-recovery": ("ckf", _params("zone+full", **STRICT), False),
    # the reciprocal check's pre-pass beside zone trust (its state kept for judged rows only)
    "zone+full+redundancy+sequence+reciprocal": (
        "ckf",
        _params("zone+full+redundancy+sequence+reciprocal"),
        False,
    ),
    # the neighbours inside the map weakened as landmarks (their claims, before the kernel)
    "zone+full+redundancy+sequence+cap+landmarks": (
        "ckf",
        _params("zone+full+redundancy+sequence+cap+landmarks"),
        False,
    ),
    "zone-ekf": ("ekf", _params("zone+full+redundancy+sequence"), False),
    "zone-gate-only-ekf": ("ekf", _params("zone"), False),
}

#: Liars (batch indices, one per trial): a Python hook adds this to their readings.
LIARS = (5, 17 + 9)


def _tamper(z: np.ndarray, lied: np.ndarray):
    """A Python hook (no compiled form) adding 0.15 m to the liars' readings and 0.1 m to
    what their partners report of them."""

    def tamper(rows, z_hat, S):
        out = z[rows].copy()
        out[lied[rows], 0] += 0.15
        return out

    def reported(z_reciprocal):
        out = np.array(z_reciprocal, float)
        out[lied, 0] += 0.1
        return out

    tamper.reported = reported
    return tamper


class Verdicts:
    """The per-row verdicts of zone trust: the reference's (``ZoneTrust.discard`` and the
    substituted rows it is handed, round by round) and the compiled loops' (the
    :class:`~resloc.cl.kernels_zone.KernelZone` verdicts at the end of the step)."""

    def __init__(self, monkeypatch) -> None:
        self.reference: list = []
        self.compiled: list = []
        self.readmitted_substituted = 0  # by the reference's recovery, with f > 1
        discard = ZoneTrust.discard
        keep = kernels_zone.keep_unjudged_state
        recover = RejectionRecovery.discard

        def recovered(stage, evidence, params, memory):
            detected = recover(stage, evidence, params, memory)
            if evidence.inflation is not None and evidence.zone_substituted is not None:
                again = (evidence.inflation > 1.0) & ~detected & evidence.zone_substituted
                self.readmitted_substituted += int(again.sum())
            return detected

        def judged(stage, evidence, params, memory):
            withheld = discard(stage, evidence, params, memory)
            verdict = np.where(
                withheld, kernels_zone_verdicts.WITHHELD, kernels_zone_verdicts.OUTSIDE
            )
            if evidence.zone_substituted is not None:
                verdict[evidence.zone_substituted] = kernels_zone_verdicts.SUBSTITUTED
            self.reference.append((evidence.i.copy(), evidence.j.copy(), verdict))
            return withheld

        def kept(state, fixes, li, lj):
            self.compiled.append(state.kernel.verdict.copy())
            return keep(state, fixes, li, lj)

        monkeypatch.setattr(ZoneTrust, "discard", judged)
        monkeypatch.setattr(RejectionRecovery, "discard", recovered)
        monkeypatch.setattr(kernels_zone, "keep_unjudged_state", kept)

    def reference_rows(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """The reference's verdicts of the step's rows ``(i, j)`` (its rounds gathered)."""
        n = int(max(i.max(), j.max())) + 1
        verdict = np.full(len(i), -1)
        row = {int(k): e for e, k in enumerate(i * n + j)}
        for ri, rj, v in self.reference:
            for a, b, c in zip(ri, rj, v, strict=True):
                verdict[row[int(a) * n + int(b)]] = c
        self.reference.clear()
        assert (verdict >= 0).all()
        return verdict


def assert_same_correction(fast, ref, tol: float = 1e-9) -> None:
    """Two corrections agree: estimates and covariances to ``tol``, the norms and thresholds
    to ``tol`` relative, every decision identical. (The norms get the states' tolerance,
    not ``test_engine``'s 1e-12: a position fix's ``S`` is a position covariance, and its
    innovation's norm magnifies the 1e-14 the estimates of the loops differ by.)"""
    (xf, Pf, of), (xr, Pr, orf) = fast, ref
    d = xf - xr
    d[:, 2] = wrap_angle(d[:, 2])
    assert np.abs(d).max() <= tol
    assert np.abs(Pf - Pr).max() <= tol
    np.testing.assert_allclose(of.norm, orf.norm, rtol=tol, atol=1e-12)
    np.testing.assert_allclose(of.threshold, orf.threshold, rtol=tol, atol=1e-12, equal_nan=True)
    for name in ("detected", "triggered", "delivered", "fused", "repaired"):
        np.testing.assert_array_equal(getattr(of, name), getattr(orf, name), err_msg=name)


def _same_store(a: LinkStatistic, b: LinkStatistic, name: str) -> None:
    """Equal values for every link either store holds (a link the kernel inserted at 0
    reads as the reference's 0 for a link it has not stored)."""
    keys = np.union1d(a.keys, b.keys)
    i, j = keys // a.n_nodes, keys % a.n_nodes
    np.testing.assert_allclose(a.get(i, j), b.get(i, j), rtol=0, atol=1e-9, err_msg=name)


STORES = (
    ("robot_cusum", None),
    ("recovery", None),
    ("recovery_spread", None),
    ("recovery_applied", None),
    ("redundancy_sequence", 6),
    ("reciprocal", 3),
)


def assert_same_stage_state(fast: LinkMemory, ref: LinkMemory) -> None:
    _same_store(fast.cusum, ref.cusum, "cusum")
    _same_store(fast.mean_cusum, ref.mean_cusum, "mean_cusum")
    for name, width in STORES:
        _same_store(
            fast.stage_statistic(name, width=width), ref.stage_statistic(name, width=width), name
        )


def lockstep(filt, params, steps: int, seed: int, tampered: bool, verdicts: Verdicts):
    """``steps`` steps of the default scenario through the compiled loops and the
    reference; checks every step and yields the reference's per-row verdicts and outcome."""
    world = default_world(2, seed, START)  # the world alone, to the zone's edge
    paths = ("row_order", "numpy") if filt is FILTERS["ekf"] else ("rounds", "row_order", "numpy")
    state = start_states(world, paths)
    for _ in range(steps):
        ws = world.step()
        lied = np.isin(ws.j, LIARS)
        res, compiled = {}, {}
        for path, (x, P, memory) in state.items():
            with _path(path):
                xp, Pp = predict(filt, x, P, ws.u_meas, world.dt, params)
                links = LinkBatch(
                    ws.i, ws.j, ws.z, xp[ws.j].copy(), Pp[ws.j].copy(), ws.channel_ok,
                    ws.risk_s, ws.risk_c, ws.lambda2,
                    tamper=_tamper(ws.z, lied) if tampered else None,
                )  # fmt: skip
                before = rounds.LOOP_RUNS.copy()
                res[path] = correct(filt, xp, Pp, links, params, memory)
                ran = rounds.LOOP_RUNS - before
            if path != "numpy":
                assert ran == {path: 1}, f"expected the {path} loop, ran {dict(ran)}"
                assert res[path][2].compiled, "the compiled path did not run"
                assert len(verdicts.compiled) == 1, "the compiled zone stage did not run"
                compiled[path] = verdicts.compiled.pop()
            state[path] = (res[path][0], res[path][1], memory)
        reference = verdicts.reference_rows(ws.i, ws.j)
        for path in compiled:
            np.testing.assert_array_equal(compiled[path], reference, err_msg=path)
            assert_same_correction(res[path], res["numpy"])
            assert_same_stage_state(state[path][2], state["numpy"][2])
        if "rounds" in res:
            assert_same_correction(res["rounds"], res["row_order"])
        yield reference, res["numpy"][2]


@pytest.mark.parametrize("case", list(CASES))
def test_compiled_zone_trust_equals_the_reference(case: str, monkeypatch) -> None:
    name, params, tampered = CASES[case]
    filt = FILTERS[name]
    assert kernel_refusal(filt, params, links_of_one_step()) is None
    verdicts = Verdicts(monkeypatch)
    count = np.zeros(3, int)
    fused_substituted = 0
    for reference, out in lockstep(filt, params, STEPS, 41 + list(CASES).index(case), tampered,
                                   verdicts):  # fmt: skip
        count += np.bincount(reference, minlength=3)
        fused_substituted += int(out.fused[reference == kernels_zone_verdicts.SUBSTITUTED].sum())
    outside, withheld, substituted = count
    assert outside > 0 and withheld > 0, "no robot inside the map without a partner reading"
    assert substituted > 0 and fused_substituted > 0, "no partner's position fix fused"
    if params.recovery_after <= 1.0:
        assert verdicts.readmitted_substituted > 0, "no fix re-admitted with f P_i"


def test_zone_trust_selects_the_options_form() -> None:
    """Zone trust beside the paper's gate alone switches the loops to the options' form
    (the paper's form is compiled without the stage)."""
    params = _params("zone", detector_norm="nis")
    assert kernels.options_beyond_paper(params)
    assert not kernels.options_beyond_paper(replace(params, zone_trust=False))


@pytest.mark.parametrize(
    "changes, reason",
    [
        ({"fusion": "ci"}, "naive fusion"),
        ({"fusion": "gauge"}, "naive fusion"),
        ({"neighbour_estimate": "cached"}, "cached"),
    ],
)
def test_what_the_twin_does_not_cover_falls_back_with_a_reason(changes, reason) -> None:
    params = _params("zone+full", **changes)
    refusal = kernel_refusal(FILTERS["ckf"], params, links_of_one_step())
    assert refusal is not None and "zone_trust" in refusal and reason in refusal


def test_partner_readings_equal_the_reference_pairing() -> None:
    """The compiled gathering of the partners' readings is the reference's
    (``materialize_with_reciprocal`` without a hook), with links whose reverse is missing;
    rows not sorted by observer are refused."""
    links = links_of_one_step()
    keep = np.ones(len(links), bool)
    keep[::7] = False  # some pairs lose one direction
    li = links.i[keep].astype(np.int64)
    lj = links.j[keep].astype(np.int64)
    z = np.ascontiguousarray(links.z[keep])
    sub = LinkBatch(
        li, lj, z, links.x_nb[keep], links.P_nb[keep], links.channel_ok[keep],
        links.risk_s, links.risk_c, links.lambda2,
    )  # fmt: skip
    E = len(li)
    want = materialize_with_reciprocal(sub, np.zeros((E, 2)), np.zeros((E, 2, 2))).z_reciprocal
    got = np.empty((E, 2))
    assert kernels_zone.partner_readings(li, lj, z, got)
    np.testing.assert_array_equal(got, want)
    assert np.isnan(got[:, 0]).any() and np.isfinite(got[:, 0]).any()
    assert not kernels_zone.partner_readings(li[::-1].copy(), lj[::-1].copy(), z, got)
    # the three ways: a team's ids (a table of every pair), ids up to ~4 E (a table of
    # each observer's first row), ids far beyond the rows' count (a binary search per row)
    for offset in (0, 3 * E, 10**6):
        far = np.full((E, 2), -1.0)
        assert kernels_zone.partner_readings(li + offset, lj + offset, z, far)
        np.testing.assert_array_equal(far, want, err_msg=str(offset))
    # a pair twice (not a batch the loops take; the first row's reading, as the walk's)
    twice = np.insert(np.arange(E), 3, 3)
    lt, jt, zt = li[twice], lj[twice], z[twice].copy()
    zt[4] += 1.0  # the second row of the pair reads differently
    for offset in (0, 3 * E, 10**6):
        got = np.empty((E + 1, 2))
        assert kernels_zone.partner_readings(lt + offset, jt + offset, zt, got)
        partner = (lt == jt[3]) & (jt == lt[3])
        assert partner.any()
        np.testing.assert_array_equal(got[partner], np.broadcast_to(zt[3], got[partner].shape))


def test_inside_map_is_the_reference_test() -> None:
    """``kernels_zone_verdicts.inside_map`` (the squares where they decide, else hypot) is
    ``inside_zone_map`` at random points and at points on, just inside and just outside
    the edges, for a disc of radius 0 or below, far away and non-finite points."""
    from resloc.cl.detection_zone import inside_zone_map

    rng = np.random.default_rng(4)
    discs = ((0.0, 0.0, 5.0), (10.0, -2.0, 0.5), (3.0, 3.0, 0.0), (-4.0, 6.0, -1.0))
    d = np.asarray(discs)
    angle = rng.uniform(0, 2 * np.pi, 400)
    edge = []
    for cx, cy, r in discs:
        for f in (1.0, 1 - 1e-15, 1 + 1e-15, 1 - 1e-9, 1 + 1e-9, 1 - 1e-6, 1 + 1e-6):
            edge.append(np.column_stack([cx + f * r * np.cos(angle), cy + f * r * np.sin(angle)]))
    points = np.vstack(
        [
            rng.uniform(-15, 15, (2000, 2)),
            *edge,
            [[3.0, 4.0], [3.0, 3.0], [1e200, 0.0], [1e-200, 1e-200], [np.nan, 0.0]],
            [[np.inf, 0.0], [10.0, -1.5], [10.5, -2.0]],
        ]
    )
    want = inside_zone_map(points, discs)
    got = np.array([kernels_zone_verdicts.inside_map(d, px, py) for px, py in points])
    np.testing.assert_array_equal(got, want)
    assert want.any() and not want.all()
