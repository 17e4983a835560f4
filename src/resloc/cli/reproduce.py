"""``resloc reproduce``: every experiment of the paper, one command, one report."""

from __future__ import annotations

import contextlib
from pathlib import Path

import typer

from resloc.cli.common import (
    OVERWRITE,
    PROGRESS,
    handle_errors,
    out_option,
    print_table,
    timestamped_out,
)
from resloc.cli.study import FRESH, JOBS, SCHEDULER, STORE, study_session

__all__ = ["register", "reproduce_command"]


@handle_errors
def reproduce_command(
    seeds: int | None = typer.Option(
        None, "--seeds", min=2, help="Seeds per experiment \\[default: 10; 2 with --quick]."
    ),
    jobs: int | None = JOBS,
    scheduler: str | None = SCHEDULER,
    store: Path | None = STORE,
    fresh: bool = FRESH,
    quick: bool = typer.Option(
        False, "--quick", help="2 seeds and short runs: a smoke test (under a minute)."
    ),
    steps: int | None = typer.Option(
        None, "--steps", min=1, help="Steps per run \\[default: the scenario's]."
    ),
    out: Path | None = out_option("runs/reproduce-<timestamp>"),
    overwrite: bool = OVERWRITE,
    progress: bool = PROGRESS,
):
    """Re-run every experiment of the paper over seeds and write report.md/report.html."""
    from resloc.experiments.output import atomic_output_dir, check_output_dir
    from resloc.experiments.plots import pyplot
    from resloc.experiments.reproduce import run_reproduction, write_reproduction

    out = out or timestamped_out("reproduce")
    check_output_dir(out, overwrite)
    pyplot()  # the report needs matplotlib: fail before the runs if it is missing
    what = "reproducing the paper's experiments"
    with study_session(what, jobs, scheduler, store, fresh, progress, out, overwrite) as study:
        rep = run_reproduction(seeds=seeds, steps=steps, quick=quick, study=study)
    status = contextlib.nullcontext()
    if progress:
        from rich.console import Console

        status = Console(stderr=True).status("writing the report (figures, tables)")
    with status, atomic_output_dir(out, overwrite) as tmp:
        claims, _ = write_reproduction(rep, tmp)
    print_claims(claims, rep)
    print(f"report written to {out}/report.md and {out}/report.html")
    return rep, claims


def print_claims(claims, rep) -> None:
    """The short claims table."""
    style = {
        "holds": "green",
        "does not hold": "red",
        "not reproduced": "magenta",
        "inconclusive": "yellow",
    }
    rows = [(c.figure, c.short, f"[{style[c.verdict.value]}]{c.verdict.value}[/]") for c in claims]
    title = (
        f"paper claims vs measured ({rep.seeds} seeds, {rep.steps} steps, "
        f"{rep.wall_time:.0f} s{', quick' if rep.quick else ''})"
    )
    print_table(title, ("figure", "claim", "verdict"), rows, labels=3, width=110)


def register(app: typer.Typer) -> None:
    """Add ``reproduce`` to ``app``."""
    app.command("reproduce")(reproduce_command)
