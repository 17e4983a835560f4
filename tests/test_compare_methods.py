"""``resloc.experiments.compare.methods``: the catalogue matches the example files."""

from __future__ import annotations

from pathlib import Path

import pytest

from resloc.experiments import compare as cmp
from resloc.experiments.compare.methods import FUSION_METHODS, ROC_GATES
from resloc.experiments.config import default_scenario
from resloc.experiments.config_dump import scenario_to_dict
from resloc.experiments.config_parse import load_scenario

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "beyond"


@pytest.mark.parametrize("sc", cmp.SCENARIOS + cmp.EXTRA_SCENARIOS, ids=lambda s: s.key)
def test_example_files_match_the_study(sc):
    """examples/beyond/<key>.toml is the study's scenario (the paper's method)."""
    study = cmp.study_scenario(sc, cmp.METHODS[0], 10, 1000)
    example = load_scenario(EXAMPLES / f"{sc.key}.toml")
    a, b = scenario_to_dict(study), scenario_to_dict(example)
    for section in ("attack", "detector", "estimator", "trigger", "team", "sensing"):
        assert a[section] == b[section], section
    assert a.get("sdz", []) == b.get("sdz", []) and a.get("cdz", []) == b.get("cdz", [])


def test_resilient_example_is_the_best_combination():
    sc = load_scenario(EXAMPLES / "resilient.toml")
    best = next(m for m in cmp.METHODS if m.key == cmp.BEST)
    d = scenario_to_dict(sc)
    for dotted, value in best.changes.items():
        section, key = dotted.split(".")
        assert d[section][key] == value
    assert d["trigger"]["lambda2"] == "distributed"


def test_every_method_is_a_valid_scenario_and_keys_are_unique():
    for methods in (cmp.METHODS, FUSION_METHODS):
        assert len({m.key for m in methods}) == len(methods)
        for m in methods:
            default_scenario().replace(**m.changes)
    assert cmp.NAIVE_REFERENCE in {m.key for m in FUSION_METHODS}


def test_roc_gates_list_their_thresholds_strictest_first():
    """The ROC figure joins the points from the loosest threshold: each gate's values must be
    ordered by how much they discard (rho rising, false-alarm probability falling)."""
    by_key = {g.key: g for g in ROC_GATES}
    rho, nis = by_key["raw-norm"], by_key["nis"]
    assert list(rho.values) == sorted(rho.values) and rho.option == "rho"
    assert list(nis.values) == sorted(nis.values, reverse=True) and nis.option == "false_alarm"
    default_scenario().replace(**nis.changes, **{"detector.false_alarm": nis.values[0]})
