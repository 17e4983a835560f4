"""Entry point and common scaffolding of every runtime process.

``python -m resloc.runtime.process ROLE OPTIONS.json [ROBOT_IDS]`` runs the world, radio,
recorder or robot(s) of a run. Each process opens one Zenoh client session (to the run's
router), declares a liveliness token, and always closes its session and leaves within
bounded time (SIGTERM and errors included): a Zenoh session with a Python subscriber keeps
the interpreter alive otherwise.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from pathlib import Path

from resloc.errors import ResLocError
from resloc.runtime.messages import Codec, Verifier, load_or_create_key
from resloc.runtime.options import SwarmOptions
from resloc.runtime.transport import Bus, open_session

__all__ = ["connect_bus", "exit_now", "main"]

#: Exit codes: 0 done, 2 bad input, 3 the run ended abnormally (a peer was lost).
EXIT_OK, EXIT_BAD_INPUT, EXIT_LOST = 0, 2, 3


class TerminatedError(Exception):
    """SIGTERM (or SIGINT) asked this process to stop."""


def _on_signal(signum, frame) -> None:
    raise TerminatedError(signal.Signals(signum).name)


def install_signal_handlers(ignore_sigint: bool = True) -> None:
    """SIGTERM stops the process cleanly; SIGINT is the supervisor's business (children
    run in their own session, but ignore it too in case it reaches them)."""
    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, signal.SIG_IGN if ignore_sigint else _on_signal)


def connect_bus(options: SwarmOptions, sender: int) -> Bus:
    """Open this process's verified session and bus (client of the run's router)."""
    key = load_or_create_key(options.key_file)
    session = open_session("client", [], list(options.connect), options.connect_timeout_s)
    return Bus(session, options.run_id, Codec(key, sender), Verifier(key, options.max_age_s))


def exit_now(code: int, bus: Bus | None = None, grace_s: float = 5.0) -> None:
    """Close ``bus`` and leave with ``code`` within ``grace_s`` seconds, whatever hangs."""
    timer = threading.Timer(grace_s, lambda: os._exit(code))
    timer.daemon = True
    timer.start()
    if bus is not None:
        bus.close()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main(argv: list[str] | None = None) -> None:
    """``python -m resloc.runtime.process ROLE OPTIONS.json [IDS]``."""
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2:
        print("usage: python -m resloc.runtime.process ROLE OPTIONS.json [IDS]", file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)
    role, opts_path = argv[0], Path(argv[1])
    install_signal_handlers()
    options = SwarmOptions.load(opts_path)
    code = EXIT_OK
    try:
        if role == "world":
            from resloc.runtime.world_process import run_world as run
        elif role == "radio":
            from resloc.runtime.radio import run_radio as run
        elif role == "recorder":
            from resloc.runtime.recorder import run_recorder as run
        elif role == "robot":
            from resloc.runtime.robot_process import run_robots

            ids = [int(v) for v in argv[2].split(",")]

            def run(opts):
                return run_robots(opts, ids)
        else:
            print(f"error: unknown role {role!r}", file=sys.stderr)
            exit_now(EXIT_BAD_INPUT)
        code = run(options)
    except ResLocError as exc:
        print(f"error: {role}: {exc}", file=sys.stderr)
        code = EXIT_BAD_INPUT
    except TerminatedError:
        code = EXIT_OK
    exit_now(code)


if __name__ == "__main__":
    main()
