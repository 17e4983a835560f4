"""The two compiled forms of the link loops (:func:`resloc.cl.kernels_rounds.beyond_paper`):
the paper's method runs the form compiled without the options' stages, any option the form
with every stage; both forms give the paper's method the same result, and the warm-up's
choice (:func:`resloc.cl.kernels.options_beyond_paper`) is the loops' own."""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import replace

import numpy as np
import pytest

from lockstep_helpers import default_world, runner_step, start_state
from resloc.cl import kernels
from resloc.cl import kernels_rounds as rounds
from resloc.cl.fusion_methods import fusion_strategy
from resloc.experiments.config import default_scenario
from resloc.filters import make_filter

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

PARAMS = default_scenario().cl_params()
#: name -> (CLParams, whether the loops run the options' form)
CASES = {
    "paper": (PARAMS, False),
    "nis gate": (replace(PARAMS, detector_norm="nis"), False),
    "last sent": (replace(PARAMS, threshold_innovation="last_sent"), False),
    "ci": (replace(PARAMS, fusion="ci"), True),
    "split_ci": (replace(PARAMS, fusion="split_ci"), True),
    "gauge": (replace(PARAMS, fusion="gauge"), True),
    "tracked": (replace(PARAMS, fusion="tracked"), True),
    "cusum": (replace(PARAMS, detector_norm="nis", cusum=True), True),
    "mean cusum": (replace(PARAMS, mean_cusum=True), True),
    "robot cusum": (replace(PARAMS, robot_cusum=True), True),
    "recovery": (replace(PARAMS, recovery=True), True),
    "cached": (replace(PARAMS, neighbour_estimate="cached"), True),
    "redundancy": (replace(PARAMS, redundancy=True, redundancy_sequence=True), True),
    # the reciprocal check's pre-pass verdicts alone (kernels_reciprocal): the options' form
    "reciprocal": (replace(PARAMS, reciprocal=True), True),
    # zone trust alone beside the paper's gate: the verdicts are in the options' form
    "zone": (default_scenario().replace(**{"detector.zone_trust": True}).cl_params(), True),
}


@contextmanager
def _forms_seen():
    """The ``beyond`` argument of every loop call within (the loops themselves run)."""
    seen: list = []
    loops = {
        "correct_links": rounds.correct_links,
        "correct_rounds": rounds.correct_rounds,
        "correct_joint_rounds": rounds.correct_joint_rounds,
    }

    def spy(name):
        def call(*args):
            seen.append((name, args[-1]))
            return loops[name](*args)

        return call

    for name in loops:
        setattr(rounds, name, spy(name))
    try:
        yield seen
    finally:
        for name, loop in loops.items():
            setattr(rounds, name, loop)


def _steps(filt, params, steps: int, rounds_min: int):
    """``steps`` corrections of the default scenario (two trials) with ``params``; yields
    each step's result."""
    world = default_world(2, 3)
    fusion = fusion_strategy(params.fusion)
    x, P, memory = start_state(world, fusion)
    saved = rounds.ROUNDS_MIN_LINKS
    rounds.ROUNDS_MIN_LINKS = rounds_min
    try:
        for _ in range(steps):
            ws = world.step()
            x, P, out = runner_step(filt, x, P, ws, world.dt, params, fusion, memory)
            assert out.compiled
            yield x, P, out
    finally:
        rounds.ROUNDS_MIN_LINKS = saved


@pytest.mark.parametrize("name", list(CASES))
def test_the_loops_run_the_options_form_exactly_when_an_option_is_on(name: str) -> None:
    params, beyond = CASES[name]
    filt = make_filter("ckf")
    for rounds_min in (1, 10**18):  # the rounds, then the row-order loop
        with _forms_seen() as seen:
            for _ in _steps(filt, params, 2, rounds_min):
                pass
        assert seen, "no compiled loop ran"
        assert {form for _, form in seen} == {True if beyond else None}, seen
    assert kernels.options_beyond_paper(params) is beyond  # the warm-up's choice


@pytest.mark.parametrize("kind", ["ckf", "ekf"])
def test_both_forms_give_the_paper_the_same_result(kind: str) -> None:
    filt = make_filter(kind)
    for rounds_min in (1, 10**18):
        paper = list(_steps(filt, PARAMS, 4, rounds_min))
        with rounds.every_stage(), _forms_seen() as seen:
            every = list(_steps(filt, PARAMS, 4, rounds_min))
        assert {form for _, form in seen} == {True}
        for (xa, Pa, a), (xb, Pb, b) in zip(paper, every, strict=True):
            np.testing.assert_allclose(xa, xb, rtol=0, atol=1e-12)
            np.testing.assert_allclose(Pa, Pb, rtol=0, atol=1e-12)
            np.testing.assert_array_equal(a.delivered, b.delivered)
            np.testing.assert_array_equal(a.detected, b.detected)
