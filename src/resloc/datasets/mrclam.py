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

Files are streamed line by line and validated: a missing file, a line with the wrong
number of columns, a non-numeric or non-finite value, or an undeclared subject raises
:class:`~resloc.errors.DataError` naming the file and the line. Rows the official data
itself contains and that cannot be used are skipped and counted in
:attr:`MRCLAMDataset.skipped`: measurements of barcodes absent from ``Barcodes.dat``
(Dataset 6 has a few, e.g. barcode 43 in ``Robot1_Measurement.dat``), of a subject that is
neither a robot of the dataset nor a landmark, and of the observer itself.
Timestamps are made relative to the dataset start (the latest first ground-truth sample
over the robots, so that every robot has an initial pose); rows out of time order are
counted and sorted.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from resloc.errors import DataError

__all__ = [
    "BARCODES_FILE",
    "LANDMARKS_FILE",
    "MRCLAMDataset",
    "RobotLog",
    "dataset_start_time",
    "load_mrclam",
    "read_table",
]

BARCODES_FILE = "Barcodes.dat"
LANDMARKS_FILE = "Landmark_Groundtruth.dat"
ROBOT_KINDS = ("Groundtruth", "Odometry", "Measurement")
#: Ground truth is read this far (s) past a ``duration`` cut, for interpolation at the end.
GROUNDTRUTH_MARGIN = 1.0
_ROBOT_RE = re.compile(r"^Robot(\d+)_(Groundtruth|Odometry|Measurement)\.dat$")

#: Columns of every file: (names, which must be integers).
COLUMNS = {
    "Barcodes": (("subject", "barcode"), (True, True)),
    "Landmark_Groundtruth": (("subject", "x", "y", "x_std", "y_std"), (True, *([False] * 4))),
    "Groundtruth": (("time", "x", "y", "theta"), (False,) * 4),
    "Odometry": (("time", "v", "omega"), (False,) * 3),
    "Measurement": (("time", "barcode", "range", "bearing"), (False, True, False, False)),
}


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
        Rows skipped per reason (``unknown_barcode``, ``unknown_subject``,
        ``self_measurement``, ``out_of_order``, the latter sorted rather than skipped).
    skipped_by_file : dict of str to dict of str to int
    duration_limit : float or None
        The ``duration`` the data were cut to, if any.
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

    def counts(self) -> dict[str, int]:
        """Rows loaded per kind, summed over the robots."""
        return {
            "groundtruth": sum(len(r.groundtruth) for r in self.robots),
            "odometry": sum(len(r.odometry) for r in self.robots),
            "measurements": sum(len(r.measurements) for r in self.robots),
            "landmarks": len(self.landmark_subjects),
        }


