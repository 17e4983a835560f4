"""The outvoted stage: a robot its observers' notes place elsewhere widens its covariance."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from resloc.cl.detection_outvoted import Outvoted, outvoted_statistic, widen_outvoted
from resloc.cl.detection_witness import WitnessNotes, witness_statistic
from resloc.cl.detection_witness_frames import reference_record
from resloc.cl.memory import LinkMemory
from resloc.cl.params import CLParams
from resloc.errors import ConfigError
from resloc.world.attackers.outvoted import shielding_notes
from resloc.world.attackers.witness import lying_notes

PARAMS = CLParams(witness=True, outvoted=True, witness_liars=3.0, witness_k=4.0, witness_h=40.0)
ROBOT = 0
OBSERVERS = 12
SD_Q = 0.02  # each note's own noise (m): the bearing noise at the team's ranges
SD_P = 0.0015  # the robot's claimed position standard deviation (m)


def _notes(rng, offset=(0.0, 0.0), liars=0, lie=(0.0, 0.0), sd_p=SD_P) -> WitnessNotes:
    """One step's notes of observers 1.. on robot 0: its broadcast is ``offset`` away from
    where its observers see it; the first ``liars`` notes are moved by ``lie``."""
    n = OBSERVERS
    u = np.asarray(offset) + rng.normal(0.0, SD_Q, (n, 2))
    u[:liars] += np.asarray(lie)
    Q = np.tile(np.eye(2) * SD_Q**2, (n, 1, 1))
    P = np.tile(np.eye(2) * sd_p**2, (n, 1, 1))
    return WitnessNotes(u, Q, P, np.arange(1, n + 1), np.full(n, ROBOT), np.ones(n, bool))


def _links(ok=None):
    """The step's links of robot 0 (receiver) from each observer (sender)."""
    ok = np.ones(OBSERVERS, bool) if ok is None else np.asarray(ok)
    return SimpleNamespace(
        i=np.zeros(OBSERVERS, np.int64), j=np.arange(1, OBSERVERS + 1), channel_ok=ok
    )


def _P(sd_p=SD_P):
    P = np.tile(np.eye(3) * sd_p**2, (OBSERVERS + 1, 1, 1))
    P[:, 2, 2] = 0.01**2
    return P


def _run(steps, make, params=PARAMS, ok=None, sd_p=SD_P):
    """Robot 0's widening factor per step (1: none) with each step's notes waiting."""
    memory = LinkMemory(OBSERVERS + 1)
    out = []
    for k in range(steps):
        reference_record(make(k), memory)
        P = _P(sd_p)
        Pw = widen_outvoted(params, memory, _links(ok), P)
        out.append(Pw[ROBOT, 0, 0] / P[ROBOT, 0, 0])
        assert np.allclose(Pw[1:], P[1:])  # no observer touched
    return np.array(out)


def test_an_honest_robot_on_target_never_widens():
    rng = np.random.default_rng(1)
    assert (_run(300, lambda k: _notes(rng)) == 1.0).all()


def test_a_robot_persistently_off_widens_to_cover_its_offset_then_skips_a_step():
    rng = np.random.default_rng(2)
    offset = np.array([0.02, 0.015])  # 25 mm: one step's 12 notes see 4 sigma, not more
    f = _run(60, lambda k: _notes(rng, offset))
    first = int(np.flatnonzero(f > 1.0)[0])
    assert 3 <= first <= 40  # the sequence test needs several steps
    # covariance matching on the notes' median: about |offset|^2 / SD_P^2 / 2 (~139), capped
    assert f[first] == pytest.approx(PARAMS.outvoted_cap)
    assert f[first + 1] == 1.0  # the notes of the next step predate the widening


