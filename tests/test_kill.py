"""Kill ``resloc run`` at seeded random moments (SIGTERM, SIGKILL, SIGINT): no orphan
process, ``--out`` always holds a complete result set (the old or the new one), and no
temporary survives the next run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

SCENARIO = '[run]\nsteps = 150\nfilters = ["ckf", "ekf"]\n[team]\nrobots = 6\n'
COMPLETE = {"scenario.toml", "summary.json", "timeseries.csv", "trajectories.csv"}


def _resloc(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", "from resloc.cli.app import main; main()", *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group: orphans are findable
    )


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def _assert_complete(out: Path) -> None:
    names = {p.name for p in out.iterdir()}
    assert names >= COMPLETE, names
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["estimators"]) == {"ckf", "ekf", "dr"}


def _litter(root: Path) -> list[str]:
    return sorted(p.name for p in root.iterdir() if p.name.startswith(".out."))


def test_kills_at_random_moments_lose_nothing_and_leave_nothing(tmp_path: Path):
    scenario = tmp_path / "k.toml"
    scenario.write_text(SCENARIO)
    out = tmp_path / "out"
    args = ["run", str(scenario), "--out", str(out), "--overwrite", "--no-progress"]
    first = _resloc(args)
    t0 = time.perf_counter()
    assert first.wait(timeout=120) == 0, first.stderr.read()
    duration = time.perf_counter() - t0
    _assert_complete(out)

    rng = np.random.default_rng(20261123)
    kinds = [signal.SIGTERM, signal.SIGKILL, signal.SIGINT] * 2
    outcomes = []
    for kind in kinds:
        proc = _resloc(args)
        time.sleep(float(rng.uniform(0.1, 1.1 * duration)))
        proc.send_signal(kind)
        try:
            code = proc.wait(timeout=60)
        except subprocess.TimeoutExpired:  # pragma: no cover - the failure we test for
            os.killpg(proc.pid, signal.SIGKILL)
            pytest.fail(f"resloc run did not stop within 60 s of {kind.name}")
        err = proc.stderr.read()
        proc.stderr.close()
        # No orphan: the whole process group is gone.
        deadline = time.monotonic() + 10
        while _group_alive(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _group_alive(proc.pid), f"orphan processes after {kind.name}"
        assert "Traceback" not in err, err
        # Never without results: the old or the new set, complete.
        _assert_complete(out)
        if kind != signal.SIGKILL:  # cleanups ran: nothing left even before the next run
            assert _litter(tmp_path) == [], (kind.name, code, _litter(tmp_path))
        outcomes.append((kind.name, code))
    # The next run cleans whatever a SIGKILL left.
    final = _resloc(args)
    assert final.wait(timeout=120) == 0, final.stderr.read()
    final.stderr.close()
    _assert_complete(out)
    assert _litter(tmp_path) == []
    # Exit codes: finished (0), 128 + signal after a clean stop, or killed by the signal.
    for name, code in outcomes:
        allowed = {0, -getattr(signal, name), 128 + getattr(signal, name)}
        assert code in allowed, (name, code)
