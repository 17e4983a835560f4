"""MRCLAM loader: the shipped excerpt, validation errors with file and line, skip counts."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from resloc.datasets.mrclam import dataset_start_time, load_mrclam
from resloc.errors import DataError

FIXTURE = Path(__file__).parent / "fixtures" / "mrclam" / "MRCLAM_Dataset6_60s"
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mrclam"
DATASET6 = SHARED / "MRCLAM_Dataset6"

needs_shared = pytest.mark.skipif(
    not DATASET6.is_dir(), reason="full MRCLAM Dataset 6 not found under ../shared"
)


@pytest.fixture
def copy(tmp_path: Path) -> Path:
    """A writable copy of the excerpt."""
    dst = tmp_path / "MRCLAM_Dataset6_60s"
    shutil.copytree(FIXTURE, dst)
    return dst


def _append_row(path: Path, row: str) -> int:
    """Append a data row; return its 1-based line number."""
    text = path.read_text(encoding="ascii")
    if not text.endswith("\n"):
        text += "\n"
    path.write_text(text + row + "\n", encoding="ascii")
    return text.count("\n") + 1


def _replace_first_data_row(path: Path, row: str) -> int:
    lines = path.read_text(encoding="ascii").splitlines(keepends=True)
    k = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    lines[k] = row + "\n"
    path.write_text("".join(lines), encoding="ascii")
    return k + 1


def test_excerpt_loads_with_expected_structure():
    data = load_mrclam(FIXTURE)
    assert data.name == "MRCLAM_Dataset6_60s"
    assert data.n_robots == 5
    np.testing.assert_array_equal(data.robot_subjects, [1, 2, 3, 4, 5])
    np.testing.assert_array_equal(data.landmark_subjects, np.arange(6, 21))
    assert data.landmark_xy.shape == (15, 2) and data.landmark_std.shape == (15, 2)
    assert data.barcodes[5] == 1 and data.barcodes[90] == 15
    # Start = latest first ground-truth sample (Robot4's), 1248444175.118 in Dataset 6.
    assert data.t0 == pytest.approx(1248444175.118)
    assert data.t0 == pytest.approx(dataset_start_time(FIXTURE))
    assert 59.0 < data.end <= 60.0
    for log in data.robots:
        assert log.groundtruth.shape[1] == 4 and log.odometry.shape[1] == 3
        assert log.measurements.shape[1] == 4
        for table in (log.groundtruth, log.odometry, log.measurements):
            assert np.all(np.diff(table[:, 0]) >= 0)
        # Subjects are mapped from barcodes: robots 1..5 (never the observer) or landmarks.
        subj = log.measurements[:, 1].astype(int)
        assert np.all((subj >= 1) & (subj <= 20)) and not np.any(subj == log.subject)
    counts = data.counts()
    assert counts["measurements"] == 1013
    assert sum(data.skipped.values()) == 0


def test_duration_cuts_every_stream_but_keeps_ground_truth_margin():
    data = load_mrclam(FIXTURE, duration=20.0)
    assert data.end <= 20.0
    for log in data.robots:
        assert log.odometry[-1, 0] <= 20.0
        if len(log.measurements):
            assert log.measurements[-1, 0] <= 20.0
        assert 20.0 < log.groundtruth[-1, 0] <= 21.0
    assert data.counts()["measurements"] < load_mrclam(FIXTURE).counts()["measurements"]


@pytest.mark.parametrize(
    "missing", ["Barcodes.dat", "Landmark_Groundtruth.dat", "Robot3_Odometry.dat"]
)
def test_missing_file_is_named(copy: Path, missing: str):
    (copy / missing).unlink()
    with pytest.raises(DataError, match=f"{missing}: missing file"):
        load_mrclam(copy)


def test_missing_folder_and_not_a_folder(tmp_path: Path):
    with pytest.raises(DataError, match="no such dataset folder"):
        load_mrclam(tmp_path / "nope")
    f = tmp_path / "file.dat"
    f.write_text("x")
    with pytest.raises(DataError, match="not a directory"):
        load_mrclam(f)
    with pytest.raises(DataError, match="no Robot<k>"):
        load_mrclam(tmp_path)


@pytest.mark.parametrize(
    ("name", "row", "message"),
    [
        ("Robot2_Odometry.dat", "1248444300.000 0.1", "expected 3 columns"),
        ("Robot2_Odometry.dat", "1248444300.000 0.1 abc", "omega is 'abc', not a decimal"),
        ("Robot4_Groundtruth.dat", "1248444300.000 1.0 nan 0.0", "y is 'nan', not a decimal"),
        ("Robot4_Groundtruth.dat", "1248444300.000 1.0 inf 0.0", "y is 'inf', not a decimal"),
        ("Robot2_Odometry.dat", "1248444300.000 1_000 0.0", "v is '1_000', not a decimal"),
        ("Robot2_Odometry.dat", "1248444300.000 0.1 1e300", "omega is 1e300, outside"),
        ("Robot2_Odometry.dat", "1248444300.000 0.1 1e999", "omega is 1e999, outside"),
        ("Robot3_Groundtruth.dat", "1248444300.000 1e300 1.0 0.0", "x is 1e300, outside"),
        ("Robot3_Groundtruth.dat", "1248444300.000 1.0 1.0 40", "theta is 40, outside"),
        ("Robot1_Measurement.dat", "1248444300.000 14 2.0 1e6", "bearing is 1e6, outside"),
        ("Robot5_Measurement.dat", "1248444300.000 14.5 2.0 0.1", "barcode must be an integer"),
        ("Robot1_Measurement.dat", "1248444300.000 14 -2.0 0.1", "range is -2.0, outside"),
        ("Robot1_Measurement.dat", "-5 14 2.0 0.1", "time is -5, outside"),
        ("Landmark_Groundtruth.dat", "20 1.0 1.0 -0.1 0.01", "x_std is -0.1, outside"),
        ("Barcodes.dat", "0x15 5", "subject is '0x15', not a decimal"),
    ],
)
def test_malformed_line_names_file_and_line(copy: Path, name: str, row: str, message: str):
    lineno = _append_row(copy / name, row)
    with pytest.raises(DataError) as err:
        load_mrclam(copy)
    text = str(err.value)
    assert f"{name}:{lineno}:" in text
    assert message in text
    assert "\n" not in text


def test_malformed_barcode_table(copy: Path):
    lineno = _append_row(copy / "Barcodes.dat", " 21 \t  5")
    with pytest.raises(DataError, match=rf"Barcodes.dat:{lineno}: barcode 5 listed twice"):
        load_mrclam(copy)


def test_unknown_barcodes_are_skipped_and_counted(copy: Path):
    path = copy / "Robot3_Measurement.dat"
    before = load_mrclam(copy).robots[2].measurements.shape[0]
    first_time = next(ln for ln in path.read_text().splitlines() if ln[0] != "#").split()[0]
    _replace_first_data_row(path, f"{first_time} \t  43 \t  2.000 \t 0.100")
    _append_row(path, "1248444230.000 \t  99 \t  2.000 \t 0.100")
    data = load_mrclam(copy)
    assert data.skipped["unknown_barcode"] == 2
    # The appended row is also earlier than the excerpt's last one: counted as reordered.
    assert data.skipped_by_file == {
        "Robot3_Measurement.dat": {"unknown_barcode": 2, "out_of_order": 1}
    }
    assert data.robots[2].measurements.shape[0] == before - 1


def test_self_measurement_and_out_of_order_rows_are_counted(copy: Path):
    # Robot 1's own barcode is 5 (the row is also earlier than the file's last: reordered).
    _append_row(copy / "Robot1_Measurement.dat", "1248444230.000 \t   5 \t  2.000 \t 0.100")
    # A row earlier than the one before it: counted and sorted, not an error.
    _append_row(copy / "Robot2_Odometry.dat", "1248444180.000 \t  0.000 \t 0.000")
    data = load_mrclam(copy)
    assert data.skipped["self_measurement"] == 1
    assert data.skipped_by_file["Robot2_Odometry.dat"] == {"out_of_order": 1}
    assert data.skipped_by_file["Robot1_Measurement.dat"] == {
        "self_measurement": 1,
        "out_of_order": 1,
    }
    assert data.skipped["out_of_order"] == 2
    assert np.all(np.diff(data.robots[1].odometry[:, 0]) >= 0)


def _data_rows(path: Path) -> list[str]:
    return [ln for ln in path.read_text().splitlines() if ln.strip() and ln[0] != "#"]


def test_out_of_order_row_never_hides_the_rows_after_it_under_duration(copy: Path):
    """The audit's silent drop: a late row early in the file ended the --duration read."""
    path = copy / "Robot2_Odometry.dat"
    clean = load_mrclam(copy, duration=30.0)
    rows = _data_rows(path)
    # Move a row from t0 + 50 s to the third line of the file.
    late = next(r for r in rows if float(r.split()[0]) > clean.t0 + 50.0)
    lines = path.read_text().splitlines()
    lines.remove(late)
    first = next(i for i, ln in enumerate(lines) if ln[0] != "#")
    lines.insert(first + 2, late)
    path.write_text("\n".join(lines) + "\n")
    data = load_mrclam(copy, duration=30.0)
    np.testing.assert_array_equal(data.robots[1].odometry, clean.robots[1].odometry)
    assert data.skipped_by_file == {"Robot2_Odometry.dat": {"out_of_order": 1}}
    with pytest.raises(DataError, match=rf"Robot2_Odometry.dat:{first + 4}: .*out of order"):
        load_mrclam(copy, duration=30.0, strict=True)