def test_the_widening_matches_the_offset_below_the_cap():
    rng = np.random.default_rng(3)
    offset, sd_p = np.array([0.03, 0.0]), 0.005
    f = _run(120, lambda k: _notes(rng, offset, sd_p=sd_p), sd_p=sd_p)
    assert (f > 1.0).any()
    # covariance matching on the notes' median, 18 for the offset itself (the median's own
    # noise, about 7 mm a step here, adds to it)
    expected = (offset @ offset) / sd_p**2 / 2.0
    assert (f[f > 1.0] < PARAMS.outvoted_cap).all()
    assert np.median(f[f > 1.0]) == pytest.approx(expected, rel=0.3)


@pytest.mark.parametrize("lie", [(0.1, 0.0), (0.0, -0.05)])
def test_f_lying_observers_cannot_make_an_honest_robot_widen(lie):
    rng = np.random.default_rng(4)
    assert (_run(300, lambda k: _notes(rng, liars=3, lie=lie)) == 1.0).all()


def test_only_the_notes_that_reached_the_robot_count():
    rng = np.random.default_rng(5)
    notes = _notes(rng, (0.03, 0.0))
    ok = np.zeros(OBSERVERS, bool)
    ok[:3] = True  # three frames through: at most f notes, not judged
    ids, T, _ = outvoted_statistic(PARAMS, notes, *vars(_links(ok)).values())
    assert np.isnan(T[ids == ROBOT]).all()
    ok[:5] = True
    ids, T, m = outvoted_statistic(PARAMS, notes, *vars(_links(ok)).values())
    assert np.isfinite(T[ids == ROBOT][0])
    assert m[ids == ROBOT][0] == pytest.approx(np.median(notes.u[:5], axis=0))
    rng = np.random.default_rng(5)
    f = _run(80, lambda k: _notes(rng, (0.03, 0.0)), ok=np.arange(OBSERVERS) < 3)
    assert (f == 1.0).all()


def test_the_stage_is_off_without_the_witness_notes():
    rng = np.random.default_rng(6)
    params = CLParams(witness=False, outvoted=True)
    assert (_run(80, lambda k: _notes(rng, (0.03, 0.0)), params=params) == 1.0).all()
    assert Outvoted().active(PARAMS) and not Outvoted().active(CLParams(witness=True))


def test_the_liars_notes_shield_an_honest_victim():
    """The compromised observers' response: on an honest robot their notes are those that
    make its statistic smallest (here, below the accusing notes' and the honest ones')."""
    rng = np.random.default_rng(7)
    n = OBSERVERS
    notes = _notes(rng, (0.02, 0.0))
    # robots 0 (victim) .. 12; observers 1, 2, 3 compromised
    is_liar = np.zeros(n + 1, bool)
    is_liar[1:4] = True
    shielded = shielding_notes(notes, is_liar, PARAMS)
    lied = lying_notes(notes, is_liar, PARAMS)

    def T(u):
        w = WitnessNotes(u, notes.Q, notes.P_pos, notes.i, notes.j, notes.sent)
        return witness_statistic(w, PARAMS, np.array([ROBOT]))[1][0]

    assert T(shielded.u) < min(T(lied.u), T(notes.u))
    assert np.array_equal(shielded.u[3:], notes.u[3:])  # the honest notes are untouched


def test_outvoted_without_the_witness_is_a_one_line_error():
    from resloc.experiments.config import default_scenario

    with pytest.raises(ConfigError) as err:
        default_scenario().replace(**{"detector.outvoted": True})
    assert "detector.outvoted" in str(err.value) and "\n" not in str(err.value)
    sc = default_scenario().replace(**{"detector.witness": True, "detector.outvoted": True})
    assert sc.detector.outvoted


def test_the_compiled_path_takes_the_stage():
    from resloc.cl.backend import _params_refusal

    assert Outvoted.compiled
    assert _params_refusal(CLParams(witness=True, outvoted=True)) is None