def _rows(path: Path, kind: str) -> Iterator[tuple[int, list[float]]]:
    """Stream the data rows of ``path``: ``(line number, values)``; validates every line."""
    names, integer = COLUMNS[kind]
    n = len(names)
    int_cols = [c for c, must in enumerate(integer) if must]
    try:
        fh = path.open("r", encoding="ascii", errors="replace")
    except OSError as exc:
        raise DataError(f"{path}: cannot open ({exc.strerror})") from None
    isfinite = math.isfinite
    with fh:
        for lineno, line in enumerate(fh, start=1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            if len(parts) != n:
                raise DataError(
                    f"{path}:{lineno}: expected {n} columns ({' '.join(names)}), "
                    f"got {len(parts)}: {_clip(line.strip())!r}"
                )
            try:
                vals = [float(p) for p in parts]
            except ValueError:
                bad = next(p for p in parts if not _is_float(p))
                raise DataError(
                    f"{path}:{lineno}: non-numeric value {_clip(bad)!r} in {_clip(line.strip())!r}"
                ) from None
            if not all(map(isfinite, vals)):
                c = next(c for c, v in enumerate(vals) if not isfinite(v))
                raise DataError(
                    f"{path}:{lineno}: {names[c]} is {vals[c]}, expected a finite number"
                )
            for c in int_cols:
                if vals[c] != int(vals[c]):
                    raise DataError(
                        f"{path}:{lineno}: {names[c]} must be an integer, got {vals[c]:g}"
                    )
            yield lineno, vals


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _clip(s: str, n: int = 60) -> str:
    return s if len(s) <= n else s[: n - 3] + "..."


def read_table(path: Path, kind: str, t_stop: float | None = None) -> np.ndarray:
    """Read a whole MRCLAM file into an array, validating every line.

    Parameters
    ----------
    path : Path
    kind : {"Barcodes", "Landmark_Groundtruth", "Groundtruth", "Odometry", "Measurement"}
    t_stop : float, optional
        For timed files: stop at the first row with ``time > t_stop`` (absolute seconds).

    Returns
    -------
    ndarray, shape (rows, columns)
    """
    ncol = len(COLUMNS[kind][0])
    timed = kind in ROBOT_KINDS
    out: list[list[float]] = []
    for _, vals in _rows(path, kind):
        if timed and t_stop is not None and vals[0] > t_stop:
            break
        out.append(vals)
    return np.asarray(out, dtype=float).reshape(-1, ncol)


def _first_time(path: Path, kind: str) -> float:
    for _, vals in _rows(path, kind):
        return vals[0]
    raise DataError(f"{path}: no data rows")


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

    Reads only the first data row of each ``Robot<k>_Groundtruth.dat``.
    """
    folder = Path(path)
    files = _robot_files(folder)
    return max(_first_time(files[k]["Groundtruth"], "Groundtruth") for k in sorted(files))


def load_mrclam(path: str | Path, duration: float | None = None) -> MRCLAMDataset:
    """Load and validate an MRCLAM dataset folder.

    Parameters
    ----------
    path : str or Path
        The dataset folder (``.../MRCLAM_Dataset6``).
    duration : float, optional
        Keep only the first ``duration`` seconds after the start (files are streamed and
        reading stops there, so a short replay of a long dataset reads little).

    Returns
    -------
    MRCLAMDataset

    Raises
    ------
    DataError
        A missing file or folder, a malformed line (file and line number in the message),
        an invalid barcode table or a dataset without usable ground truth.
    """
    folder = Path(path)
    if not folder.exists():
        raise DataError(f"{folder}: no such dataset folder")
    if not folder.is_dir():
        raise DataError(f"{folder}: not a directory (expected an MRCLAM dataset folder)")
    if duration is not None and not duration > 0:
        raise DataError(f"duration must be > 0 s, got {duration}")
    files = _robot_files(folder)
    barcode_path = _require(folder, BARCODES_FILE)
    landmark_path = _require(folder, LANDMARKS_FILE)

    barcodes: dict[int, int] = {}
    subjects_seen: set[int] = set()
    for lineno, (subject, barcode) in _rows(barcode_path, "Barcodes"):
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
    for lineno, vals in _rows(landmark_path, "Landmark_Groundtruth"):
        s = int(vals[0])
        if s in robot_ids:
            raise DataError(f"{landmark_path}:{lineno}: subject {s} is a robot, not a landmark")
        if s not in subjects_seen:
            raise DataError(f"{landmark_path}:{lineno}: subject {s} is not in {BARCODES_FILE}")
        lm_rows.append(vals)
    lm = np.asarray(lm_rows, float).reshape(-1, 5)
    if len(np.unique(lm[:, 0])) != len(lm):
        raise DataError(f"{landmark_path}: a landmark subject is listed twice")
    landmark_subjects = lm[:, 0].astype(int)

    t0 = max(_first_time(files[k]["Groundtruth"], "Groundtruth") for k in robot_ids)
    t_stop = None if duration is None else t0 + float(duration)
    skipped = {"unknown_barcode": 0, "unknown_subject": 0, "self_measurement": 0, "out_of_order": 0}
    by_file: dict[str, dict[str, int]] = {}
    usable = set(robot_ids) | set(landmark_subjects.tolist())
    robots = []
    end = 0.0
    for k in robot_ids:
        tables = {}
        for kind in ROBOT_KINDS:
            p = files[k][kind]
            if kind == "Measurement":
                tab, counts = _read_measurements(p, barcodes, usable, k, t_stop)
            elif kind == "Groundtruth":
                # A margin past the cut so the last replayed step can still be scored.
                margin = None if t_stop is None else t_stop + GROUNDTRUTH_MARGIN
                tab = read_table(p, kind, margin)
                counts = {}
            else:
                tab = read_table(p, kind, t_stop)
                counts = {}
            n_bad = int(np.count_nonzero(np.diff(tab[:, 0]) < 0)) if len(tab) > 1 else 0
            if n_bad:
                counts["out_of_order"] = n_bad
                tab = tab[np.argsort(tab[:, 0], kind="stable")]
            tab[:, 0] -= t0
            if len(tab) and kind != "Groundtruth":
                end = max(end, float(tab[-1, 0]))
            counts = {c: v for c, v in counts.items() if v}
            if counts:
                by_file[p.name] = counts
                for c, v in counts.items():
                    skipped[c] += v
            tables[kind] = tab
        if len(tables["Groundtruth"]) == 0:
            raise DataError(f"{files[k]['Groundtruth']}: no ground truth in the replayed window")
        robots.append(RobotLog(k, tables["Groundtruth"], tables["Odometry"], tables["Measurement"]))
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
    )


def _read_measurements(
    path: Path, barcodes: dict[int, int], usable: set[int], observer: int, t_stop: float | None
) -> tuple[np.ndarray, dict[str, int]]:
    """Measurement rows with barcodes mapped to subjects; unusable rows counted."""
    out: list[list[float]] = []
    counts = {"unknown_barcode": 0, "unknown_subject": 0, "self_measurement": 0}
    for lineno, (t, barcode, rng, bearing) in _rows(path, "Measurement"):
        if t_stop is not None and t > t_stop:
            break
        if rng < 0:
            raise DataError(f"{path}:{lineno}: negative range {rng:g}")
        subject = barcodes.get(int(barcode))
        if subject is None:
            counts["unknown_barcode"] += 1
        elif subject == observer:
            counts["self_measurement"] += 1
        elif subject not in usable:
            counts["unknown_subject"] += 1
        else:
            out.append([t, float(subject), rng, bearing])
    return np.asarray(out, dtype=float).reshape(-1, 4), counts
