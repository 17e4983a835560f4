"""The run's CSV files, written column-wise, are byte for byte what a row-by-row
``csv.writer`` wrote (the reference kept here), for several trials, NaN and odd names."""

from __future__ import annotations

import csv
import dataclasses
import warnings

import numpy as np
import pytest

from resloc.experiments.config import default_scenario
from resloc.experiments.run_files import csv_field, csv_rows, write_timeseries, write_trajectories
from resloc.experiments.runner import run_scenario


def reference_timeseries(path, result) -> None:
    """The row-by-row writer this module replaced."""
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["step", "time_s", "estimator", "msle", "rmse", "nees", "comm_rate", "detected"])
        for name, est in result.estimators.items():
            s = est.series
            with np.errstate(invalid="ignore", divide="ignore"):
                cr = s["triggered"].sum(axis=1) / s["candidates"].sum(axis=1)
            for k in range(len(result.time)):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    row = [f"{np.nanmean(s[key][k]):.6g}" for key in ("msle", "rmse", "nees")]
                w.writerow(
                    [
                        k + 1,
                        f"{result.time[k]:.4f}",
                        name,
                        *row,
                        f"{cr[k]:.6g}",
                        int(np.nansum(s["detected"][k])),
                    ]
                )


def reference_trajectories(path, result) -> None:
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["step", "robot", "source", "x", "y", "theta"])
        sources = {"truth": result.truth} | {n: e.track for n, e in result.estimators.items()}
        for src, arr in sources.items():
            for k in range(arr.shape[0]):
                for r in range(arr.shape[1]):
                    x, y, th = arr[k, r]
                    w.writerow([k, r, src, f"{x:.5f}", f"{y:.5f}", f"{th:.5f}"])


@pytest.fixture(scope="module")
def run_result():
    scenario = default_scenario().replace(**{"run.steps": 60, "run.trials": 3, "team.robots": 9})
    return run_scenario(scenario, metric_stride=4)


def _odd(result):
    """The same result with NaN, inf, -0.0, huge and tiny values and awkward names."""
    estimators = {}
    for name, est in result.estimators.items():
        series = {k: v.copy() for k, v in est.series.items()}
        series["msle"][5] = np.nan  # a step whose trials are all NaN
        series["msle"][6, 1] = np.nan
        series["rmse"][7] = np.inf
        series["nees"][8] = [-0.0, 1e300, 1e-300]
        series["candidates"][9] = 0  # comm rate 0/0
        track = est.track.copy()
        track[3, 2] = [np.nan, -1e-7, 123456789.123456]
        track[4, 0] = [-0.0, 0.000005, -0.000005]
        odd_name = {"ckf": 'c,k "f"', "ukf": "u\nkf"}.get(name, name)
        estimators[odd_name] = dataclasses.replace(est, series=series, track=track)
    return dataclasses.replace(result, estimators=estimators)


@pytest.mark.parametrize("odd", [False, True], ids=["run", "odd values"])
def test_csv_files_are_byte_identical_to_the_row_writer(tmp_path, run_result, odd):
    result = _odd(run_result) if odd else run_result
    for write, reference in [
        (write_timeseries, reference_timeseries),
        (write_trajectories, reference_trajectories),
    ]:
        new, old = tmp_path / f"new_{write.__name__}.csv", tmp_path / f"old_{write.__name__}.csv"
        write(new, result)
        reference(old, result)
        assert new.read_bytes() == old.read_bytes()
        assert new.read_bytes().count(b"\r\n") >= len(result.time)


def test_csv_rows_and_field():
    assert (
        csv_rows("%d,%s,%.2f", [[1, 2], ["a", "b"], [0.125, -0.0]]) == "1,a,0.12\r\n2,b,-0.00\r\n"
    )
    assert csv_rows("%d", []) == ""
    assert csv_field("plain") == "plain"
    assert csv_field('a,"b"') == '"a,""b"""'
    with pytest.raises(ValueError):
        csv_rows("%d,%d", [[1, 2], [3]])
