"""Command-line interface (thin: parse, call an importable ``run_*`` function, save)."""

import sys


def _one_line_interrupt(exc_type, exc, tb):
    """Ctrl-C while the command is still starting (imports): one line, not a traceback."""
    if issubclass(exc_type, KeyboardInterrupt):
        print("error: interrupted (SIGINT) while starting; nothing was written", file=sys.stderr)
        return
    sys.__excepthook__(exc_type, exc, tb)


# Installed as soon as the command line is imported; typer installs its own hook when the
# app runs, and the commands map KeyboardInterrupt themselves (exit 130).
sys.excepthook = _one_line_interrupt
