"""Writing results: an output directory appears complete or not at all, and never lost.

The life of an output directory ``OUT``:

1. :func:`check_output_dir`, before any computation: ``OUT`` must be usable (creatable,
   writable, a sane name, not the current directory, not under a file, not inside an input,
   not holding an input that ``--overwrite`` would delete) and, unless ``--overwrite``, new
   or empty. It first recovers what a killed run left (:func:`recover_leftovers`).
2. :func:`atomic_output_dir`: the results are written into a hidden sibling
   ``.OUT.tmp-PID-XXXX``; on success it takes the place of ``OUT`` in one atomic step (Linux
   ``renameat2(RENAME_EXCHANGE)`` swaps the old and the new directory, so ``OUT`` always holds
   either complete result set). On an exception, SIGINT, SIGTERM or SIGHUP the temporary is
   removed and ``OUT`` is untouched.
3. After SIGKILL (or a power cut) a hidden ``.OUT.tmp-PID-*`` or ``.OUT.old-PID`` may remain;
   the next command writing to ``OUT`` finds it (its process is gone), restores old results
   that the kill left only in ``.OUT.old-PID``, removes the rest and says so on stderr.
"""

from __future__ import annotations

import contextlib
import csv
import ctypes
import ctypes.util
import errno
import io
import itertools
import json
import math
import os
import re
import shutil
import signal
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from resloc.errors import ConfigError
from resloc.signals import raising_handler, temporary_directory

__all__ = [
    "Terminated",
    "atomic_output_dir",
    "check_output_dir",
    "csv_field",
    "csv_rows",
    "recover_leftovers",
    "save_run",
    "signals_as_exceptions",
    "write_json",
    "write_timeseries",
    "write_trajectories",
]

#: Signals that end a command cleanly (temporaries removed) instead of killing it outright.
CLEAN_EXIT_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_LEFTOVER_RE = re.compile(r"^\.(?P<name>.+)\.(?P<kind>tmp|old)-(?P<pid>\d+)(?:-.*)?$")
#: Characters the temporary's name adds to ``OUT``'s (``.`` + ``.tmp-`` + pid + ``-`` + 8).
_TMP_EXTRA = 1 + 5 + 10 + 1 + 8


class Terminated(BaseException):
    """SIGTERM or SIGHUP received: raised in the main thread so that cleanups run (a
    ``BaseException``, so that ``except Exception`` blocks do not swallow it)."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(f"stopped by {signal.Signals(signum).name}")


@contextlib.contextmanager
def signals_as_exceptions() -> Iterator[None]:
    """Within the block, SIGTERM/SIGHUP raise :class:`Terminated` (SIGINT already raises
    ``KeyboardInterrupt``), so ``finally`` blocks remove temporaries. Signals that already
    have a handler keep it; outside the main thread this does nothing."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    terminate = raising_handler(Terminated)
    interrupt = raising_handler(lambda signum: KeyboardInterrupt())
    # A handler someone else installed (a runtime process stopping gracefully) is respected.
    wanted = {signal.SIGTERM: terminate, signal.SIGHUP: terminate, signal.SIGINT: interrupt}
    defaults = {signal.SIGTERM: signal.SIG_DFL, signal.SIGHUP: signal.SIG_DFL}
    defaults[signal.SIGINT] = signal.default_int_handler
    free = [s for s in wanted if signal.getsignal(s) in (defaults[s], wanted[s])]
    previous = {s: signal.signal(s, wanted[s]) for s in free}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


# ---------------------------------------------------------------------------- checks
def check_output_dir(out: Path, overwrite: bool = False, inputs: Sequence[str | Path] = ()) -> None:
    """Check ``--out`` before any work (see the module doc); recover a killed run's leftovers.

    Parameters
    ----------
    out : Path
    overwrite : bool
        Allow replacing a non-empty directory.
    inputs : sequence of Path
        Files or folders the command reads: ``out`` may not lie inside one, nor (with
        ``overwrite``) contain one.

    Raises
    ------
    ConfigError
        One line naming ``--out`` and the fix.
    """
    out = Path(out)
    text = str(out)
    if not text.strip() or "\n" in text or "\x00" in text:
        raise ConfigError(f"--out {text!r}: not a usable path; name a new directory")
    target = Path(os.path.abspath(out))
    cwd = Path.cwd()
    if target == cwd or target in cwd.parents:
        raise ConfigError(
            f"--out {out}: is the current directory or one of its parents; name a new "
            "subdirectory such as runs/NAME"
        )
    _check_names(out, target)
    for item in inputs:
        src = Path(os.path.abspath(item))
        if target == src or src in target.parents:
            raise ConfigError(
                f"--out {out}: lies inside the input {item}; write the results elsewhere"
            )
        if overwrite and target in src.parents:
            raise ConfigError(
                f"--out {out}: holds the input {item}, which --overwrite would delete; "
                "write the results elsewhere"
            )
    existing = _nearest_existing(target)
    if existing != target and not existing.is_dir():
        raise ConfigError(f"--out {out}: {existing} is a file, not a directory")
    recover_leftovers(target)
    if target.exists() and not target.is_dir():
        raise ConfigError(f"--out {out}: exists and is not a directory; choose another path")
    if target.exists() and any(target.iterdir()) and not overwrite:
        raise ConfigError(
            f"--out {out}: directory exists and is not empty; choose another or pass --overwrite"
        )
    _probe_writable(out, existing, target)


