"""What makes ``resloc run`` fast without changing a number: the metrics in bulk, and the
compiled kernels loaded before any estimator's timer starts."""

from __future__ import annotations

import numpy as np
import pytest

from resloc.experiments import lockstep, runner
from resloc.experiments.config import default_scenario
from resloc.experiments.metrics import (
    NEES_EXCEED_3DOF,
    AccuracyRecorder,
    msle,
    nees,
    position_rmse,
    relative_nees,
)

T, N, STEPS = 3, 5, 23


def _steps(seed: int = 0):
    rng = np.random.default_rng(seed)
    for _ in range(STEPS):
        pose = rng.normal(size=(T * N, 3))
        x = pose + 0.1 * rng.normal(size=(T * N, 3))
        A = rng.normal(size=(T * N, 3, 3))
        P = 0.01 * (A @ np.swapaxes(A, 1, 2)) + 1e-3 * np.eye(3)
        yield pose, x, P


def _per_step_reference(recorded):
    series = {k: np.full((STEPS, T), np.nan) for k in ("msle", "rmse", "nees", "nees_rel")}
    exceed, exceed_rel = np.zeros(T, np.int64), np.zeros(T, np.int64)
    for k, (pose, x, P) in recorded:
        pos_t, pos_e = pose[:, :2].reshape(T, N, 2), x[:, :2].reshape(T, N, 2)
        series["msle"][k] = msle(pos_t, pos_e)
        series["rmse"][k] = position_rmse(pos_t, pos_e)
        per_robot = nees(pose, x, P).reshape(T, N)
        rel = relative_nees(pose.reshape(T, N, 3), x.reshape(T, N, 3), P.reshape(T, N, 3, 3))
        series["nees"][k], series["nees_rel"][k] = per_robot.mean(1), rel.mean(1)
        exceed += (per_robot > NEES_EXCEED_3DOF).sum(1)
        exceed_rel += (rel > NEES_EXCEED_3DOF).sum(1)
    return series, exceed, exceed_rel


@pytest.mark.parametrize("capacity", [1, 4, 7, 256])
@pytest.mark.parametrize("stride", [1, 3])
def test_bulk_metrics_equal_the_per_step_metrics(capacity, stride):
    series = {k: np.full((STEPS, T), np.nan) for k in ("msle", "rmse", "nees", "nees_rel")}
    totals = {k: np.zeros(T, np.int64) for k in ("nees_samples", "nees_exceed", "nees_rel_exceed")}
    recorder = AccuracyRecorder(series, totals, T, N)
    recorder.capacity = min(capacity, recorder.capacity)
    recorded = []
    for k, (pose, x, P) in enumerate(_steps()):
        if (k + 1) % stride == 0 or k == STEPS - 1:
            recorded.append((k, (pose.copy(), x.copy(), P.copy())))
            recorder.add(k, pose, x, P)
            pose[:] = np.nan  # the caller reuses its arrays: the recorder must have copied
    assert recorder.filled == 0  # the last row empties the buffer without a flush call
    expected, exceed, exceed_rel = _per_step_reference(recorded)
    for key, values in expected.items():
        np.testing.assert_array_equal(series[key], values, err_msg=key)
    assert (totals["nees_samples"] == N * len(recorded)).all()
    np.testing.assert_array_equal(totals["nees_exceed"], exceed)
    np.testing.assert_array_equal(totals["nees_rel_exceed"], exceed_rel)


def test_flush_keeps_the_steps_before_a_divergence():
    series = {k: np.full((STEPS, T), np.nan) for k in ("msle", "rmse", "nees", "nees_rel")}
    totals = {k: np.zeros(T, np.int64) for k in ("nees_samples", "nees_exceed", "nees_rel_exceed")}
    recorder = AccuracyRecorder(series, totals, T, N)
    for k, (pose, x, P) in enumerate(_steps()):
        if k == 10:
            break
        recorder.add(k, pose, x, P)
    assert np.isnan(series["msle"][:10]).all()  # still buffered
    recorder.flush()
    assert np.isfinite(series["msle"][:10]).all() and np.isnan(series["msle"][10:]).all()
    recorder.flush()  # empty: nothing happens
    assert (totals["nees_samples"] == 10 * N).all()


def test_buffer_is_bounded_for_large_teams():
    robots = 2_000
    series = {"msle": np.zeros((10, 1))}
    recorder = AccuracyRecorder(series, {}, 1, robots)
    assert recorder.capacity == 1
    assert recorder.P.nbytes <= AccuracyRecorder.BUFFER_BYTES


def test_kernels_are_loaded_before_the_first_estimator_step(monkeypatch):
    events = []
    monkeypatch.setattr(runner, "warm_up_kernels", lambda **forms: events.append(forms))
    real_predict = lockstep.predict

    def predict(*args, **kwargs):
        events.append("predict")
        return real_predict(*args, **kwargs)

    monkeypatch.setattr(lockstep, "predict", predict)
    runner.run_scenario(
        default_scenario().replace(
            **{"run.steps": 2, "run.filters": ["ckf"], "run.dead_reckoning": False}
        )
    )
    # the paper's method: only the link loops' form without the options' stages
    assert events == [{"paper": True, "options": False}, "predict", "predict"]
