"""The one estimator loop (``resloc.experiments.lockstep``) of simulated runs and MRCLAM
replays: both step every estimator through it, and a diverging estimator is stopped and
reported in both while the others finish unchanged."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import numpy as np
import pytest

from resloc.datasets.mrclam import load_mrclam
from resloc.errors import NumericalError
from resloc.experiments import lockstep
from resloc.experiments.config import default_scenario
from resloc.experiments.mrclam import DEAD_RECKONING, MRCLAMConfig, run_mrclam, save_mrclam
from resloc.experiments.runner import run_scenario

FIXTURE = Path(__file__).parent / "fixtures" / "mrclam" / "MRCLAM_Dataset6_60s"
SRC = Path(__file__).resolve().parents[1] / "src" / "resloc"
SMALL = {"run.steps": 30, "run.trials": 2, "team.robots": 5, "run.filters": ["ekf", "ckf"]}


@pytest.fixture(scope="module")
def data():
    return load_mrclam(FIXTURE)


def _fail_from(monkeypatch, kind: str, call: int) -> None:
    """Make ``correct`` of the filter class named ``kind`` raise from its ``call``-th call."""
    real = lockstep.correct
    calls = {"n": 0}

    def correct(filt, x, P, links, params, memory=None):
        if type(filt).__name__ == kind:
            calls["n"] += 1
            if calls["n"] >= call:
                raise NumericalError("injected failure")
        return real(filt, x, P, links, params, memory)

    monkeypatch.setattr(lockstep, "correct", correct)


def test_every_step_of_both_runs_goes_through_the_one_loop(monkeypatch, data):
    real = lockstep._step_estimator
    steps: dict[str, int] = {}

    def counted(est, step, setup):
        steps[est.name] = steps.get(est.name, 0) + 1
        return real(est, step, setup)

    monkeypatch.setattr(lockstep, "_step_estimator", counted)
    run_scenario(default_scenario().replace(**SMALL))
    assert steps == {"ekf": 30, "ckf": 30, DEAD_RECKONING: 30}
    steps.clear()
    result = run_mrclam(data, MRCLAMConfig(filters=("ekf",), duration=2.0))
    K = result.info["steps"]
    assert steps == {"ekf": K, DEAD_RECKONING: K}


def test_only_the_lockstep_module_runs_the_cl_step_in_experiments():
    """A second estimator loop would import ``predict`` / ``correct`` again."""
    users = []
    for path in sorted((SRC / "experiments").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module == "resloc.cl.step":
                names = {a.name for a in node.names}
                if names & {"predict", "correct"}:
                    users.append(path.relative_to(SRC).as_posix())
    assert users == ["experiments/lockstep.py"]


def test_a_failing_step_stops_one_estimator_of_a_simulated_run(monkeypatch):
    scenario = default_scenario().replace(**SMALL)
    clean = run_scenario(scenario)
    _fail_from(monkeypatch, "ExtendedFilter", 7)
    result = run_scenario(scenario)
    ekf = result.estimators["ekf"]
    assert ekf.diverged["step"] == 7 and ekf.diverged["reason"] == "injected failure"
    assert np.isnan(ekf.track[7:]).all() and np.isfinite(ekf.track[:7]).all()
    assert np.isnan(result.summary()["ekf"]["msle_mean"])
    for name in ("ckf", DEAD_RECKONING):  # the others are untouched
        np.testing.assert_array_equal(result.estimators[name].track, clean.estimators[name].track)


def test_a_failing_step_stops_one_estimator_of_a_replay(monkeypatch, data, tmp_path):
    config = MRCLAMConfig(filters=("ekf", "ckf"), duration=20.0)
    clean = run_mrclam(data, config)
    _fail_from(monkeypatch, "ExtendedFilter", 10)  # some step after a few sightings
    result = run_mrclam(data, config)
    ekf = result.estimators["ekf"]
    k = ekf.diverged["step"]
    assert ekf.diverged["reason"] == "injected failure" and 1 <= k < result.info["steps"]
    assert np.isnan(ekf.track[k:]).all() and np.isfinite(ekf.track[:k]).all()
    np.testing.assert_array_equal(ekf.track[:k], clean.estimators["ekf"].track[:k])
    later = result.measurements["step"] >= k
    assert not ekf.links["fused"][later].any() and ekf.links["fused"][~later].any()
    s = result.summary()["ekf"]
    assert np.isnan(s["position_rmse"]) and s["diverged_step"] == k
    for name in ("ckf", DEAD_RECKONING):
        np.testing.assert_array_equal(result.estimators[name].track, clean.estimators[name].track)
        got, want = (
            {k: v for k, v in r.summary()[name].items() if k != "wall_time_s"}
            for r in (result, clean)
        )
        assert got == pytest.approx(want, nan_ok=True)
    save_mrclam(result, tmp_path, plots=False)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["diverged"]["ekf"]["step"] == k and set(summary["diverged"]) == {"ekf"}


def test_a_replay_stops_a_filter_whose_covariance_turns_indefinite(data):
    """A real divergence: the UKF (negative centre weight) started with a 1.5 rad heading
    error loses positive definiteness; it is stopped there, the CKF finishes."""
    config = MRCLAMConfig(filters=("ukf", "ckf"), init_std=(0.02, 1.5), duration=20.0)
    result = run_mrclam(data, config)
    ukf, ckf = result.estimators["ukf"], result.estimators["ckf"]
    k = ukf.diverged["step"]
    assert 1 <= k < result.info["steps"]
    assert np.isnan(ukf.cov[k:]).all() and np.isfinite(ukf.nees[:k][result.valid[:k]]).all()
    assert ckf.diverged is None and np.isfinite(ckf.overall["position_rmse"])
    assert np.isnan(ukf.overall["position_rmse"]) and np.isnan(ukf.overall["nees_mean"])


def test_resloc_mrclam_reports_a_diverged_filter_and_writes_the_others(monkeypatch, tmp_path):
    from typer.testing import CliRunner

    from resloc.cli.app import app

    _fail_from(monkeypatch, "ExtendedFilter", 10)
    out = tmp_path / "out"
    args = ["mrclam", str(FIXTURE), "-f", "ekf", "--duration", "20", "--no-plots", "-o", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    err = res.stderr if hasattr(res, "stderr") else res.output
    assert "warning: EKF diverged at step" in err and "diverged" in res.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["diverged"]) == {"ekf"}
    assert summary["overall"]["dr"]["position_rmse"] is not None
