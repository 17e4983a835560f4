"""Scenario schema: validation errors name the field; TOML round-trips."""

import enum
import tomllib
from pathlib import Path

import pytest

from resloc.errors import ConfigError
from resloc.experiments.config import default_scenario
from resloc.experiments.config_dump import dump_scenario, scenario_to_dict
from resloc.experiments.config_parse import load_scenario, parse_scenario

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_default_scenario_is_the_paper_setup():
    s = default_scenario()
    assert s.world.team.robots == 17
    assert s.world.motion.dt == 0.033
    assert s.world.motion.v_max == 0.2 and s.world.motion.omega_max == 3.6
    assert s.world.sensing.radius == 1.0
    assert (s.world.sensing.range_std, s.world.sensing.bearing_std) == (0.005, 0.05)
    assert len(s.world.sdz) == 1 and len(s.world.cdz) == 1
    assert s.run.filters == ["ckf", "ukf", "ekf"]


def test_a_partial_file_is_the_default_without_its_zones(tmp_path):
    """What the README promises a partial scenario file: every key not set is the embedded
    default's, but the zone lists are the file's own (none here)."""
    p = tmp_path / "partial.toml"
    p.write_text("[run]\nsteps = 50\n", encoding="utf-8")
    s, d = load_scenario(p), default_scenario()
    assert s.run.steps == 50
    assert len(s.world.sdz) == 0 and len(s.world.cdz) == 0
    zoned = s.replace(**{"run.steps": d.run.steps})
    without_zones = {k: v for k, v in scenario_to_dict(d).items() if k not in ("sdz", "cdz")}
    assert scenario_to_dict(zoned) == without_zones


def test_dump_load_roundtrip(tmp_path):
    s = default_scenario().replace(**{"detector.rho": 0.7, "trigger.norm": "nis"})
    text = dump_scenario(s)
    assert parse_scenario(tomllib.loads(text)) == s
    p = tmp_path / "s.toml"
    p.write_text(text)
    assert load_scenario(p) == s


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"sensing": {"radiu": 1.0}}, "sensing.radiu: unknown key"),
        ({"sensnig": {}}, "sensnig: unknown section"),
        ({"sensing": {"radius": -1.0}}, "sensing.radius: -1.0 must be greater than 0"),
        ({"sensing": {"range_std": -0.1}}, "sensing.range_std: -0.1 is below the minimum"),
        ({"sensing": {"radius": "far"}}, "sensing.radius: expected a number, got string"),
        ({"team": {"robots": 1}}, "team.robots: 1 robots cannot localize"),
        ({"team": {"robots": 2.5}}, "team.robots: expected an integer"),
        ({"team": {"robots": True}}, "team.robots: expected an integer, got boolean"),
        ({"run": {"filters": ["ckf", "kf"]}}, "run.filters[1]: 'kf' is not one of"),
        ({"detector": {"norm": "l1"}}, "detector.norm: 'l1' is not one of euclidean"),
        ({"sdz": [{"center": [0, 0], "radius": 0}]}, "sdz[0].radius: 0 must be greater"),
        ({"sdz": [{"center": [0]}]}, "sdz[0].center: expected 2 numbers"),
        ({"cdz": [{"peak": 1.5}]}, "cdz[0].peak: 1.5 is above the maximum 1.0"),
        ({"motion": {"waypoints": [[0, 0]]}}, "motion.waypoints"),
        ({"attack": {"bias": [0.1, -0.2]}}, "attack.bias[1]: -0.2 is below the minimum"),
        ({"trigger": {"lambda2": "local"}}, "trigger.lambda2: 'local' is not one of"),
        ({"estimator": {"gauge_sums": "sum"}}, "estimator.gauge_sums: 'sum' is not one of exact"),
        ({"run": {"steps": 0}}, "run.steps: 0 is below the minimum 1"),
    ],
)
def test_bad_values_name_the_field(data, message):
    with pytest.raises(ConfigError) as info:
        parse_scenario(data, source="x.toml")
    text = str(info.value)
    assert "\n" not in text
    assert text.startswith("x.toml: ")
    assert message in text


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="no such scenario file"):
        load_scenario(tmp_path / "missing.toml")
    p = tmp_path / "bad.toml"
    p.write_text("[run\nsteps = 3")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scenario(p)


def test_replace_validates():
    with pytest.raises(ConfigError, match=r"detector\.rho"):
        default_scenario().replace(**{"detector.rho": -1.0})


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.toml")), ids=lambda p: p.name)
def test_examples_are_valid(path):
    load_scenario(path)


