"""One MRCLAM data file, read and validated line by line, and a timed file's rows put in
time order (the file formats: :mod:`resloc.datasets.mrclam`).

Every line is validated: a line with the wrong number of columns, a value that is not a
plain decimal number (``1_000``, ``inf``, ``nan`` are refused), a value outside its physical
range (:data:`BOUNDS`) or a non-integer in an integer column raises
:class:`~resloc.errors.DataError` naming the file and the line. :func:`order_rows` sorts a
timed file by time and drops repeated rows, counting them.
"""

from __future__ import annotations

import bisect
import math
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from resloc.errors import DataError

__all__ = [
    "BOUNDS",
    "COLUMNS",
    "ROBOT_KINDS",
    "order_rows",
    "read_rows",
    "read_table",
    "stream_rows",
]

#: The three files of each robot (``Robot<k>_<kind>.dat``); the timed files.
ROBOT_KINDS = ("Groundtruth", "Odometry", "Measurement")

#: Columns of every file: (names, which must be integers).
COLUMNS = {
    "Barcodes": (("subject", "barcode"), (True, True)),
    "Landmark_Groundtruth": (("subject", "x", "y", "x_std", "y_std"), (True, *([False] * 4))),
    "Groundtruth": (("time", "x", "y", "theta"), (False,) * 4),
    "Odometry": (("time", "v", "omega"), (False,) * 3),
    "Measurement": (("time", "barcode", "range", "bearing"), (False, True, False, False)),
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


def stream_rows(path: Path, kind: str) -> Iterator[tuple[int, list[float]]]:
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
    for lineno, vals in stream_rows(path, kind):
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
