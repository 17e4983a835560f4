"""Metrics against hand-computed cases."""

import numpy as np
import pytest

from resloc.experiments.metrics import detector_scores, msle, nees, position_rmse


def test_msle_hand_computed():
    # Three robots; the estimate stretches the 0-1 distance from 1 to 2 and moves robot 2.
    p = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]])
    q = np.array([[[0.0, 0.0], [2.0, 0.0], [0.0, 1.0]]])
    # d01: 1 vs 2 -> 1; d02: 1 vs 1 -> 0; d12: sqrt2 vs sqrt5 -> (sqrt5 - sqrt2)^2.
    want = 2 * (1.0 + (np.sqrt(5) - np.sqrt(2)) ** 2) / 3  # both orders of each pair, / N
    assert msle(p, q)[0] == pytest.approx(want)


def test_msle_is_invariant_to_rigid_motion_of_the_estimate():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(2, 10, 2))
    c, s = np.cos(0.7), np.sin(0.7)
    q = p @ np.array([[c, s], [-s, c]]) + np.array([3.0, -1.0])
    np.testing.assert_allclose(msle(p, q), 0.0, atol=1e-20)
    assert (position_rmse(p, q) > 1).all()


def test_rmse_and_nees():
    p = np.zeros((1, 2, 2))
    q = np.array([[[3.0, 4.0], [0.0, 0.0]]])
    assert position_rmse(p, q)[0] == pytest.approx(np.sqrt(25 / 2))
    x = np.array([[0.0, 0.0, np.pi - 0.05]])
    xh = np.array([[0.1, 0.0, -np.pi + 0.05]])  # heading error 0.1 across the seam
    P = np.diag([0.01, 1.0, 0.01])[None]
    assert nees(x, xh, P)[0] == pytest.approx(1.0 + 1.0)


def test_detector_scores():
    det = np.array([1, 1, 0, 0, 1], bool)
    att = np.array([1, 0, 1, 0, 1], bool)
    s = detector_scores(det, att)
    assert (s["tp"], s["fp"], s["fn"], s["tn"]) == (2, 1, 1, 1)
    assert s["precision"] == pytest.approx(2 / 3) and s["recall"] == pytest.approx(2 / 3)
    assert s["false_alarm_rate"] == pytest.approx(0.5)
    assert np.isnan(detector_scores(np.zeros(2, bool), np.zeros(2, bool))["precision"])
