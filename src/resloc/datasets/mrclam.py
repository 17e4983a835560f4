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
its physical range (:data:`BOUNDS`), an undeclared subject, an empty ground-truth or odometry
file, or a file whose rows all share one time raises :class:`~resloc.errors.DataError`
naming the file and the line.

Each timed file is read whole, then sorted by time and de-duplicated (:func:`order_rows`)
*before* any ``duration`` cut. Nothing is dropped without being counted in
:attr:`MRCLAMDataset.skipped` (per file in :attr:`MRCLAMDataset.skipped_by_file`):

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

import bisect
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from resloc.errors import DataError

__all__ = [
    "BARCODES_FILE",
    "BOUNDS",
    "DROP_REASONS",
    "LANDMARKS_FILE",
    "MRCLAMDataset",
    "RobotLog",
    "dataset_start_time",
    "load_mrclam",
    "order_rows",
    "read_rows",
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


#: One number as the MRCLAM files write it: plain decimal with an optional exponent. Python's
#: ``float()`` also accepts ``1_000``, ``inf``, ``nan``, ``infinity`` and ``1e999`` (inf):
#: none of these is data.
_NUMBER = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d{1,3})?"
_NUMBER_RE = re.compile(_NUMBER)
_LINE_RE = re.compile(rf"\s*{_NUMBER}(?:\s+{_NUMBER})*\s*")

_TIME = (0.0, 1e10)  # absolute Unix seconds (the official files: ~1.25e9)
_XY = (-1e4, 1e4)  # m: far beyond any arena
_ANGLE = (-2 * math.pi, 2 * math.pi)  # rad: a heading or bearing a sensor reports
_SUBJECT = (0.0, 1e6)
#: Inclusive physical bounds of every column, per file kind (same order as COLUMNS). A value
#: outside is rejected with file:line: no sensor of the MRCLAM setup reports it.
BOUNDS = {
    "Barcodes": (_SUBJECT, _SUBJECT),
    "Landmark_Groundtruth": (_SUBJECT, _XY, _XY, (0.0, 1e3), (0.0, 1e3)),
    "Groundtruth": (_TIME, _XY, _XY, _ANGLE),
    "Odometry": (_TIME, (-10.0, 10.0), (-50.0, 50.0)),
    "Measurement": (_TIME, _SUBJECT, (0.0, 1e3), _ANGLE),
}
#: Reasons a row is dropped while loading (counted in :attr:`MRCLAMDataset.skipped`).
DROP_REASONS = (
    "unknown_barcode",
    "unknown_subject",
    "self_measurement",
    "duplicate",
    "conflicting",
)


def _rows(path: Path, kind: str) -> Iterator[tuple[int, list[float]]]:
    """Stream the data rows of ``path``: ``(line number, values)``; validates every line:
    column count, number grammar (:data:`_NUMBER`), integer columns and :data:`BOUNDS`."""
    names, integer = COLUMNS[kind]
    bounds = BOUNDS[kind]
    n = len(names)
    int_cols = [c for c, must in enumerate(integer) if must]
    try:
        fh = path.open("r", encoding="ascii", errors="replace")
    except OSError as exc:
        raise DataError(f"{path}: cannot open ({exc.strerror})") from None
    line_ok = _LINE_RE.fullmatch
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
            if not line_ok(line.rstrip("\r\n")):
                c = next(c for c, p in enumerate(parts) if not _NUMBER_RE.fullmatch(p))
                raise DataError(
                    f"{path}:{lineno}: {names[c]} is {_clip(parts[c])!r}, not a decimal number "
                    "(digits, '.', an exponent; no '_', inf or nan)"
                )
            vals = [float(p) for p in parts]
            for c, (v, (lo, hi)) in enumerate(zip(vals, bounds, strict=True)):
                if not lo <= v <= hi:
                    raise DataError(
                        f"{path}:{lineno}: {names[c]} is {parts[c]}, outside the physical "
                        f"range [{lo:g}, {hi:g}]"
                    )
            for c in int_cols:
                if vals[c] != int(vals[c]):
                    raise DataError(
                        f"{path}:{lineno}: {names[c]} must be an integer, got {vals[c]:g}"
                    )
            yield lineno, vals


def _clip(s: str, n: int = 60) -> str:
    return s if len(s) <= n else s[: n - 3] + "..."


