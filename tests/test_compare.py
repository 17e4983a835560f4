"""``resloc compare`` (issue 6): study definitions, a tiny run, the report and the CLI."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import pytest
from scipy.stats import chi2
from typer.testing import CliRunner

from resloc.cli.app import app
from resloc.experiments import compare as cmp
from resloc.experiments.config import load_scenario, scenario_to_dict

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


def test_nees_band():
    lo, hi = cmp.nees_band(3, 170)
    assert lo == pytest.approx(chi2.ppf(0.025, 510) / 170) and 2.6 < lo < 3.0 < hi < 3.4
    lo1, hi1 = cmp.nees_band(3, 1)
    assert lo1 == pytest.approx(0.216, abs=1e-3) and hi1 == pytest.approx(9.348, abs=1e-3)


def _tiny(**kw):
    return cmp.run_compare(quick=True, seeds=2, steps=30, robots=5, **kw)


def test_run_compare_tiny_and_report(tmp_path):
    res = _tiny(studies=("table", "fusion", "lambda2"))
    keys = {(r["scenario"], r["method"]) for r in res.table}
    assert ("sdz_stealthy", cmp.BEST) in keys and ("clean", cmp.PAPER) in keys
    row = next(r for r in res.table if r["scenario"] == "clean" and r["method"] == cmp.PAPER)
    assert row["msle"]["n"] == 2 and row["msle"]["mean"] > 0
    assert {r["method"] for r in res.fusion} == {"naive", cmp.NAIVE_REFERENCE, cmp.BEST}
    assert {r["mode"] for r in res.lambda2} == {"global", "distributed"}
    assert any(f"fusion {cmp.BEST}" in t["target"] for t in res.targets)
    assert not any(f"fusion {cmp.NAIVE_REFERENCE}" in t["target"] for t in res.targets)
    md = res.markdown()
    for heading in ("### Method x scenario", "### Fusion consistency", "### Targets"):
        assert heading in md
    files = cmp.save_compare(res, tmp_path, plots=False)
    assert {p.name for p in files} == {"compare.json", "compare.md", "roc.csv", "lambda2.csv"}
    data = json.loads((tmp_path / "compare.json").read_text())
    assert data["config"]["seeds"] == 2


def test_run_compare_roc_parallel():
    res = _tiny(studies=("roc",), jobs=2)
    gates = {r["gate"] for r in res.roc}
    assert gates == {"raw-norm", "nis"}
    for r in res.roc:
        assert 0.0 <= r["fpr"]["mean"] <= 1.0


def test_cli_compare(tmp_path, monkeypatch):
    tiny = functools.partial(cmp.run_compare, steps=20, robots=4, studies=("table",))
    monkeypatch.setattr(cmp, "run_compare", tiny)
    out = tmp_path / "cmp"
    r = CliRunner().invoke(
        app, ["compare", "--quick", "--seeds", "2", "--out", str(out), "--no-plots"]
    )
    assert r.exit_code == 0, r.output
    assert "### Method x scenario" in r.output
    assert (out / "compare.md").exists()
    bad = CliRunner().invoke(app, ["compare", "--seeds", "1", "--out", str(tmp_path / "x")])
    assert bad.exit_code == 2
