"""The defence stages as strategies: config keys, the defences mapping, the per-robot CUSUM,
robot nodes equal to the batched engine with the new stages, and ``resloc mrclam``'s
``--noise auto`` / ``--paper-detector``."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from resloc.cl import kernels
from resloc.cl.detection_robot import robot_cusum
from resloc.cli.app import app
from resloc.errors import ConfigError
from resloc.experiments.config import default_scenario
from resloc.experiments.defences import DEFENCES, defence_overrides
from resloc.filters.base import make_filter
from test_node import assert_same, hot_scenario, run_batched, run_nodes, simulate

FIXTURE = Path(__file__).parent / "fixtures" / "mrclam" / "MRCLAM_Dataset6_60s"
runner = CliRunner()


def test_every_defence_is_a_valid_scenario_and_maps_to_its_params():
    base = default_scenario()
    for name in DEFENCES:
        params = base.replace(**defence_overrides(name)).cl_params()
        assert params.detector
    full = base.replace(**DEFENCES["full"]).cl_params()
    assert full.recovery and full.robot_cusum and full.cusum and full.mean_cusum
    assert full.recovery_gate == pytest.approx(13.8155, rel=1e-4)
    with pytest.raises(ConfigError, match="defence 'nope' is unknown; known defences: paper"):
        defence_overrides("nope")


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("detector.recovery_after", 0, "detector.recovery_after: 0 is below the minimum 1"),
        ("detector.recovery_false_alarm", 0.0, "must be greater than 0"),
        ("detector.recovery_inflation_cap", 0.5, "below the minimum 1.0"),
        ("detector.robot_cusum", "yes", "expected true or false"),
        ("detector.robot_cusum_h", -1.0, "must be greater than 0"),
    ],
)
def test_defence_keys_fail_with_one_line(key, value, message):
    with pytest.raises(ConfigError, match=message) as err:
        default_scenario().replace(**{key: value})
    assert "\n" not in str(err.value) and key in str(err.value)


def test_robot_cusum_sums_a_robots_rows_and_clips():
    robots, g = robot_cusum(
        np.array([1.0, 0.0]),
        np.array([0, 0, 3, 3]),
        np.array([5.0, 4.0, 1.0, 0.5]),
        np.full(4, 3.0),
        np.full(4, 2.5),
    )
    np.testing.assert_array_equal(robots, [0, 3])
    np.testing.assert_allclose(g, [2.5, 0.0])  # 1 + 2 + 1 clipped at 2.5; 0 - 2 - 2.5 -> 0


def test_robot_cusum_catches_a_lie_spread_over_rotating_links():
    """A 1.3-sigma range lie moved to a new link every 3 measurements: no per-link CUSUM
    reaches its threshold, the per-robot one does."""
    from resloc.cl.detection import Evidence, detect
    from resloc.cl.memory import LinkMemory
    from resloc.cl.params import CLParams

    params = CLParams(detector_norm="nis", rho=3.717, cusum=True, robot_cusum=True)
    memory = LinkMemory(100)
    S = np.diag([0.01, 0.0025])[None]
    robot_hits = link_hits = 0
    for k in range(300):
        nu = np.array([[0.1 * 2.2, 0.0]])  # NIS 4.84 > k = 3
        j = np.array([1 + k // 3])
        ev = Evidence(nu, S, np.sqrt([4.84]), np.array([0]), j, np.zeros(1, bool))
        detected = detect(ev, params, memory)
        link_hits += int(memory.cusum.get(np.array([0]), j)[0] > 20.0)
        robot_hits += int(detected[0])
    assert link_hits == 0
    assert robot_hits > 250


def test_robot_nodes_reproduce_the_batched_engine_with_recovery_and_robot_cusum():
    scenario = hot_scenario(12)
    params = replace(
        scenario.cl_params(),
        detector_norm="nis",
        rho=1.2,  # strict: rejection runs happen, so the recovery acts
        recovery=True,
        recovery_after=2.0,
        robot_cusum=True,
        robot_cusum_h=5.0,
    )
    world, x0, P0, ws_list = simulate(scenario, trials=1, seed=5)
    filt = make_filter("ekf")
    with kernels.use_backend("auto"):
        batched = run_batched(filt, params, world, x0, P0, ws_list)
        by_robot = run_nodes(filt, params, world, x0, P0, ws_list)
        strict = run_batched(filt, replace(params, recovery=False), world, x0, P0, ws_list)
    # The compiled kernel runs the per-robot stages (tests/test_kernels_defence.py).
    assert assert_same(batched, by_robot, ws_list, compiled=True) > 0
    detected = sum(int(h[2].detected.sum()) for h in batched)
    assert detected < sum(int(h[2].detected.sum()) for h in strict)  # re-admissions happened


def test_mrclam_noise_auto_feeds_the_fit_into_the_run(tmp_path):
    out = tmp_path / "run"
    args = ["mrclam", str(FIXTURE), "-f", "ekf", "--duration", "20", "--no-plots"]
    res = runner.invoke(app, [*args, "--noise", "auto", "--bearing-std", "0.02", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "noise fitted against ground truth" in res.output
    config = json.loads((out / "summary.json").read_text())["config"]
    assert config["bearing_std"] == 0.02  # an explicit option wins over the fit
    assert config["range_std_rel"] != 0.07 and config["odometry_density"] != [0.015, 0.04]
    assert config["detector_norm"] == "nis" and config["recovery"] is True
    paper = tmp_path / "paper"
    res = runner.invoke(app, [*args, "--paper-detector", "-o", str(paper)])
    assert res.exit_code == 0, res.output
    config = json.loads((paper / "summary.json").read_text())["config"]
    assert (config["detector_norm"], config["rho"], config["recovery"]) == ("euclidean", 1.0, False)
    bad = runner.invoke(app, [*args, "--noise", "guess", "-o", str(tmp_path / "x")])
    assert bad.exit_code == 2
    # 8 s of the excerpt hold no sighting with ground truth: one line, exit 2, nothing written.
    short = [*args[:5], "8", "--no-plots", "--noise", "auto", "-o", str(tmp_path / "y")]
    bad = runner.invoke(app, short)
    assert bad.exit_code == 2 and "cannot fit the sensor noise" in bad.output
    assert len(bad.output.strip().splitlines()) == 1 and not (tmp_path / "y").exists()
