"""Signal handlers that raise an exception, but never inside a finalizer.

Python runs a signal handler between two bytecodes of whatever is executing, which can be a
weakref callback or a ``__del__`` run by the garbage collector. An exception raised there
cannot propagate: Python prints "Exception ignored in ..." with a traceback and the signal
is lost (measured: Ctrl-C and SIGTERM of ``resloc run`` were ignored that way). These
handlers re-deliver the signal instead while a finalizer runs (from a helper thread: a
``kill`` from the handler itself would run the handler again at once, still inside the
finalizer), so it is raised as soon as the finalizer returns.

The same loss happens in code called back from C (a ``ctypes`` callback: numba's compiler
calls one while it writes its cache, so a SIGTERM during the first compilation was printed
as "Exception ignored on calling ctypes callback function" and lost). There the frame does
not say so; the exception reaches :data:`sys.unraisablehook`, which these handlers wrap
to re-deliver their own signals instead of printing them.

A third place is a write that a library cannot leave cleanly: numpy's ``savez`` interrupted
inside its zip member's ``close`` leaves the ``ZipFile`` with an open write handle, whose
``__del__`` prints a traceback when the exception frees it (measured: Ctrl-C during ``resloc
run``'s recording, the run itself stopping cleanly). :func:`held` keeps these handlers'
signals pending over such a block and raises them when it ends. The same holds for making
and removing a temporary directory (:func:`temporary_directory`):
a Ctrl-C inside ``mkdtemp`` (after its ``mkdir``, before it returns) or part-way through
``rmtree`` left a hidden ``.OUT.tmp-*`` behind after a clean stop (measured, once in a CI
run of the kill test), and so did one that landed as the removal was entering its hold
(once in a fresh clone's kill test): the removal keeps that exception and raises it once
the directory is gone.
"""

from __future__ import annotations

import _thread
import os
import shutil
import signal
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["held", "raising_handler", "temporary_directory"]

_FINALIZER_FILES = ("weakref.py", "_weakrefset.py")
#: Marks an exception raised by one of these handlers with its signal number.
_SIGNAL_ATTRIBUTE = "resloc_signal"


#: Open :func:`held` blocks, and the signals that arrived during them (in order).
_HOLD = {"depth": 0, "pending": []}


@contextmanager
def held() -> Iterator[None]:
    """Run the block with the signals of :func:`raising_handler` handlers held: one that
    arrives meanwhile is raised when the outermost block ends (its exception then, not
    inside the block). For short writes only: a held Ctrl-C waits for the block."""
    _HOLD["depth"] += 1
    try:
        yield
    finally:
        _HOLD["depth"] -= 1
        if _HOLD["depth"] == 0 and _HOLD["pending"]:
            signum = _HOLD["pending"][0]
            _HOLD["pending"].clear()
            signal.raise_signal(signum)


@contextmanager
def temporary_directory(prefix: str, where: Path) -> Iterator[Path]:
    """A new directory ``where/PREFIX*`` (``tempfile.mkdtemp``) for the block, removed with
    everything in it when the block ends, however it ends. Making and removing it run
    with signals held, so a signal arrives either before the directory exists or after
    its path is known (and is then raised, the directory still removed)."""
    path = None
    try:
        with held():
            path = Path(tempfile.mkdtemp(prefix=prefix, dir=where))
        yield path
    finally:
        if path is not None:
            _remove_held(path)


def _remove_held(path: Path, attempts: int = 3) -> None:
    """Remove the directory ``path`` with signals held. A handler's exception raised before
    the hold takes effect (between the bytecodes that enter it) is kept and raised once the
    directory is gone, as is the signal the hold kept pending."""
    stopped = None
    for _ in range(attempts):
        try:
            with held():
                shutil.rmtree(path, ignore_errors=True)
        except BaseException as exc:  # a signal's exception: raised below, once removed
            stopped = exc
        if not path.exists():
            break
    if stopped is not None:
        raise stopped


def _in_finalizer(frame) -> bool:
    if frame is None:
        return False
    code = frame.f_code
    return code.co_name == "__del__" or code.co_filename.endswith(_FINALIZER_FILES)


def _redeliver(signum: int) -> None:
    _thread.start_new_thread(os.kill, (os.getpid(), signum))


def _redelivering_hook(previous: Callable) -> Callable:
    """``sys.unraisablehook`` that re-delivers a signal our handler raised where it could
    not propagate, and passes everything else to ``previous``."""

    def hook(unraisable) -> None:
        signum = getattr(unraisable.exc_value, _SIGNAL_ATTRIBUTE, None)
        if signum is None:
            previous(unraisable)
        else:
            _redeliver(signum)

    hook.redelivers_signals = True
    return hook


def raising_handler(make_exception: Callable[[int], BaseException]):
    """A handler for :func:`signal.signal` that raises ``make_exception(signum)`` in the
    main thread, deferred while a finalizer or a callback from C is running."""
    if not getattr(sys.unraisablehook, "redelivers_signals", False):
        sys.unraisablehook = _redelivering_hook(sys.unraisablehook)

    def handler(signum, frame):
        if _HOLD["depth"]:
            _HOLD["pending"].append(signum)
            return
        if _in_finalizer(frame):
            _redeliver(signum)
            return
        exc = make_exception(signum)
        setattr(exc, _SIGNAL_ATTRIBUTE, signum)
        raise exc

    return handler
