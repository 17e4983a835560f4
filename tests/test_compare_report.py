"""``resloc.experiments.compare.report`` and the ROC figure: rows, targets, Markdown, files,
from synthetic cell outputs (no simulation)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.stats import chi2

from resloc.experiments import compare as cmp
from resloc.experiments.compare.report import compare_result
from resloc.experiments.plots import compare as roc_plot


def test_nees_band():
    lo, hi = cmp.nees_band(3, 170)
    assert lo == pytest.approx(chi2.ppf(0.025, 510) / 170) and 2.6 < lo < 3.0 < hi < 3.4
    lo1, hi1 = cmp.nees_band(3, 1)
    assert lo1 == pytest.approx(0.216, abs=1e-3) and hi1 == pytest.approx(9.348, abs=1e-3)


def _metrics(msle, nees=3.0, tpr=0.9, fpr=0.01):
    n = len(msle)
    full = {k: np.full(n, v) for k, v in (("nees", nees), ("tpr", tpr), ("fpr", fpr))}
    rest = ("msle_final", "rmse", "nees_rel", "comm_rate", "bytes_per_step", "attacked_fused")
    return {"msle": np.asarray(msle), **full, **{k: np.full(n, 0.5) for k in rest}}


def _cell(study, scenario, method, msle, **metrics):
    task = {
        "study": study,
        "scenario_key": scenario,
        "scenario_label": scenario.upper(),
        "method_key": method,
        "method_label": method.upper(),
        "label": f"{study}: {scenario} / {method}",
    }
    m = {**_metrics(msle, **metrics), "repairs": 0, "wall_time_s": 1.0}
    return {"task": task, "metrics": m}


def _result():
    outputs = [
        _cell("table", "clean", cmp.PAPER, [1.0, 1.2]),
        _cell("table", "sdz_stealthy", cmp.PAPER, [9.0, 11.0]),
        _cell("table", "clean", cmp.BEST, [1.0, 1.0]),
        _cell("table", "sdz_stealthy", cmp.BEST, [2.0, 2.2]),
        _cell("fusion", "default", cmp.NAIVE_REFERENCE, [1.0, 1.0], nees=400.0),
        _cell("fusion", "default", cmp.BEST, [1.5, 1.5], nees=3.0),
    ]
    roc = _cell("roc", "sdz_stealthy", "nis", [1.0, 2.0, 3.0, 4.0], tpr=0.5)
    roc["task"].update({"values": [0.3, 0.01], "threshold_name": "p_fa", "seeds": 2})
    roc["metrics"]["fpr"] = np.array([0.3, 0.2, 0.01, 0.0])
    lam = _cell("lambda2", "clean", "distributed", [1.0, 1.0])
    lam["task"]["robots"] = 5
    lam["lambda2"] = {"true_mean": 2.0, "estimate_mean": 2.1, "abs_rel_error_after_warmup": 0.05}
    config = {"quick": True, "seeds": 2, "steps": 30, "filter": "ckf", "jobs": 1}
    config.update({"robots": 5, "wall_time_s": 1.0, "cells": 8})
    return compare_result(config, [*outputs, roc, lam])


def test_rows_and_targets():
    res = _result()
    assert (res.table[0]["scenario"], res.table[0]["method"]) == ("clean", cmp.PAPER)
    assert res.table[0]["msle"]["mean"] == pytest.approx(1.1) and res.table[0]["msle"]["n"] == 2
    met = {t["target"]: t["met"] for t in res.targets}
    assert met[f"stealthy: {cmp.BEST} MSLE within 3x of its clean run"] is True  # x2.1
    assert met["stealthy: the paper's configuration far worse than 3x of its clean run"] is True
    fusion = next(t for t in res.targets if t["target"].startswith(f"fusion {cmp.BEST}"))
    assert fusion["met"] is True and "MSLE x1.5" in fusion["measured"]
    assert [(r["threshold"], r["fpr"]["mean"]) for r in res.roc] == [(0.3, 0.25), (0.01, 0.005)]
    assert res.lambda2[0]["lambda2_abs_rel_error"] == 0.05


def test_markdown_csv_json_and_roc_figure(tmp_path, monkeypatch):
    res = _result()
    md = res.markdown()
    assert "| SDZ_STEALTHY | PAPER | 10 ± 12.7 |" in md
    assert (
        "| sdz_stealthy | nis | p_fa = 0.3 | 0.500 ± 0.000 | 0.2500 ± 0.6353 | 1.5 ± 6.35 |" in md
    )
    layouts = []
    save = roc_plot.save

    def recording_save(plt, fig, path, **kw):
        layouts.append(fig.get_layout_engine())
        return save(plt, fig, path, **kw)

    monkeypatch.setattr(roc_plot, "save", recording_save)
    files = {p.name for p in cmp.save_compare(res, tmp_path)}
    assert files == {"compare.json", "compare.md", "roc.csv", "lambda2.csv", "roc.png"}
    assert type(layouts[0]).__name__ == "ConstrainedLayoutEngine"
    assert (tmp_path / "roc.png").read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "roc.csv").read_text().splitlines()[1:] == [
        "sdz_stealthy,nis,p_fa,0.3,0.5,0.25,1.5",
        "sdz_stealthy,nis,p_fa,0.01,0.5,0.005,3.5",
    ]
    assert json.loads((tmp_path / "compare.json").read_text())["config"]["cells"] == 8
