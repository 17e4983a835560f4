"""The ``resloc`` command. Each sub-command lives in its own module with a ``register``."""

from __future__ import annotations

import typer

from resloc import __version__
from resloc.cli.common import OneLineErrors

app = typer.Typer(
    name="resloc",
    cls=OneLineErrors,
    help="Resilient distributed multi-robot cooperative localization (CKF / UKF / EKF).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)


def _version(value: bool) -> None:
    if value:
        print(f"resloc {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version."
    ),
) -> None:
    """Resilient distributed multi-robot cooperative localization."""


def _register_all() -> None:
    # One line per command module; each module defines ``register(app)``.
    from resloc.cli import run as _run

    _run.register(app)
    from resloc.cli import sweep as _sweep

    _sweep.register(app)
    from resloc.cli import reproduce as _reproduce

    _reproduce.register(app)
    from resloc.cli import mrclam as _mrclam

    _mrclam.register(app)
    from resloc.cli import compare as _compare

    _compare.register(app)
    from resloc.cli import attack as _attack

    _attack.register(app)
    from resloc.cli import export as _export

    _export.register(app)
    from resloc.cli import swarm as _swarm  # imports zenoh only when the command runs

    _swarm.register(app)
    from resloc.cli import robot as _robot

    _robot.register(app)


_register_all()


def main() -> None:
    """Console-script entry point."""
    app()
