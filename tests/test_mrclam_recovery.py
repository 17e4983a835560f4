"""No lock-out on real data: cut a stretch of one robot's sightings out of MRCLAM Dataset 6
and require its estimate to come back to the uncut run's within a bounded time of the
sightings resuming, with ``resloc mrclam``'s default detector (the NIS gate with recovery).

A regression guard on real data: on the cuts below the paper's detector comes back too
(measured, ``docs/mrclam.md``); the lock-out itself, and the recovery's bound, are tested
on a simulated blackout in ``tests/test_defence_recovery.py``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from resloc.datasets.mrclam import load_mrclam
from resloc.experiments.mrclam import MRCLAMConfig, run_mrclam

HERE = Path(__file__).parent
FIXTURE = HERE / "fixtures" / "mrclam" / "MRCLAM_Dataset6_60s"
DATASET6 = HERE.parent.parent / "shared" / "data" / "mrclam" / "MRCLAM_Dataset6"

#: The cut robot is back when its position error stays within this of the uncut run's (m).
TOLERANCE = 0.15


def cut_sightings(path: Path, duration: float, robot: int, start: float, length: float):
    """Dataset ``path`` (first ``duration`` s) without robot ``robot``'s own sightings in
    ``[start, start + length)``."""
    data = load_mrclam(path, duration=duration)
    m = data.robots[robot].measurements
    data.robots[robot].measurements = m[(m[:, 0] < start) | (m[:, 0] >= start + length)]
    return data


def recovery_time(
    path: Path, config: MRCLAMConfig, robot: int, start: float, length: float
) -> float:
    """Seconds after the sightings resume until robot ``robot``'s error stays within
    :data:`TOLERANCE` of the uncut run's (inf: never)."""
    duration = config.duration
    ref = run_mrclam(load_mrclam(path, duration=duration), config).estimators["ekf"]
    cut = run_mrclam(cut_sightings(path, duration, robot, start, length), config)
    err = cut.estimators["ekf"].pos_err[:, robot]
    excess = np.abs(err - ref.pos_err[:, robot])
    t = cut.time
    after = np.flatnonzero(t >= start + length)
    bad = after[~(excess[after] <= TOLERANCE)]  # nan (no ground truth) is not "back"
    valid_after = after[np.isfinite(err[after])]
    if not len(bad):
        return 0.0
    if bad[-1] >= valid_after[-1]:
        return float("inf")
    return float(t[bad[-1] + 1] - (start + length))


def _config(duration: float, **kw) -> MRCLAMConfig:
    return MRCLAMConfig(filters=("ekf",), duration=duration, **kw)


def test_recovery_on_the_shipped_excerpt():
    """The 60 s excerpt (always present): 20 s without sightings, back within 10 s."""
    config = _config(60.0)
    assert config.detector_norm == "nis" and config.recovery
    t = recovery_time(FIXTURE, config, robot=4, start=25.0, length=20.0)
    assert t <= 10.0, t


@pytest.mark.skipif(not DATASET6.is_dir(), reason="MRCLAM Dataset 6 not in ../shared/data")
def test_dataset6_forty_second_cut_recovers_within_twenty_seconds():
    """Robot 3 (index 2) without sightings from 150 s to 190 s: it is 0.2 m off the uncut
    run when they resume."""
    t = recovery_time(DATASET6, _config(220.0), robot=2, start=150.0, length=40.0)
    assert t <= 20.0, t


def test_paper_detector_is_one_flag_away():
    paper = _config(60.0).paper_detector()
    assert (paper.detector_norm, paper.rho, paper.recovery) == ("euclidean", 1.0, False)
    assert not paper.cl_params().recovery and _config(60.0).cl_params().recovery
    assert dataclasses.replace(paper, rho=0.5).rho == 0.5
