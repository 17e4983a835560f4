"""The validation layer: every number finite and bounded, names one line, memory estimated
before allocating; each failure one line naming the field (issue: never crash)."""

from __future__ import annotations

import math

import pytest

from resloc.errors import ConfigError
from resloc.experiments.config import default_scenario
from resloc.experiments.config_dump import dump_scenario
from resloc.experiments.config_parse import load_scenario, parse_scenario
from resloc.experiments.runner import check_run_size, run_bytes
from resloc.validation import (
    INT64_MAX,
    cap_workers,
    check_finite,
    check_memory,
    check_one_line_name,
    check_seed,
)

HUGE = (math.inf, -math.inf, 1e300)

# Every float field the audit broke with inf or 1e300 (tracebacks), plus the rest.
FLOAT_FIELDS = [
    ("team", "spacing"),
    ("team", "leader_gap"),
    ("team", "init_pos_std"),
    ("team", "init_heading_std"),
    ("motion", "dt"),
    ("motion", "v_max"),
    ("motion", "omega_max"),
    ("motion", "leader_speed"),
    ("motion", "gain"),
    ("motion", "projection"),
    ("sensing", "radius"),
    ("sensing", "comm_radius"),
    ("sensing", "range_std"),
    ("sensing", "bearing_std"),
    ("estimator", "ukf_alpha"),
    ("estimator", "ukf_beta"),
    ("estimator", "ukf_kappa"),
    ("detector", "rho"),
    ("detector", "cusum_k"),
    ("detector", "cusum_h"),
    ("detector", "mean_cusum_k"),
    ("detector", "mean_cusum_h"),
    ("trigger", "alpha"),
    ("trigger", "gamma"),
    ("trigger", "zeta_s"),
    ("trigger", "zeta_c"),
    ("trigger", "risk_factor_floor"),
    ("attack", "link_fraction"),
    ("attack", "stealth_margin"),
]


def _error(data: dict) -> str:
    with pytest.raises(ConfigError) as info:
        parse_scenario(data, source="s.toml")
    text = str(info.value)
    assert "\n" not in text and text.startswith("s.toml: ")
    return text


@pytest.mark.parametrize(("section", "key"), FLOAT_FIELDS)
@pytest.mark.parametrize("value", HUGE)
def test_non_finite_and_absurd_floats_are_one_line_errors(section, key, value):
    text = _error({section: {key: value}})
    assert f"{section}.{key}:" in text


@pytest.mark.parametrize(
    ("section", "key", "length"),
    [
        ("motion", "odometry_std", 2),
        ("motion", "process_floor_std", 3),
        ("attack", "bias", 2),
        ("attack", "stealth_direction", 2),
    ],
)
@pytest.mark.parametrize("value", HUGE)
def test_non_finite_list_items(section, key, length, value):
    text = _error({section: {key: [value] + [0.1] * (length - 1)}})
    assert f"{section}.{key}[0]:" in text


def test_zone_values_are_bounded():
    assert "sdz[0].center[1]:" in _error({"sdz": [{"center": [0.0, math.inf]}]})
    assert "cdz[0].radius:" in _error({"cdz": [{"radius": 1e300}]})


