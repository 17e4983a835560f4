"""End-to-end behaviour of the simulated system (seeded, short runs)."""

import dataclasses

import numpy as np
import pytest

from resloc.experiments.config import default_scenario
from resloc.experiments.runner import run_scenario
from resloc.world.spec import ZoneSpec


def _no_zones(s):
    return dataclasses.replace(s, world=dataclasses.replace(s.world, sdz=(), cdz=()))


def _with_zones(s, sdz=(), cdz=()):
    return dataclasses.replace(s, world=dataclasses.replace(s.world, sdz=sdz, cdz=cdz))


@pytest.fixture(scope="module")
def clean_run():
    s = _no_zones(default_scenario()).replace(**{"run.steps": 250, "run.trials": 2})
    return run_scenario(s)


def test_cl_beats_dead_reckoning_without_adversaries(clean_run):
    summ = clean_run.summary()
    dr = summ["dr"]["msle_mean"]
    for name in ("ckf", "ukf", "ekf"):
        assert summ[name]["msle_mean"] < 0.2 * dr, (name, summ[name]["msle_mean"], dr)
        assert summ[name]["repairs"] == 0
    assert not np.isnan(clean_run.estimators["ckf"].series["msle"]).any()


def test_run_is_reproducible_from_seed():
    s = default_scenario().replace(**{"run.steps": 60, "run.filters": ["ckf"]})
    a, b = run_scenario(s), run_scenario(s)
    np.testing.assert_array_equal(a.estimators["ckf"].track, b.estimators["ckf"].track)
    c = run_scenario(s, seed=1)
    assert not np.array_equal(a.estimators["ckf"].track, c.estimators["ckf"].track)


def _attack_scenario(detector: bool):
    # A strong sensing zone over the team's start: most links there are falsified by a random
    # injection. (With a *fixed* bias the paper's detector locks out and raises MSLE: a
    # constant bearing bias is indistinguishable from a heading error; docs/algorithm.md.)
    sdz = (ZoneSpec(center=[-0.9, -0.9], radius=0.9, peak=0.9),)
    s = _with_zones(default_scenario(), sdz=sdz).replace(
        **{
            "run.steps": 200,
            "run.trials": 2,
            "run.filters": ["ckf"],
            "attack.kind": "random",
            "attack.bias": [0.6, 1.2],
            "detector.enabled": detector,
        }
    )
    return run_scenario(s).summary()["ckf"]


def test_detector_lowers_msle_under_sdz_attack():
    on, off = _attack_scenario(True), _attack_scenario(False)
    assert on["attacked_rate"] > 0.2
    assert on["detector_recall"] > 0.5 and on["detector_precision"] > 0.95
    assert on["attacked_fused"] < 0.5 * off["attacked_fused"]
    assert on["msle_mean"] < 0.85 * off["msle_mean"], (on["msle_mean"], off["msle_mean"])


def test_cdz_jams_and_trigger_saves_messages():
    cdz = (ZoneSpec(center=[-0.9, -0.9], radius=0.9, peak=1.0),)
    base = _with_zones(default_scenario(), cdz=cdz).replace(
        **{"run.steps": 120, "run.filters": ["ckf"]}
    )
    jam = run_scenario(base).summary()["ckf"]
    assert jam["delivery_rate"] < 0.8
    always = run_scenario(base.replace(**{"trigger.enabled": False})).summary()["ckf"]
    assert always["comm_rate"] == pytest.approx(1.0)
    assert jam["comm_rate"] < always["comm_rate"]
