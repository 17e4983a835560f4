"""``resloc reproduce``: the experiment list, the example files, and the --quick report."""

import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from resloc.cli.app import app
from resloc.experiments.config_parse import load_scenario
from resloc.experiments.reproduce import FIGURES, SECTIONS, experiments, write_examples
from resloc.experiments.stats import Verdict
from resloc.experiments.sweep import load_sweep

runner = CliRunner()
EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "paper"


def test_experiments_cover_the_paper():
    exps = {e.key: e for e in experiments()}
    assert list(exps) == [
        "fig4a",
        "fig4b",
        "fig4c",
        "fig5a",
        "fig5a_zeta0",
        "fig5b",
        "fig5c",
        "fig5d",
    ]
    assert not exps["fig4a"].base().world.sdz and not exps["fig4a"].base().world.cdz
    b = exps["fig4b"].base().world.attack
    assert b.links.value == "partial" and b.link_fraction == 0.5
    assert exps["fig4c"].base().world.attack.links.value == "full"
    assert exps["fig5a"].values == (0.2, 0.3, 0.4, 0.5)
    assert exps["fig5a"].parameter == "zones.radius"
    # The ablation: the same radii with the adaptive risk term of eq. (11) off.
    ablation = exps["fig5a_zeta0"]
    assert ablation.values == exps["fig5a"].values and ablation.parameter == "zones.radius"
    assert ablation.base().trigger.zeta_s == 0.0 and ablation.base().trigger.zeta_c == 0.0
    assert exps["fig5b"].parameter == "detector.rho"
    assert exps["fig5c"].parameter == "trigger.alpha"
    n = exps["fig5d"].values
    assert exps["fig5d"].parameter == "team.robots" and min(n) <= 5 and max(n) >= 40
    assert {12, 25} <= set(n) and exps["fig5d"].base().run.filters == ["ckf", "ukf", "ekf"]
    # Sweeps contain the default's value, so they cross the Fig. 4c scenario.
    d = exps["fig4c"].base()
    assert d.detector.rho in exps["fig5b"].values and d.trigger.alpha in exps["fig5c"].values
    assert d.world.team.robots in n


def test_example_files_match_the_experiments(tmp_path):
    """examples/paper/ is generated from experiments(); regenerate it when this fails:
    python -m resloc.experiments.reproduce --write-examples examples/paper"""
    for exp in experiments():
        path = EXAMPLES / exp.filename
        assert path.is_file(), path
        assert path.read_text() == exp.example_text(), f"{path} is stale"
        if exp.is_sweep:
            assert load_sweep(path) == exp.sweep()
        else:
            assert load_scenario(path) == exp.base()
    written = write_examples(tmp_path)
    assert sorted(p.name for p in written) == sorted(p.name for p in EXAMPLES.glob("*.toml"))


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("rep") / "report"
    res = runner.invoke(app, ["reproduce", "--quick", "--jobs", "1", "--out", str(out)])
    return res, out


def test_quick_report_has_every_section_and_figure(quick_report):
    res, out = quick_report
    assert res.exit_code == 0, res.output
    assert f"report written to {out}/report.md" in res.output
    assert "paper claims vs measured" in res.output and "verdict" in res.output
    md = (out / "report.md").read_text()
    page = (out / "report.html").read_text()
    headings = re.findall(r"^## (.+)$", md, flags=re.M)
    assert headings == list(SECTIONS)
    for h in SECTIONS:
        assert h in page
    for name in FIGURES:
        assert (out / "figures" / name).stat().st_size > 1000, name
        assert f"(figures/{name})" in md, name
    assert page.count('src="data:image/png;base64,') == len(FIGURES)
    assert "Quick run" in md
    assert (out / "results.json").is_file()
    for exp in experiments():
        assert (out / "scenarios" / exp.filename).is_file()


def test_quick_report_claims(quick_report):
    _, out = quick_report
    results = json.loads((out / "results.json").read_text())
    claims = results["claims"]
    assert len(claims) >= 9
    assert {c["verdict"] for c in claims} <= {v.value for v in Verdict}
    assert results["seeds"] == 2 and results["quick"] is True
    text = " ".join(c["claim"] for c in claims)
    for needle in (
        "lowest MSLE",
        "partial-link",
        "full-link",
        "communication rate rises",
        "detection threshold",
        "communication rate decreases",
        "N = 25",
    ):
        assert needle in text, needle
    # Every measured value carries a mean ± CI.
    assert all("±" in c["measured"] for c in claims)
    md = (out / "report.md").read_text()
    table = md.split("## Paper claims vs measured", 1)[1].split("\n## ", 1)[0]
    assert sum(line.startswith("| ") for line in table.splitlines()) == len(claims) + 1
    # The parameters section lists the values used and the reasons for chosen ones.
    params = md.split("## Parameters", 1)[1].split("\n## ", 1)[0]
    assert "chosen" in params and "[detector]" in params and "rho" in params


def test_reproduce_refuses_existing_output(tmp_path):
    out = tmp_path / "keep"
    out.mkdir()
    (out / "x.txt").write_text("data")
    res = runner.invoke(app, ["reproduce", "--quick", "--out", str(out)])
    assert res.exit_code == 2
    err = res.stderr if hasattr(res, "stderr") else res.output
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "--overwrite" in lines[0]
    assert (out / "x.txt").read_text() == "data"
