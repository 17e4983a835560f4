"""The lockstep runner's bookkeeping: per-trial totals are booked into their own trial."""

from __future__ import annotations

import numpy as np

from resloc.experiments import lockstep, runner
from resloc.experiments.config import default_scenario
from resloc.experiments.metrics import detector_scores

SMALL = {
    "run.steps": 25,
    "run.trials": 3,
    "run.filters": ["ekf"],
    "run.dead_reckoning": False,
    "team.robots": 5,
}


def test_covariance_repairs_are_booked_into_their_trial(monkeypatch) -> None:
    """Every fused link of trial 1 is marked repaired: trials 0 and 2 must stay at 0."""
    scenario = default_scenario().replace(**SMALL)
    N = scenario.world.team.robots
    flagged = np.zeros(scenario.run.trials, dtype=np.int64)
    real_correct = lockstep.correct

    def correct_marking_trial_one(filt, x, P, links, params, memory=None):
        x, P, out = real_correct(filt, x, P, links, params, memory)
        mark = out.fused & (links.i // N == 1)
        out.repaired = out.repaired | mark
        flagged[1] += int(mark.sum())
        return x, P, out

    monkeypatch.setattr(lockstep, "correct", correct_marking_trial_one)
    result = runner.run_scenario(scenario)
    assert flagged[1] > 0
    np.testing.assert_array_equal(result.estimators["ekf"].totals["repairs"], flagged)
    assert result.summary()["ekf"]["repairs"] == flagged.sum()


def test_per_trial_confusion_counts_are_the_detector_scores_of_each_trial(monkeypatch) -> None:
    zone = {"center": [0.0, 0.0], "radius": 5.0, "peak": 0.5}
    scenario = default_scenario().replace(**SMALL, **{"detector.rho": 0.05, "sdz": [zone]})
    N = scenario.world.team.robots
    seen: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    real_correct = lockstep.correct

    def correct_recording(filt, x, P, links, params, memory=None):
        x, P, out = real_correct(filt, x, P, links, params, memory)
        seen.append((links.i // N, out.detected.copy()))
        return x, P, out

    monkeypatch.setattr(lockstep, "correct", correct_recording)
    world_attacked: list[np.ndarray] = []
    real_step = runner.World.step

    def step_recording(self):
        ws = real_step(self)
        world_attacked.append(np.asarray(ws.attacked, bool))
        return ws

    monkeypatch.setattr(runner.World, "step", step_recording)
    totals = runner.run_scenario(scenario).estimators["ekf"].totals
    trial = np.concatenate([t for t, _ in seen])
    detected = np.concatenate([d for _, d in seen])
    attacked = np.concatenate(world_attacked)
    assert detected.any() and attacked.any()
    for t in range(scenario.run.trials):
        want = detector_scores(detected[trial == t], attacked[trial == t])
        for key in ("tp", "fp", "fn", "tn"):
            assert totals[key][t] == want[key], (t, key)
