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
import ctypes
import ctypes.util
import errno
import os
import re
import shutil
import signal
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

from resloc.errors import ConfigError
from resloc.signals import raising_handler, temporary_directory

__all__ = [
    "Terminated",
    "atomic_output_dir",
    "check_output_dir",
    "recover_leftovers",
    "signals_as_exceptions",
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
    # After a swap the temporary held the old results: _replace removes them.
    with signals_as_exceptions(), temporary_directory(prefix, out.parent) as tmp:
        umask = os.umask(0)
        os.umask(umask)
        tmp.chmod(0o777 & ~umask)  # mkdtemp creates 0700; give the usual directory mode
        yield tmp
        _replace(tmp, out)


def _replace(tmp: Path, out: Path) -> None:
    """Put ``tmp`` at ``out`` and remove ``out``'s old content, if any, with the clean-exit
    signals blocked throughout: a signal handled between the swap and a later removal (in
    Python, any bytecode) would leave the old content at ``tmp``."""
    blocked = set(CLEAN_EXIT_SIGNALS)
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, blocked)
    try:
        if not out.exists():
            tmp.rename(out)
            return
        if not _exchange(tmp, out):
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            out.rename(old)
            try:
                tmp.rename(out)
            except BaseException:
                old.rename(out)
                raise
            old.rename(tmp)
        shutil.rmtree(tmp, ignore_errors=True)  # the old content
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