def _check_names(out: Path, target: Path) -> None:
    anchor = _nearest_existing(target)
    try:
        name_max = os.pathconf(anchor if anchor.is_dir() else anchor.parent, "PC_NAME_MAX")
        path_max = os.pathconf(anchor if anchor.is_dir() else anchor.parent, "PC_PATH_MAX")
    except (OSError, ValueError):
        name_max, path_max = 255, 4096
    for part in target.relative_to(anchor).parts if target != anchor else ():
        if len(part.encode()) > name_max:
            raise ConfigError(
                f"--out {out}: the name {part[:20]!r}... has {len(part.encode())} bytes; "
                f"this file system allows {name_max}"
            )
    if len(target.name.encode()) + _TMP_EXTRA > name_max:
        raise ConfigError(
            f"--out {out}: the name {target.name[:20]!r}... is too long; use at most "
            f"{name_max - _TMP_EXTRA} bytes (its temporary sibling needs {_TMP_EXTRA} more)"
        )
    if len(str(target).encode()) + _TMP_EXTRA + 64 > path_max:
        raise ConfigError(f"--out {out}: the path is too long; use a shorter one")


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _probe_writable(out: Path, existing: Path, target: Path) -> None:
    """Create and remove a directory where the results will go (catches read-only file
    systems, missing permissions and quotas that ``os.access`` does not)."""
    where = existing if existing != target else target.parent
    try:
        with temporary_directory(f".{target.name}.tmp-{os.getpid()}-", where):
            pass
    except OSError as exc:
        reason = exc.strerror or exc.__class__.__name__
        raise ConfigError(f"--out {out}: cannot create a directory in {where} ({reason})") from None


# ---------------------------------------------------------------------------- leftovers
def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def recover_leftovers(out: Path, log=None) -> list[str]:
    """Clean what a killed command left next to ``out`` and restore lost results.

    For each hidden sibling ``.NAME.tmp-PID-*`` or ``.NAME.old-PID`` whose process ``PID``
    is no longer running: an ``.old`` directory is renamed back to ``out`` when ``out`` is
    missing (the kill fell between the two renames of a replacement), every other leftover
    is removed. Leftovers of running processes are left alone (and named).

    Parameters
    ----------
    out : Path
    log : callable(str), optional
        Receives one line per action (default: ``note: ...`` on stderr).

    Returns
    -------
    list of str
        The actions taken.
    """
    out = Path(os.path.abspath(out))
    parent = out.parent
    if not parent.is_dir():
        return []
    log = log or (lambda line: print(f"note: {line}", file=sys.stderr))
    found = []
    try:
        entries = list(parent.iterdir())
    except OSError:
        return []
    actions = []
    for p in entries:
        m = _LEFTOVER_RE.match(p.name)
        if not m or m["name"] != out.name:
            continue
        pid = int(m["pid"])
        if not _pid_alive(pid):
            found.append((0 if m["kind"] == "old" else 1, p, m["kind"], pid))
        elif pid != os.getpid():
            actions.append(f"{p.name} belongs to running process {pid}; left alone")
    for _, p, kind, pid in sorted(found):
        if kind == "old" and not out.exists():
            p.rename(out)
            actions.append(f"restored {out} from {p.name} (a replacement killed midway, pid {pid})")
        else:
            shutil.rmtree(p, ignore_errors=True)
            what = "temporary" if kind == "tmp" else "previous results"
            actions.append(f"removed {p.name}, the {what} of a killed run (pid {pid})")
    for line in actions:
        log(line)
    return actions


