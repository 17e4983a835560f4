"""Loader for the UTIAS Multi-Robot Cooperative Localization and Mapping (MRCLAM) dataset.

Leung, Halpern, Barfoot, Liu, "The UTIAS multi-robot cooperative localization and mapping
dataset", IJRR 30(8), 2011. One dataset folder (``MRCLAM_Dataset1`` ... ``MRCLAM_Dataset9``)
holds, in whitespace-separated text with ``#`` header lines:

``Barcodes.dat``
    ``subject  barcode``: subjects 1-5 are the robots, 6-20 the landmarks.
``Landmark_Groundtruth.dat``
    ``subject  x  y  x_std  y_std`` (m).
``Robot<k>_Groundtruth.dat``
    ``time  x  y  theta`` (s, m, m, rad) from the motion-capture system, ~100 Hz.
``Robot<k>_Odometry.dat``
    ``time  v  omega`` (s, m/s, rad/s), the commanded velocities, ~67 Hz.
``Robot<k>_Measurement.dat``
    ``time  barcode  range  bearing`` (s, -, m, rad): camera detections by robot k.

Every line is validated: a missing file, a line with the wrong number of columns, a value
that is not a plain decimal number (``1_000``, ``inf``, ``nan`` are refused), a value outside
its physical range (:data:`~resloc.datasets.mrclam_files.BOUNDS`), an undeclared subject,
an empty ground-truth or odometry file, or a file whose rows all share one time raises
:class:`~resloc.errors.DataError` naming the file and the line. One file's reading and
validation live in :mod:`resloc.datasets.mrclam_files`; this module assembles a dataset.

Each timed file is read whole, then sorted by time and de-duplicated
(:func:`~resloc.datasets.mrclam_files.order_rows`) *before* any ``duration`` cut. Nothing
is dropped without being counted in :attr:`MRCLAMDataset.skipped` (per file in
:attr:`MRCLAMDataset.skipped_by_file`):

* ``out_of_order``: rows that were moved into time order (kept);
* ``duplicate``: rows equal to an earlier row (dropped; the official Dataset 6 odometry
  has 18);
* ``conflicting``: rows with the time (and, for measurements, the barcode) of an earlier
  row but other values (dropped, the first row in file order is kept; Dataset 6 has 5);
* ``unknown_barcode``, ``unknown_subject``, ``self_measurement``: measurements of barcodes
  absent from ``Barcodes.dat`` (Dataset 6 has 6), of a subject that is neither a robot of
  the dataset nor a landmark, and of the observer itself (dropped).

With ``strict=True`` the first such row raises instead. Timestamps are made relative to the
dataset start (the latest first ground-truth sample over the robots, so that every robot
has an initial pose).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from resloc.datasets.mrclam_files import ROBOT_KINDS, order_rows, read_rows, stream_rows
from resloc.errors import DataError

__all__ = [
    "BARCODES_FILE",
    "DROP_REASONS",
    "LANDMARKS_FILE",
    "MRCLAMDataset",
    "RobotLog",
    "dataset_start_time",
    "load_mrclam",
]

BARCODES_FILE = "Barcodes.dat"
LANDMARKS_FILE = "Landmark_Groundtruth.dat"
#: Ground truth is read this far (s) past a ``duration`` cut, for interpolation at the end.
GROUNDTRUTH_MARGIN = 1.0
_ROBOT_RE = re.compile(r"^Robot(\d+)_(Groundtruth|Odometry|Measurement)\.dat$")


@dataclass
class RobotLog:
    """Everything recorded for one robot; times relative to :attr:`MRCLAMDataset.t0`.

    Attributes
    ----------
    subject : int
        Subject number (1-5 in the official datasets).
    groundtruth : ndarray, shape (G, 4)
        ``time, x, y, theta``.
    odometry : ndarray, shape (M, 3)
        ``time, v, omega`` (commanded).
    measurements : ndarray, shape (K, 4)
        ``time, subject, range, bearing``; the barcode already mapped to its subject and
        unusable rows removed.
    """

    subject: int
    groundtruth: np.ndarray
    odometry: np.ndarray
    measurements: np.ndarray


@dataclass
class MRCLAMDataset:
    """One MRCLAM dataset folder, loaded and validated.

    Attributes
    ----------
    path : Path
    t0 : float
        Absolute (Unix) time of relative time 0: the latest first ground-truth sample.
    end : float
        Relative time of the last odometry or measurement row read (the end of the sensor
        stream; ground truth is only used for scoring).
    robots : list of RobotLog
        Robots in subject order (index ``r`` is subject ``robots[r].subject``).
    barcodes : dict of int to int
        Barcode -> subject.
    landmark_subjects : ndarray of int, shape (L,)
    landmark_xy : ndarray, shape (L, 2)
    landmark_std : ndarray, shape (L, 2)
        Ground-truth standard deviations of the landmark positions.
    skipped : dict of str to int
        Rows dropped per reason (:data:`DROP_REASONS`) and rows reordered
        (``out_of_order``, kept), summed over the files.
    skipped_by_file : dict of str to dict of str to int
        The same per file name (zeros omitted).
    duration_limit : float or None
        The ``duration`` the data were cut to, if any.
    end_row : str
        ``file:line`` of the row that sets :attr:`end` (for messages about the length).
    """

    path: Path
    t0: float
    end: float
    robots: list[RobotLog]
    barcodes: dict[int, int]
    landmark_subjects: np.ndarray
    landmark_xy: np.ndarray
    landmark_std: np.ndarray
    skipped: dict[str, int] = field(default_factory=dict)
    skipped_by_file: dict[str, dict[str, int]] = field(default_factory=dict)
    duration_limit: float | None = None
    end_row: str = ""

    @property
    def name(self) -> str:
        """Folder name, e.g. ``MRCLAM_Dataset6``."""
        return self.path.name

    @property
    def n_robots(self) -> int:
        return len(self.robots)

    @property
    def robot_subjects(self) -> np.ndarray:
        """Subject numbers of the robots, shape (N,)."""
        return np.array([r.subject for r in self.robots], dtype=int)

    @property
    def dropped(self) -> int:
        """Rows dropped while loading, all reasons (reordered rows are kept)."""
        return sum(self.skipped.get(c, 0) for c in DROP_REASONS)

    def counts(self) -> dict[str, int]:
        """Rows loaded per kind, summed over the robots."""
        return {
            "groundtruth": sum(len(r.groundtruth) for r in self.robots),
            "odometry": sum(len(r.odometry) for r in self.robots),
            "measurements": sum(len(r.measurements) for r in self.robots),
            "landmarks": len(self.landmark_subjects),
        }


#: Reasons a row is dropped while loading (counted in :attr:`MRCLAMDataset.skipped`).
DROP_REASONS = (
    "unknown_barcode",
    "unknown_subject",
    "self_measurement",
    "duplicate",
    "conflicting",
)


def _robot_files(folder: Path) -> dict[int, dict[str, Path]]:
    found: dict[int, dict[str, Path]] = {}
    for p in folder.iterdir():
        m = _ROBOT_RE.match(p.name)
        if m:
            found.setdefault(int(m.group(1)), {})[m.group(2)] = p
    if not found:
        raise DataError(
            f"{folder}: no Robot<k>_Groundtruth/Odometry/Measurement.dat files; "
            "is this an MRCLAM dataset folder?"
        )
    for k in range(1, max(found) + 1):
        for kind in ROBOT_KINDS:
            if kind not in found.get(k, {}):
                raise DataError(f"{folder / f'Robot{k}_{kind}.dat'}: missing file")
    return found


def _require(folder: Path, name: str) -> Path:
    p = folder / name
    if not p.is_file():
        raise DataError(f"{p}: missing file")
    return p


def dataset_start_time(path: str | Path) -> float:
    """Absolute start time of a dataset folder: the latest first ground-truth sample.

    Reads every ``Robot<k>_Groundtruth.dat`` (the earliest row of a file need not be its
    first line).
    """
    folder = Path(path)
    files = _robot_files(folder)
    return max(_earliest_time(files[k]["Groundtruth"], "Groundtruth") for k in sorted(files))


def _earliest_time(path: Path, kind: str) -> float:
    values, _ = read_rows(path, kind)
    if len(values) == 0:
        raise DataError(f"{path}: no data rows")
    return float(values[:, 0].min())


def load_mrclam(
    path: str | Path, duration: float | None = None, strict: bool = False
) -> MRCLAMDataset:
    """Load and validate an MRCLAM dataset folder.

    Every timed file is read whole, sorted by time and de-duplicated (:func:`order_rows`)
    before the ``duration`` cut; every reordered, repeated or unusable row is counted in
    :attr:`MRCLAMDataset.skipped` (per file in ``skipped_by_file``).

    Parameters
    ----------
    path : str or Path
        The dataset folder (``.../MRCLAM_Dataset6``).
    duration : float, optional
        Keep only the first ``duration`` seconds after the start.
    strict : bool
        Fail (:class:`DataError`, file:line) on the first row that would be reordered,
        dropped as a repeat, or skipped as unusable, instead of counting it.

    Returns
    -------
    MRCLAMDataset

    Raises
    ------
    DataError
        A missing file or folder, a malformed line (file and line number in the message),
        an invalid barcode table, an empty ground-truth or odometry file, a file without a
        time axis, or (``strict``) any row that is not used as written.
    """
    folder = Path(path)
    if not folder.exists():
        raise DataError(f"{folder}: no such dataset folder")
    if not folder.is_dir():
        raise DataError(f"{folder}: not a directory (expected an MRCLAM dataset folder)")
    if duration is not None and not (math.isfinite(duration) and duration > 0):
        raise DataError(f"duration must be a finite number > 0 s, got {duration}")
    files = _robot_files(folder)
    barcode_path = _require(folder, BARCODES_FILE)
    landmark_path = _require(folder, LANDMARKS_FILE)

    barcodes: dict[int, int] = {}
    subjects_seen: set[int] = set()
    for lineno, (subject, barcode) in stream_rows(barcode_path, "Barcodes"):
        s, b = int(subject), int(barcode)
        if b in barcodes:
            raise DataError(f"{barcode_path}:{lineno}: barcode {b} listed twice")
        if s in subjects_seen:
            raise DataError(f"{barcode_path}:{lineno}: subject {s} listed twice")
        barcodes[b] = s
        subjects_seen.add(s)
    robot_ids = sorted(files)
    for k in robot_ids:
        if k not in subjects_seen:
            raise DataError(f"{barcode_path}: robot subject {k} has no barcode")

    lm_rows = []
    lm_seen: set[int] = set()
    for lineno, vals in stream_rows(landmark_path, "Landmark_Groundtruth"):
        s = int(vals[0])
        if s in robot_ids:
            raise DataError(f"{landmark_path}:{lineno}: subject {s} is a robot, not a landmark")
        if s not in subjects_seen:
            raise DataError(f"{landmark_path}:{lineno}: subject {s} is not in {BARCODES_FILE}")
        if s in lm_seen:
            raise DataError(f"{landmark_path}:{lineno}: landmark subject {s} listed twice")
        lm_seen.add(s)
        lm_rows.append(vals)
    lm = np.asarray(lm_rows, float).reshape(-1, 5)
    landmark_subjects = lm[:, 0].astype(int)

    # Every timed file, whole: validated, sorted and de-duplicated before any cut.
    raw: dict[tuple[int, str], tuple[np.ndarray, np.ndarray]] = {}
    by_file: dict[str, dict[str, int]] = {}
    for k in robot_ids:
        for kind in ROBOT_KINDS:
            p = files[k][kind]
            values, lines = read_rows(p, kind)
            if len(values) == 0 and kind != "Measurement":
                raise DataError(
                    f"{p}: no data rows; every robot needs its {kind.lower()} "
                    "(a robot without measurements may have an empty Measurement file)"
                )
            values, lines, counts = order_rows(p, kind, values, lines, strict)
            raw[k, kind] = values, lines
            if counts:
                by_file[p.name] = counts
    t0 = max(float(raw[k, "Groundtruth"][0][0, 0]) for k in robot_ids)
    t_stop = None if duration is None else t0 + float(duration)
    usable = set(robot_ids) | set(landmark_subjects.tolist())
    robots = []
    end, end_row = 0.0, ""
    for k in robot_ids:
        tables = {}
        for kind in ROBOT_KINDS:
            p = files[k][kind]
            tab, lines = raw[k, kind]
            if kind == "Measurement":
                tab, lines, counts = _map_measurements(p, tab, lines, barcodes, usable, k, strict)
                if counts:
                    by_file.setdefault(p.name, {}).update(counts)
            if t_stop is not None:
                # Ground truth keeps a margin past the cut so the last step can be scored.
                stop = t_stop + (GROUNDTRUTH_MARGIN if kind == "Groundtruth" else 0.0)
                inside = tab[:, 0] <= stop
                tab, lines = tab[inside], lines[inside]
            tab = tab.copy()
            tab[:, 0] -= t0
            if len(tab) and kind != "Groundtruth" and float(tab[-1, 0]) >= end:
                end, end_row = float(tab[-1, 0]), f"{p}:{lines[-1]}"
            tables[kind] = tab
        if len(tables["Groundtruth"]) == 0:
            raise DataError(f"{files[k]['Groundtruth']}: no ground truth in the replayed window")
        robots.append(RobotLog(k, tables["Groundtruth"], tables["Odometry"], tables["Measurement"]))
    skipped = dict.fromkeys((*DROP_REASONS, "out_of_order"), 0)
    for counts in by_file.values():
        for c, v in counts.items():
            skipped[c] += v
    return MRCLAMDataset(
        path=folder,
        t0=t0,
        end=end if duration is None else min(end, float(duration)),
        robots=robots,
        barcodes=barcodes,
        landmark_subjects=landmark_subjects,
        landmark_xy=lm[:, 1:3].copy(),
        landmark_std=lm[:, 3:5].copy(),
        skipped=skipped,
        skipped_by_file=by_file,
        duration_limit=None if duration is None else float(duration),
        end_row=end_row,
    )


def _map_measurements(
    path: Path,
    tab: np.ndarray,
    lines: np.ndarray,
    barcodes: dict[int, int],
    usable: set[int],
    observer: int,
    strict: bool,
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Measurement rows with barcodes mapped to subjects; unusable rows counted (or, with
    ``strict``, refused with file:line)."""
    subject = np.array([barcodes.get(int(b), -1) for b in tab[:, 1]], dtype=np.int64)
    reasons = {
        "unknown_barcode": subject < 0,
        "self_measurement": subject == observer,
        "unknown_subject": (subject >= 0)
        & (subject != observer)
        & ~np.isin(subject, sorted(usable)),
    }
    if strict:
        for reason, mask in reasons.items():
            if mask.any():
                k = int(np.argmax(mask))
                raise DataError(
                    f"{path}:{lines[k]}: barcode {int(tab[k, 1])} is not usable "
                    f"({reason.replace('_', ' ')}; --strict)"
                )
    keep = ~(reasons["unknown_barcode"] | reasons["self_measurement"] | reasons["unknown_subject"])
    out = tab[keep].copy()
    out[:, 1] = subject[keep]
    counts = {c: int(m.sum()) for c, m in reasons.items() if m.any()}
    return out, lines[keep], counts