def test_duplicate_and_conflicting_rows_are_counted_or_refused(copy: Path):
    path = copy / "Robot4_Groundtruth.dat"
    rows = _data_rows(path)
    t, x, y, th = rows[10].split()
    dup_line = _append_row(path, rows[10])
    conflict_line = _append_row(path, f"{t} {float(x) + 1.0} {y} {th}")
    data = load_mrclam(copy)
    assert data.skipped_by_file["Robot4_Groundtruth.dat"] == {
        "out_of_order": 2,
        "duplicate": 1,
        "conflicting": 1,
    }
    assert data.dropped == 2
    gt = data.robots[3].groundtruth
    assert len(gt) == len(rows) and np.all(np.diff(gt[:, 0]) > 0)
    # The first row in file order is kept.
    assert gt[10, 1] == pytest.approx(float(x))
    with pytest.raises(DataError, match=rf"Robot4_Groundtruth.dat:{dup_line}: .*out of order"):
        load_mrclam(copy, strict=True)
    # Measurements: the same time with another barcode is a second sighting, not a repeat.
    m = copy / "Robot1_Measurement.dat"
    mt, mb, mr, mbr = _data_rows(m)[-1].split()
    other = 25  # subject 20, a landmark not seen at that time
    _append_row(m, f"{mt} {other} {mr} {mbr}")
    _append_row(m, f"{mt} {mb} {float(mr) + 0.5} {mbr}")
    data = load_mrclam(copy)
    assert data.skipped_by_file["Robot1_Measurement.dat"] == {"conflicting": 1}
    assert conflict_line == dup_line + 1