# ---------------------------------------------------------------------------- atomic swap
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux ``renameat2(RENAME_EXCHANGE)``); False if the OS
    or file system cannot."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    rc = fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


@contextlib.contextmanager
def atomic_output_dir(
    out: Path, overwrite: bool = False, inputs: Sequence[str | Path] = ()
) -> Iterator[Path]:
    """Yield a temporary sibling directory; on success it replaces ``out`` atomically.

    On any exception (including SIGINT, SIGTERM, SIGHUP) the temporary directory is removed
    and ``out`` is left untouched, so nothing half-written is ever visible at ``out``. With
    ``overwrite`` an existing ``out`` is swapped with the new results in one
    ``renameat2(RENAME_EXCHANGE)`` where the OS allows it; elsewhere by two renames, and a
    kill between them is repaired by the next :func:`check_output_dir`.
    """
    out = Path(out)
    check_output_dir(out, overwrite, inputs)
    out.parent.mkdir(parents=True, exist_ok=True)
    prefix = f".{out.name}.tmp-{os.getpid()}-"
    # After a swap the temporary holds the old results; it is removed either way.
    with signals_as_exceptions(), temporary_directory(prefix, out.parent) as tmp:
        umask = os.umask(0)
        os.umask(umask)
        tmp.chmod(0o777 & ~umask)  # mkdtemp creates 0700; give the usual directory mode
        yield tmp
        _replace(tmp, out)


def _replace(tmp: Path, out: Path) -> None:
    """Put ``tmp`` at ``out`` (whose old content, if any, ends up at ``tmp``)."""
    blocked = set(CLEAN_EXIT_SIGNALS)
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, blocked)
    try:
        if not out.exists():
            tmp.rename(out)
            return
        if _exchange(tmp, out):
            return
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        out.rename(old)
        try:
            tmp.rename(out)
        except BaseException:
            old.rename(out)
            raise
        old.rename(tmp)  # removed by the caller, like a swapped-out directory
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)


# ---------------------------------------------------------------------------- writers
def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, float | np.floating):
        f = float(v)
        return None if math.isnan(f) or math.isinf(f) else f
    return v


def write_json(path: Path, data: Any) -> None:
    """Write JSON with NaN/inf as ``null`` (strict JSON)."""
    path.write_text(json.dumps(_jsonable(data), indent=2) + "\n", encoding="utf-8")


def warn(message: str) -> None:
    """One ``warning: ...`` line on stderr."""
    print(f"warning: {message}", file=sys.stderr)


def draw_plots(draw, *args, what: str = "figures") -> list[Path]:
    """Call a plotting function; if it fails, warn in one line and return no files.

    Figures are a view of data already written: a figure that cannot be drawn (a
    matplotlib error, a missing font, a backend problem) must not cost the data.
    """
    try:
        return list(draw(*args))
    except Exception as exc:  # any plotting failure is only a warning
        detail = str(exc).splitlines()[0] if str(exc) else ""
        warn(f"{what} skipped ({exc.__class__.__name__}: {detail[:160]}); the data are written")
        return []


def save_run(result, out: Path, plots: bool = True) -> list[Path]:
    """Write a :class:`~resloc.experiments.runner.RunResult` into directory ``out``.

    Files: ``scenario.toml`` (resolved, re-runnable), ``summary.json``, ``timeseries.csv``
    (per step and estimator: means over trials), ``transmissions_<filter>.csv`` (robot x
    step raster of trial 0), ``trajectories.csv`` (trial 0, truth and estimates),
    ``recording.npz`` (trial 0 step by step, for ``resloc export``) and, with
    matplotlib, ``trajectories.png``, ``msle.png`` and ``transmissions.png`` (a figure that
    cannot be drawn is skipped with a warning).

    Returns
    -------
    list of Path
        The files written.
    """
    from resloc.experiments.config_dump import dump_scenario

    out = Path(out)
    written = []
    p = out / "scenario.toml"
    p.write_text(dump_scenario(result.scenario), encoding="utf-8")
    written.append(p)
    p = out / "summary.json"
    write_json(
        p,
        {
            "scenario": result.scenario.run.name,
            "seed": result.scenario.run.seed,
            "trials": result.scenario.run.trials,
            "robots": result.meta.get("robots"),
            "steps": result.scenario.run.steps,
            "wall_time_s": result.wall_time,
            "estimators": result.summary(),
            "diverged": {
                name: est.diverged
                for name, est in result.estimators.items()
                if getattr(est, "diverged", None)
            },
        },
    )
    written.append(p)
    p = out / "timeseries.csv"
    write_timeseries(p, result)
    written.append(p)
    for name, est in result.estimators.items():
        if name == "dr":
            continue
        p = out / f"transmissions_{name}.csv"
        np.savetxt(p, est.raster.T, fmt="%d", delimiter=",", header="rows: robots, cols: steps")
        written.append(p)
    p = out / "trajectories.csv"
    write_trajectories(p, result)
    written.append(p)
    from resloc.experiments.recording import RECORDING_FILE, recording_from_run

    written.append(recording_from_run(result).save(out / RECORDING_FILE))
    if plots:
        from resloc.experiments import plots as plotting

        written += draw_plots(plotting.plot_run, result, out)
    return written