@pytest.mark.parametrize(
    ("data", "needle"),
    [
        ({"estimator": {"ukf_kappa": -3.0}}, "estimator.ukf_kappa: -3.0 must be greater than -3"),
        ({"estimator": {"ukf_alpha": 0.0}}, "estimator.ukf_alpha: 0.0 is below the minimum"),
        ({"estimator": {"gauge_rounds": 10**15}}, "estimator.gauge_rounds: 1000000000000000 is"),
        ({"sensing": {"range_std": 0.0}}, "makes the covariance singular"),
        ({"sensing": {"bearing_std": 0.0}}, "sensing.bearing_std: 0.0 is below the minimum"),
        ({"team": {"init_pos_std": 0.0}}, "team.init_pos_std"),
        ({"motion": {"process_floor_std": [0.0, 0.0, 0.0]}}, "motion.process_floor_std[0]"),
        ({"motion": {"dt": 1e-7}}, "motion.dt: 1e-07 is below the minimum 0.0001"),
        ({"trigger": {"zeta_s": math.inf}}, "trigger.zeta_s: inf is not allowed"),
        ({"run": {"seed": 2**64}}, "run.seed: 18446744073709551616 is above the maximum"),
        ({"run": {"name": "two\nlines"}}, "run.name: contains the control character '\\n'"),
        ({"run": {"name": ""}}, "run.name: empty"),
        ({"run": {"name": 5}}, "run.name: expected a string"),
        ({"team": {"robots": True}}, "team.robots: expected an integer, got boolean"),
        ({"detector": {"rho": "big"}}, "detector.rho: expected a number, got string"),
        ({"motion": {"waypoints": [[0, "a"], [1, 1]]}}, "motion.waypoints[0][1]: expected a"),
        ({"motion": {"waypoints": [1, 2]}}, "motion.waypoints[0]: expected [x, y]"),
        ({"motion": {"waypoints": [{"x": 1}, [0, 0]]}}, "motion.waypoints[0]: expected [x, y]"),
        ({"motion": {"waypoints": [[0, 0, 0], [1, 1]]}}, "motion.waypoints[0]: expected [x, y]"),
        ({"motion": {"waypoints": [[0, 1e300], [1, 1]]}}, "motion.waypoints[0][1]: 1e+300"),
        ({"motion": {"waypoints": ["arc", [0, 0], [1, 1]]}}, "motion.waypoints[0]: 'arc'"),
        ({"motion": {"waypoints": [[0, True], [1, 1]]}}, "motion.waypoints[0][1]: expected"),
    ],
)
def test_each_audit_case_names_its_field(data, needle):
    assert needle in _error(data)


def test_allowed_values_at_the_bounds_still_parse():
    s = parse_scenario(
        {
            "estimator": {"ukf_kappa": -2.5, "ukf_alpha": 1.0, "gauge_rounds": 1000},
            "sensing": {"range_std": 1e-6, "bearing_std": 1e-6},
            "run": {"seed": INT64_MAX, "name": "gain $\\alpha$ = 0.3 — ünïcode"},
        }
    )
    assert s.run.seed == INT64_MAX


def test_names_and_seeds_round_trip_through_scenario_toml(tmp_path):
    s = default_scenario().replace(
        **{"run.name": 'quote " back\\slash $x^2$ end', "run.seed": INT64_MAX}
    )
    p = tmp_path / "s.toml"
    p.write_text(dump_scenario(s), encoding="utf-8")
    assert load_scenario(p) == s


def test_utf8_byte_order_mark_is_accepted(tmp_path):
    p = tmp_path / "bom.toml"
    p.write_bytes(b"\xef\xbb\xbf[team]\nrobots = 5\n")
    assert load_scenario(p).world.team.robots == 5


def test_run_memory_estimate_refuses_the_allowed_maxima_before_allocating(monkeypatch):
    import resloc.validation as validation

    monkeypatch.setattr(validation, "available_memory", lambda: 8 * 2**30)
    big = default_scenario().replace(**{"team.robots": 200_000, "run.steps": 10})
    assert run_bytes(big) > 8 * 2**30
    with pytest.raises(ConfigError, match=r"team.robots = 1 x 200000 robots.*more than"):
        check_run_size(big)
    trials = default_scenario().replace(**{"team.robots": 5, "run.trials": 1_000_000})
    with pytest.raises(ConfigError, match=r"lower team\.robots, run\.trials or run\.steps"):
        check_run_size(trials)
    check_run_size(default_scenario())  # the default fits easily


def test_helpers():
    assert check_finite("x", 2, 0, 3) == 2.0
    with pytest.raises(ConfigError, match="x: 0 is out of range; use > 0"):
        check_finite("x", 0, 0, 3, lo_open=True)
    with pytest.raises(ConfigError, match="--seed: 9223372036854775808 is outside"):
        check_seed("--seed", INT64_MAX + 1)
    with pytest.raises(ConfigError, match="control character"):
        check_one_line_name("n", "a\rb")
    with pytest.raises(ConfigError, match=r"needs about 1\.0 GiB"):
        check_memory(2**30, "thing", "use less", available=2**20)
    check_memory(2**20, "thing", "use less", available=2**30)
    assert cap_workers(100, cells=3, cores=2) == 2
    assert cap_workers(100, cells=1, cores=8) == 1
    assert cap_workers(4, cells=10, cores=8) == 4
