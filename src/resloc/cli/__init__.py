"""Command-line interface (thin: parse, call an importable ``run_*`` function, save)."""

import sys


def _one_line_interrupt(exc_type, exc, tb):
    """Ctrl-C while the command is still starting (imports): one line, not a traceback."""
    if issubclass(exc_type, KeyboardInterrupt):
        print("error: interrupted (SIGINT) while starting; nothing was written", file=sys.stderr)
        return
    sys.__excepthook__(exc_type, exc, tb)


def _install() -> None:
    import signal
    import threading

    from resloc.signals import raising_handler

    sys.excepthook = _one_line_interrupt
    # Ctrl-C raises KeyboardInterrupt as usual, but never inside a finalizer (where Python
    # would print a traceback and drop it).
    if (
        threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGINT) is signal.default_int_handler
    ):
        signal.signal(signal.SIGINT, raising_handler(lambda signum: KeyboardInterrupt()))


# Installed as soon as the command line is imported; typer installs its own hook when the
# app runs, and the commands map KeyboardInterrupt themselves (exit 130).
_install()