#: The line ending of Python's ``csv`` module, which the files have always used.
CSV_LINE_END = "\r\n"


def csv_field(text: str) -> str:
    """One CSV field as :mod:`csv` writes it (quoted when it holds a comma, a quote or a
    line break)."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator=CSV_LINE_END).writerow([text])
    return buf.getvalue().removesuffix(CSV_LINE_END)


def csv_rows(row_format: str, columns: Sequence[Sequence]) -> str:
    """Rows of CSV text from whole columns, formatted by one ``%`` operation.

    The same bytes as ``csv.writer`` writing one row at a time with each value formatted
    by the matching ``%`` code (Python's float formatting is the same under ``%`` and
    ``format``), at a fraction of the cost: no Python call per row or field.

    Parameters
    ----------
    row_format : str
        One row's ``%`` format without the line ending, e.g. ``"%d,%s,%.5f"``; string
        fields must already be CSV fields (:func:`csv_field`).
    columns : sequence of sequences, each of length ``n``
        The fields, column by column (lists of Python numbers format fastest).

    Returns
    -------
    str
        ``n`` rows, each ending in ``\\r\\n``.
    """
    n = len(columns[0]) if columns else 0
    if n == 0:
        return ""
    values = tuple(itertools.chain.from_iterable(zip(*columns, strict=True)))
    return ((row_format + CSV_LINE_END) * n) % values


TIMESERIES_COLUMNS = (
    "step",
    "time_s",
    "estimator",
    "msle",
    "rmse",
    "nees",
    "comm_rate",
    "detected",
)
TRAJECTORY_COLUMNS = ("step", "robot", "source", "x", "y", "theta")


def write_timeseries(path: Path, result) -> None:
    """``timeseries.csv``: per step and estimator, the means over trials."""
    steps = len(result.time)
    step_numbers = list(range(1, steps + 1))
    times = np.asarray(result.time, float).tolist()
    parts = [",".join(TIMESERIES_COLUMNS) + CSV_LINE_END]
    for name, est in result.estimators.items():
        s = est.series
        with np.errstate(invalid="ignore", divide="ignore"), _quiet_empty_means():
            comm_rate = s["triggered"].sum(axis=1) / s["candidates"].sum(axis=1)
            means = [np.nanmean(s[key], axis=1).tolist() for key in ("msle", "rmse", "nees")]
        detected = np.nansum(s["detected"], axis=1).astype(np.int64).tolist()
        columns = [step_numbers, times, [csv_field(name)] * steps, *means]
        columns += [comm_rate.tolist(), detected]
        parts.append(csv_rows("%d,%.4f,%s,%.6g,%.6g,%.6g,%.6g,%d", columns))
    path.write_text("".join(parts), encoding="utf-8", newline="")


def write_trajectories(path: Path, result) -> None:
    """``trajectories.csv``: trial 0's true and estimated poses, step by step."""
    sources = {"truth": result.truth} | {n: e.track for n, e in result.estimators.items()}
    parts = [",".join(TRAJECTORY_COLUMNS) + CSV_LINE_END]
    for source, poses in sources.items():
        steps, robots = poses.shape[:2]
        rows = steps * robots
        flat = np.asarray(poses, float).reshape(rows, 3)
        columns = [
            np.repeat(np.arange(steps), robots).tolist(),
            np.tile(np.arange(robots), steps).tolist(),
            [csv_field(source)] * rows,
            *(flat[:, c].tolist() for c in range(3)),
        ]
        parts.append(csv_rows("%d,%d,%s,%.5f,%.5f,%.5f", columns))
    path.write_text("".join(parts), encoding="utf-8", newline="")


@contextlib.contextmanager
def _quiet_empty_means() -> Iterator[None]:
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Mean of empty slice", RuntimeWarning)
        yield