def read_rows(path: Path, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Every data row of an MRCLAM file, validated, in file order.

    Parameters
    ----------
    path : Path
    kind : {"Barcodes", "Landmark_Groundtruth", "Groundtruth", "Odometry", "Measurement"}

    Returns
    -------
    values : ndarray, shape (rows, columns)
    lines : ndarray of int, shape (rows,)
        1-based line number of each row (for messages).
    """
    ncol = len(COLUMNS[kind][0])
    lines: list[int] = []
    out: list[list[float]] = []
    for lineno, vals in _rows(path, kind):
        lines.append(lineno)
        out.append(vals)
    return np.asarray(out, dtype=float).reshape(-1, ncol), np.asarray(lines, dtype=np.int64)


def order_rows(
    path: Path, kind: str, values: np.ndarray, lines: np.ndarray, strict: bool = False
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Sort a timed file by time and drop repeated rows, counting everything.

    Rows are sorted by time (stably: equal times keep their file order). Rows with the same
    key (the time; for measurements the time and the barcode) as an earlier row are dropped:
    counted as ``duplicate`` when every value is equal, as ``conflicting`` otherwise (the
    first row in file order is kept). Rows that had to move are counted as ``out_of_order``
    (kept): the fewest rows whose moving sorts the file (rows minus the longest
    non-decreasing run), so one misplaced row counts 1, not the rows it jumped over.

    Parameters
    ----------
    path : Path
        For messages.
    kind : {"Groundtruth", "Odometry", "Measurement"}
    values : ndarray, shape (rows, columns)
    lines : ndarray of int, shape (rows,)
    strict : bool
        Raise on the first out-of-order, duplicate or conflicting row instead.

    Returns
    -------
    values : ndarray, shape (kept, columns)
    lines : ndarray of int, shape (kept,)
    counts : dict of str to int
        ``out_of_order``, ``duplicate``, ``conflicting`` (zeros omitted).

    Raises
    ------
    DataError
        All rows at one time (no time axis), or, with ``strict``, the first offending row.
    """
    n = len(values)
    if n == 0:
        return values, lines, {}
    t = values[:, 0]
    if n > 1 and t.min() == t.max():
        raise DataError(
            f"{path}: all {n} rows have the same time {t[0]:.3f}; the file has no time axis"
        )
    late = np.zeros(n, dtype=bool)
    late[1:] = t[1:] < np.maximum.accumulate(t)[:-1]
    if strict and late.any():
        k = int(np.argmax(late))
        raise DataError(
            f"{path}:{lines[k]}: time {t[k]:.3f} is earlier than a previous row "
            "(out of order; --strict)"
        )
    if kind == "Measurement":
        order = np.lexsort((values[:, 1], t))  # by time, then barcode; stable
        key_cols = [0, 1]
    else:
        order = np.argsort(t, kind="stable")
        key_cols = [0]
    v, ln = values[order], lines[order]
    same_key = np.zeros(n, dtype=bool)
    same_key[1:] = np.all(v[1:, key_cols] == v[:-1, key_cols], axis=1)
    # Index of the first row (in file order) of each group of equal keys.
    first = np.maximum.accumulate(np.where(same_key, 0, np.arange(n)))
    equal_first = np.all(v == v[first], axis=1)
    duplicate = same_key & equal_first
    conflicting = same_key & ~equal_first
    if strict and (duplicate.any() or conflicting.any()):
        k = int(np.argmax(duplicate | conflicting))
        what = "repeats" if duplicate[k] else "conflicts with"
        raise DataError(
            f"{path}:{ln[k]}: {what} line {ln[first[k]]} (same "
            f"{' and '.join(COLUMNS[kind][0][c] for c in key_cols)}; --strict)"
        )
    keep = ~same_key
    counts = {
        "out_of_order": _misplaced(t) if late.any() else 0,
        "duplicate": int(duplicate.sum()),
        "conflicting": int(conflicting.sum()),
    }
    return v[keep], ln[keep], {c: k for c, k in counts.items() if k}


def _misplaced(t: np.ndarray) -> int:
    """Fewest rows to move to sort ``t``: ``len(t)`` minus its longest non-decreasing
    subsequence (patience sorting, O(n log n))."""
    tails: list[float] = []
    for v in t.tolist():
        k = bisect.bisect_right(tails, v)
        if k == len(tails):
            tails.append(v)
        else:
            tails[k] = v
    return len(t) - len(tails)


def read_table(
    path: Path, kind: str, t_stop: float | None = None, strict: bool = False
) -> np.ndarray:
    """Read a whole MRCLAM file into an array, validating every line.

    Timed files are sorted and de-duplicated (:func:`order_rows`) *before* the cut at
    ``t_stop``, so an out-of-order row never hides the rows after it.

    Parameters
    ----------
    path : Path
    kind : {"Barcodes", "Landmark_Groundtruth", "Groundtruth", "Odometry", "Measurement"}
    t_stop : float, optional
        For timed files: keep the rows with ``time <= t_stop`` (absolute seconds).
    strict : bool
        Fail on any out-of-order or repeated row.

    Returns
    -------
    ndarray, shape (rows, columns)
    """
    values, lines = read_rows(path, kind)
    if kind in ROBOT_KINDS:
        values, lines, _ = order_rows(path, kind, values, lines, strict)
        if t_stop is not None:
            values = values[values[:, 0] <= t_stop]
    return values


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
    lm_seen: set[int] = set()
    for lineno, vals in _rows(landmark_path, "Landmark_Groundtruth"):
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
