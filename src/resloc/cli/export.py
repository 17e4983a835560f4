"""``resloc export``: write a run directory as TUM, a ROS 2 bag, a Foxglove scene or HTML.

Also the ``--export`` option of ``resloc run`` and ``resloc mrclam``. Nothing here imports
``rosbags`` or ``mcap``: the writers import them when a format is written.
"""

from __future__ import annotations

from pathlib import Path

import typer

from resloc.cli.common import handle_errors, print_table

__all__ = ["EXPORT_HELP", "export_command", "export_option", "print_alignment", "write_exports"]

EXPORT_HELP = (
    "Also write these exports into OUT/export/: tum, rosbag, foxglove, html or all "
    "(comma-separated; see resloc export --help)."
)


def export_option():
    """The ``--export`` option shared by ``run`` and ``mrclam``."""
    return typer.Option(None, "--export", help=EXPORT_HELP, callback=_check_export)


def _check_export(value: str | None) -> str | None:
    """Validate ``--export`` at parse time (before any run) and check its dependencies."""
    from resloc.cli.common import fail
    from resloc.errors import ResLocError
    from resloc.export import check_dependencies, parse_formats

    try:
        check_dependencies(parse_formats(value, "--export"))
    except ResLocError as exc:
        raise fail(str(exc)) from None
    return value


def print_alignment(results) -> None:
    """Print the TUM alignment table (raw, team-aligned, per-robot aligned RMSE)."""
    for res in results:
        if res.format.value != "tum":
            continue
        rows = [
            (
                "DR" if name == "dr" else name.upper(),
                f"{e['raw']:.4f}",
                f"{e['team']:.4f}",
                f"{e['per_robot']:.4f}",
            )
            for name, e in res.info.items()
        ]
        print_table(
            "position RMSE (m): raw / team-aligned (one SE(2) for all robots) / per-robot aligned",
            ("estimator", "raw", "team-aligned", "per-robot aligned"),
            rows,
            width=None,
        )


def write_exports(
    run_dir: Path,
    formats: str | None,
    out: Path | None = None,
    overwrite: bool = False,
    estimator: str | None = None,
    rate: float | None = None,
):
    """Export a finished run directory (no-op without formats); print where it went."""
    from resloc.export import ExportOptions, export_run_dir, parse_formats

    fmts = parse_formats(formats, "--export" if out is None else "--format")
    if not fmts:
        return []
    results = export_run_dir(run_dir, fmts, out, overwrite, ExportOptions(estimator, rate))
    print_alignment(results)
    for res in results:
        shown = res.path.relative_to(run_dir) if res.path.is_relative_to(run_dir) else res.path
        print(f"export {res.format.value}: {shown}")
    return results


@handle_errors
def export_command(
    run_dir: Path = typer.Argument(..., help="A directory written by resloc run or resloc mrclam."),
    formats: list[str] = typer.Option(
        [],
        "--format",
        "-F",
        help="tum, rosbag, foxglove, html or all (repeat, or comma-separate).",
    ),
    out: Path | None = typer.Option(
        None, "--out", "-o", help="Export directory (default: RUN_DIR/export)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing exports."),
    estimator: str | None = typer.Option(
        None,
        "--estimator",
        "-e",
        help="Estimator on /tf and shown first (default: the first filter).",
    ),
    rate: float | None = typer.Option(
        None,
        "--rate",
        help="Highest rate (Hz) of bag, scene, viewer (default: every step; scene 10 Hz).",
    ),
):
    """Export a run for evo (TUM), ROS 2 (MCAP bag), Foxglove, or a browser (HTML)."""
    from resloc.errors import ConfigError

    if not formats:
        raise ConfigError("--format: give at least one of tum, rosbag, foxglove, html, all")
    return write_exports(
        run_dir, ",".join(formats), out or Path(run_dir) / "export", overwrite, estimator, rate
    )


def register(app: typer.Typer) -> None:
    """Add ``export`` to ``app``."""
    app.command("export")(export_command)
