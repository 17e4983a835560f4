"""The link rounds' second pass runs only in a round that has a lane for it.

:func:`resloc.cl.kernels_rounds.retried_lanes` decides, per round, whether
:func:`~resloc.cl.kernels_round_stages.inflated_moments` (and zone trust's fixes again from
``f P_i``) is called at all: it must answer True exactly when that pass would select a lane
(delivered, and re-admitted with ``f > 1`` or fused with a cached estimate's fresh moments).
The results of the rounds with the second pass (the recovery's re-admissions, ``cached``)
are compared with the reference in ``tests/test_kernels_round_options.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

from resloc.cl import kernels
from resloc.cl.kernels_lanes import CHUNK
from resloc.cl.kernels_rounds import retried_lanes

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")


def _selected(n, inflation, decision, fresh) -> bool:
    """Whether ``inflated_moments`` selects a lane (its own test, in numpy)."""
    lanes = slice(0, n)
    chosen = (decision[3, lanes] == 1.0) & ((inflation[lanes] > 1.0) | (fresh[lanes] == 1.0))
    return bool(chosen.any())


def _round(rng, n: int):
    decision = np.zeros((4, CHUNK))
    decision[3] = rng.random(CHUNK) < 0.3
    inflation = np.where(rng.random(CHUNK) < 0.05, 1.0 + rng.random(CHUNK), 1.0)
    fresh = (rng.random(CHUNK) < 0.05).astype(float)
    return n, inflation, decision, fresh


def test_a_round_needs_the_second_pass_exactly_when_a_lane_is_selected() -> None:
    rng = np.random.default_rng(7)
    answers = []
    for _ in range(400):
        args = _round(rng, int(rng.integers(1, 40)))
        answers.append(_selected(*args))
        assert retried_lanes(*args) == answers[-1]
    assert any(answers) and not all(answers)  # both answers seen


def test_each_reason_alone_selects_a_lane_and_nothing_else_does() -> None:
    n = 17
    decision = np.zeros((4, CHUNK))
    inflation = np.ones(CHUNK)
    fresh = np.zeros(CHUNK)
    assert not retried_lanes(n, inflation, decision, fresh)
    inflation[5] = 1.5  # re-admitted, not delivered
    fresh[6] = 1.0
    assert not retried_lanes(n, inflation, decision, fresh)
    decision[3, 9] = 1.0  # delivered, neither re-admitted nor fresh
    assert not retried_lanes(n, inflation, decision, fresh)
    decision[3, 5] = 1.0  # delivered and re-admitted with f > 1
    assert retried_lanes(n, inflation, decision, fresh)
    decision[3, 5] = 0.0
    decision[3, 6] = 1.0  # delivered with a cached estimate's fresh moments
    assert retried_lanes(n, inflation, decision, fresh)
    # a lane past the round's n is never read
    decision[3, 6] = 0.0
    decision[3, n + 1] = 1.0
    inflation[n + 1] = 2.0
    assert not retried_lanes(n, inflation, decision, fresh)
