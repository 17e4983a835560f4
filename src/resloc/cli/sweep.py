"""``resloc sweep``: scenario parameters over points (one, grid, zip) x seeds x filters."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from resloc.cli.common import (
    OVERWRITE,
    PLOTS,
    PROGRESS,
    handle_errors,
    out_option,
    print_table,
    timestamped_out,
)
from resloc.cli.study import FRESH, JOBS, SCHEDULER, STORE, study_session

__all__ = ["print_sweep", "register", "sweep_command"]


@handle_errors
def sweep_command(
    path: Path = typer.Argument(
        ...,
        help="Sweep file: a scenario file plus \\[sweep] (parameter and values, or "
        "\\[sweep.grid] / \\[sweep.zip]).",
    ),
    seeds: int | None = typer.Option(
        None, "--seeds", min=1, help="Seeds per value \\[default: the file's run.trials]."
    ),
    steps: int | None = typer.Option(None, "--steps", min=1, help="Override run.steps."),
    jobs: int | None = JOBS,
    scheduler: str | None = SCHEDULER,
    store: Path | None = STORE,
    fresh: bool = FRESH,
    out: Path | None = out_option("runs/sweep-<timestamp>"),
    overwrite: bool = OVERWRITE,
    plots: bool = PLOTS,
    progress: bool = PROGRESS,
):
    """Run a scenario at every point of a sweep (one parameter, a grid or zipped
    parameters) x seeds x filters, as cells on a Dask cluster, kept in the result store
    (a failed cell does not stop the others; it is in cells.csv and failures.json, exit 1)."""
    from resloc.experiments.output import atomic_output_dir, check_output_dir
    from resloc.experiments.sweep import load_sweep, run_sweep, save_sweep

    spec = load_sweep(path)
    out = out or timestamped_out("sweep")
    check_output_dir(out, overwrite, [path])  # before any work: a bad --out loses nothing
    spec.with_run(seeds, steps).scenarios()  # every point valid before any work
    if plots:
        from resloc.experiments.plots import pyplot

        pyplot()
    points = len(spec.values)
    with study_session(
        f"sweep {spec.axis_label} ({points} points)", jobs, scheduler, store, fresh, progress
    ) as study:
        result = run_sweep(spec, seeds=seeds, steps=steps, study=study)
    print_sweep(result)
    with atomic_output_dir(out, overwrite, [path]) as tmp:
        save_sweep(result, tmp, plots=plots)
    print(f"results written to {out}/ (sweep.toml, summary.json, cells.csv, sweep.csv, plots)")
    if result.failures:
        print(
            f"error: {len(result.failures)} cell(s) failed; the others are in the results; "
            f"details (scenario, traceback): {out}/failures.json",
            file=sys.stderr,
        )
        raise typer.Exit(1)
    return result


def print_sweep(result) -> None:
    """Print one row per value: each filter's metric and the communication rate (95% CI)."""
    from resloc.experiments.stats import mean_ci

    spec = result.spec
    columns = [spec.axis_label]
    for f in result.filters:
        columns += [f"{f.upper()} {spec.metric}", f"{f.upper()} comm rate"]
    rows = []
    for k, v in enumerate(spec.values):
        row = [spec.label(v)]
        for f in result.filters:
            if result.runs[k] is None:
                row += ["failed", "failed"]
            else:
                row.append(mean_ci(result.per_trial(f)[k]).format(".3g"))
                row.append(mean_ci(result.per_trial(f, "comm_rate")[k]).format(".3f"))
        rows.append(row)
    title = (
        f"{spec.name}: {result.seeds} seed(s), {spec.base.run.steps} steps, "
        f"mean ± 95% CI, {result.wall_time:.1f} s"
    )
    print_table(title, columns, rows)


def register(app: typer.Typer) -> None:
    """Add ``sweep`` to ``app``."""
    app.command("sweep")(sweep_command)