@pytest.mark.parametrize(
    ("section", "key", "value"),
    [("trigger", "lambda2", "distributed"), ("estimator", "gauge_sums", "consensus")],
)
def test_string_choices_are_enums(section, key, value):
    default = getattr(getattr(default_scenario(), section), key)
    assert isinstance(default, enum.StrEnum)
    changed = default_scenario().replace(**{f"{section}.{key}": value})
    chosen = getattr(getattr(changed, section), key)
    assert isinstance(chosen, enum.StrEnum) and chosen == value


def test_fusion_choices_are_the_registry():
    """``estimator.fusion`` accepts the registered strategies' names, and says which."""
    from resloc.cl.fusion import FusionMethod
    from resloc.cl.fusion_methods import FUSION_STRATEGIES

    with pytest.raises(ConfigError) as err:
        default_scenario().replace(**{"estimator.fusion": "bogus"})
    assert str(err.value) == (
        f"override: estimator.fusion: 'bogus' is not one of {', '.join(FUSION_STRATEGIES)}"
    )
    chosen = default_scenario().replace(**{"estimator.fusion": "ci"}).estimator.fusion
    assert chosen is FusionMethod.CI and chosen == "ci" and chosen.value == "ci"
    assert [m.value for m in FusionMethod] == list(FUSION_STRATEGIES)


def test_a_new_fusion_method_is_one_registry_entry(monkeypatch):
    """A strategy registered here (nowhere else) is a valid ``estimator.fusion`` and
    ``CLParams.fusion``, round-trips through TOML, and is what the runner calls."""
    from resloc.cl.fusion import FusionMethod
    from resloc.cl.fusion_methods import FUSION_STRATEGIES, FusionStrategy
    from resloc.cl.params import CLParams
    from resloc.experiments.runner import run_scenario

    updated_links: list[int] = []

    class CountingNaive(FusionStrategy):
        """The paper's fusion (the protocol's bodies), counting the links it fuses."""

        method = "counting_naive"

        def update(self, memory, x_i, P_i, i, j, x_j, P_j, P_j_ind, nu, m, params):
            updated_links.append(len(i))
            return super().update(memory, x_i, P_i, i, j, x_j, P_j, P_j_ind, nu, m, params)

    base = default_scenario().replace(
        **{"run.steps": 40, "team.robots": 5, "run.filters": ["ekf"], "run.dead_reckoning": False}
    )
    with pytest.raises(ConfigError, match="counting_naive"):
        base.replace(**{"estimator.fusion": "counting_naive"})
    with monkeypatch.context() as patch:
        patch.setitem(FUSION_STRATEGIES, "counting_naive", CountingNaive())
        mine = base.replace(**{"estimator.fusion": "counting_naive"})
        assert mine.estimator.fusion is FusionMethod("counting_naive")
        assert parse_scenario(tomllib.loads(dump_scenario(mine))) == mine
        assert CLParams(fusion="counting_naive").fusion == "counting_naive"
        ours = run_scenario(mine).summary()["ekf"]
    assert sum(updated_links) > 0
    naive = run_scenario(base).summary()["ekf"]  # the same fusion, dispatched as "naive"
    assert ours["msle_mean"] == pytest.approx(naive["msle_mean"], rel=1e-9)
    assert ours["comm_rate"] == naive["comm_rate"]
    # unregistered again: the name is refused everywhere
    with pytest.raises(ConfigError, match="counting_naive"):
        base.replace(**{"estimator.fusion": "counting_naive"})
    with pytest.raises(ConfigError, match=r"CLParams\.fusion"):
        CLParams(fusion="counting_naive")


def test_the_gate_strategy_validates_and_sets_the_threshold():
    """``detector.false_alarm`` is the norm gate's: a chi-square gate needs a chi-square norm
    (the message names the field and the fix), and then sets rho."""
    from resloc.cl.cusum import chi2_gate
    from resloc.cl.detection import NORM_GATE

    for norm in ("euclidean", "scaled"):
        with pytest.raises(ConfigError) as err:
            default_scenario().replace(**{"detector.norm": norm, "detector.false_alarm": 0.01})
        assert "detector.false_alarm: 0.01 sets a chi-square gate on the NIS" in str(err.value)
        assert f'set detector.norm = "nis" (now {norm!r})' in str(err.value)
    nis = default_scenario().replace(**{"detector.norm": "nis", "detector.false_alarm": 0.01})
    assert nis.cl_params().rho == pytest.approx(chi2_gate(0.01) ** 0.5)
    assert NORM_GATE.threshold(nis.detector) == nis.cl_params().rho
    plain = default_scenario().replace(**{"detector.norm": "nis", "detector.rho": 2.5})
    assert plain.cl_params().rho == 2.5
