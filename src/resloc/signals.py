"""Signal handlers that raise an exception, but never inside a finalizer.

Python runs a signal handler between two bytecodes of whatever is executing, which can be a
weakref callback or a ``__del__`` run by the garbage collector. An exception raised there
cannot propagate: Python prints "Exception ignored in ..." with a traceback and the signal
is lost (measured: Ctrl-C and SIGTERM of ``resloc run`` were ignored that way). These
handlers re-deliver the signal instead while a finalizer runs (from a helper thread: a
``kill`` from the handler itself would run the handler again at once, still inside the
finalizer), so it is raised as soon as the finalizer returns.
"""

from __future__ import annotations

import _thread
import os
from collections.abc import Callable

__all__ = ["raising_handler"]

_FINALIZER_FILES = ("weakref.py", "_weakrefset.py")


def _in_finalizer(frame) -> bool:
    if frame is None:
        return False
    code = frame.f_code
    return code.co_name == "__del__" or code.co_filename.endswith(_FINALIZER_FILES)


def raising_handler(make_exception: Callable[[int], BaseException]):
    """A handler for :func:`signal.signal` that raises ``make_exception(signum)`` in the
    main thread, deferred while a finalizer is running."""

    def handler(signum, frame):
        if _in_finalizer(frame):
            _thread.start_new_thread(os.kill, (os.getpid(), signum))
            return
        raise make_exception(signum)

    return handler