def test_the_attacker_sees_the_widened_covariances():
    from resloc.cl.detection_outvoted import applied_factors
    from resloc.world.attackers.outvoted import widened

    rng = np.random.default_rng(2)
    memory = LinkMemory(OBSERVERS + 1)
    for _ in range(60):
        reference_record(_notes(rng, (0.02, 0.015)), memory)
        P = _P()
        used = widen_outvoted(PARAMS, memory, _links(), P)
        assert np.allclose(widened(P, memory, PARAMS), used)
        if used is not P:
            break
    assert used is not P  # it widened (the comparison above saw a widened step)
    f = applied_factors(memory, OBSERVERS + 1)
    assert f[ROBOT] > 1.0 and (f[1:] == 1.0).all()


def test_the_shield_is_a_choice_with_auto_against_the_stage_only():
    from resloc.world.attackers import make_attacker
    from resloc.world.attackers.estimates import SHIELDS

    against = CLParams(witness=True, outvoted=True)
    witness_only = CLParams(witness=True)
    assert SHIELDS["auto"](against) and not SHIELDS["auto"](witness_only)
    assert SHIELDS["on"](witness_only) and not SHIELDS["off"](against)
    assert make_attacker("compromised").shield == "auto"
    with pytest.raises(ValueError, match="shield") as err:
        make_attacker("compromised", shield="sometimes")
    assert "\n" not in str(err.value)


def test_group_medians_are_numpys_median_per_group_to_the_bit():
    from resloc.cl.detection_outvoted import group_medians

    rng = np.random.default_rng(7)
    count = rng.integers(1, 9, size=40)
    start = np.r_[0, np.cumsum(count)[:-1]]
    u = rng.normal(size=(int(count.sum()), 2))
    u[rng.integers(0, len(u), 6)] = u[rng.integers(0, len(u), 6)]  # ties
    u[start[5] + 1 if count[5] > 1 else start[5], 1] = np.nan  # a nan in group 5
    want = np.stack([np.median(u[a : a + c], axis=0) for a, c in zip(start, count, strict=True)])
    got = group_medians(u, start, count)
    assert np.array_equal(got, want, equal_nan=True)
    assert np.isnan(got[5, 1]) and not np.isnan(got[5, 0])


def test_no_widening_goes_beyond_the_largest_standard_deviation():
    rng = np.random.default_rng(4)
    offset, sd_p = np.array([0.1, 0.0]), 0.02  # matching asks ~12.5: std 0.02 -> 0.07
    f = _run(120, lambda k: _notes(rng, offset, sd_p=sd_p), sd_p=sd_p)
    assert (f > 1.0).any()
    bound = (PARAMS.outvoted_max_std / sd_p) ** 2  # 6.25: std 0.05
    assert f.max() == pytest.approx(bound)
    unbounded = replace(PARAMS, outvoted_max_std=1e3)
    g = _run(120, lambda k: _notes(rng, offset, sd_p=sd_p), params=unbounded, sd_p=sd_p)
    assert g.max() > 2 * bound  # the bound is what stopped it
    # a robot already beyond the bound is not widened at all
    wide = 0.06
    assert (_run(120, lambda k: _notes(rng, 4 * offset, sd_p=wide), sd_p=wide) == 1.0).all()


def test_the_runtime_runs_the_outvoted_defence_on_broadcast_estimates_only():
    """Robot processes exchange the witness notes the stage reads and judge the notes on
    themselves (tests/test_runtime_witness.py); pulled estimates (``cached``) carry no
    notes: refused by name before any process starts."""
    from resloc.experiments.config import default_scenario
    from resloc.experiments.defences import DEFENCES
    from resloc.runtime.team import check_supported

    defence = DEFENCES["zone+full+redundancy+sequence+cap+landmarks+witness+outvoted"]
    sc = default_scenario().replace(**{"run.trials": 1, **defence})
    assert sc.detector.outvoted
    check_supported(sc)
    pulled = sc.replace(**{"estimator.neighbour_estimate": "cached"})
    with pytest.raises(ConfigError, match=r"^detector\.\w+: pulled estimates") as err:
        check_supported(pulled)
    assert "\n" not in str(err.value)
