"""``resloc.experiments.compare.run`` and the command: tiny runs of the studies."""

from __future__ import annotations

import functools
import json

from typer.testing import CliRunner

from resloc.cli.app import app
from resloc.experiments import compare as cmp


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
