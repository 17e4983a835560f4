"""The public API: its names, the lazy top level, and the README's library examples run."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

import resloc
from resloc import api

ROOT = Path(__file__).resolve().parents[1]


def test_every_api_name_is_reachable_from_the_top_level() -> None:
    for name in api.__all__:
        assert getattr(resloc, name) is getattr(api, name), name
    assert set(api.__all__) <= set(dir(resloc))
    with pytest.raises(AttributeError, match="no attribute 'nonexistent'"):
        resloc.nonexistent  # noqa: B018


def test_import_resloc_stays_light() -> None:
    code = "import sys, resloc; print(sorted({'numpy', 'resloc.api'} & set(sys.modules)))"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == "[]"


def _readme_python_blocks() -> list[str]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_readme_library_examples_run(monkeypatch, capsys) -> None:
    """Every ``python`` block of the README, executed in order from the repository root."""
    blocks = _readme_python_blocks()
    assert len(blocks) >= 3
    if not (ROOT / "tests/fixtures/mrclam/MRCLAM_Dataset6_60s").is_dir():
        pytest.skip("MRCLAM fixture absent")
    monkeypatch.chdir(ROOT)
    for k, code in enumerate(blocks):
        namespace: dict = {}
        exec(compile(code, f"README.md python block {k}", "exec"), namespace)
        if "outcome" in namespace:
            assert len(namespace["outcome"].norm) == 1
        if "result" in namespace:
            assert namespace["result"].summary()["ckf"]["msle_mean"] > 0
        if "sweep" in namespace:
            assert namespace["sweep"].per_trial("ckf", "msle_mean").shape == (6, 2)
        if "replay" in namespace:
            assert namespace["replay"].summary()["ekf"]["position_rmse"] > 0
    assert "does not run in a robot process" in capsys.readouterr().out