def test_empty_odometry_and_constant_time_are_refused(copy: Path):
    odo = copy / "Robot3_Odometry.dat"
    header = "".join(ln + "\n" for ln in odo.read_text().splitlines() if ln[0] == "#")
    odo.write_text(header)
    with pytest.raises(DataError, match=r"Robot3_Odometry\.dat: no data rows"):
        load_mrclam(copy)
    odo.write_text(header + "1248444180.0 0.1 0.0\n" * 3 + "1248444180.0 0.2 0.0\n")
    with pytest.raises(DataError, match="all 4 rows have the same time"):
        load_mrclam(copy)
    # An empty measurement file is a robot that saw nothing: loaded, with 0 rows.
    odo.unlink()
    shutil.copy(FIXTURE / "Robot3_Odometry.dat", odo)
    m = copy / "Robot3_Measurement.dat"
    m.write_text("# nothing seen\n")
    assert load_mrclam(copy).robots[2].measurements.shape == (0, 4)


def test_unknown_barcode_fails_under_strict(copy: Path):
    line = _append_row(copy / "Robot3_Measurement.dat", "1248444240.000 99 2.0 0.1")
    with pytest.raises(DataError, match=rf"Robot3_Measurement.dat:{line}: barcode 99"):
        load_mrclam(copy, strict=True)


def test_invalid_duration():
    with pytest.raises(DataError, match="duration must be a finite number > 0"):
        load_mrclam(FIXTURE, duration=0.0)
    with pytest.raises(DataError, match="duration must be a finite number > 0"):
        load_mrclam(FIXTURE, duration=float("inf"))


@needs_shared
def test_full_dataset6_counts_and_skips_the_official_unknown_barcodes():
    data = load_mrclam(DATASET6)
    assert data.n_robots == 5
    assert 895.0 < data.end < 905.0
    # The official Dataset 6 contains 6 sightings of barcodes missing from Barcodes.dat
    # (43 in Robot1, 34 in Robot3, 50 in Robot4).
    assert data.skipped["unknown_barcode"] == 6
    # Its odometry repeats 18 rows exactly and has 5 rows that share a time with an
    # earlier, different command (the first in file order is kept); nothing is out of order.
    assert data.skipped_by_file == {
        "Robot1_Measurement.dat": {"unknown_barcode": 1},
        "Robot3_Measurement.dat": {"unknown_barcode": 2},
        "Robot4_Measurement.dat": {"unknown_barcode": 3},
        "Robot2_Odometry.dat": {"duplicate": 1},
        "Robot3_Odometry.dat": {"conflicting": 1, "duplicate": 7},
        "Robot4_Odometry.dat": {"conflicting": 3, "duplicate": 7},
        "Robot5_Odometry.dat": {"conflicting": 1, "duplicate": 3},
    }
    assert data.skipped["out_of_order"] == 0 and data.dropped == 6 + 18 + 5
    assert data.counts()["measurements"] == 19371


@needs_shared
def test_excerpt_matches_the_full_dataset():
    full = load_mrclam(DATASET6, duration=60.0)
    small = load_mrclam(FIXTURE)
    assert full.t0 == small.t0
    for a, b in zip(full.robots, small.robots, strict=True):
        np.testing.assert_array_equal(a.measurements, b.measurements)
        # The excerpt drops repeated odometry commands (lossless under zero-order hold).
        assert set(map(tuple, b.odometry)) <= set(map(tuple, a.odometry))
