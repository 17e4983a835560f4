"""``resloc sweep``: one scenario parameter over a list of values, over seeds, in parallel."""

from __future__ import annotations

import contextlib
import datetime as _dt
import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import typer

from resloc.cli.common import handle_errors

__all__ = ["default_jobs", "progress_bar", "register", "sweep_command"]


def default_jobs() -> int:
    """Worker processes by default: the CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def progress_bar(description: str, enabled: bool) -> Iterator[Callable[[float, float], None]]:
    """A rich progress bar on stderr; yields ``update(done, total)`` (a no-op when off)."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        Progress,
        TaskProgressColumn,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    with Progress(
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        TaskProgressColumn(),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        console=Console(stderr=True),
        transient=True,
        disable=not enabled,
    ) as bar:
        task = bar.add_task(description, total=1.0)

        def update(done: float, total: float) -> None:
            bar.update(task, completed=done, total=max(total, 1e-9))

        yield update


def sweep_command(
    path: Path,
    seeds: int | None,
    steps: int | None,
    jobs: int | None,
    out: Path | None,
    overwrite: bool,
    plots: bool,
    progress: bool,
):
    """Load the sweep file, run it, print the table, write the outputs."""
    from resloc.experiments.output import atomic_output_dir, check_output_dir
    from resloc.experiments.sweep import load_sweep, run_sweep, save_sweep

    spec = load_sweep(path)
    if out is None:
        out = Path("runs") / f"sweep-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}"
    check_output_dir(out, overwrite, [path])  # before any work: a bad --out loses nothing
    if plots:
        from resloc.experiments.plots import pyplot

        pyplot()
    jobs = jobs or default_jobs()
    with progress_bar(f"sweep {spec.parameter} ({len(spec.values)} values)", progress) as upd:
        result = run_sweep(spec, seeds=seeds, steps=steps, jobs=jobs, progress=upd)
    print_sweep(result)
    with atomic_output_dir(out, overwrite, [path]) as tmp:
        save_sweep(result, tmp, plots=plots)
    print(f"results written to {out}/ (sweep.toml, summary.json, sweep.csv, plots)")
    return result


def print_sweep(result) -> None:
    """Print one row per value: each filter's metric and the communication rate (95% CI)."""
    from rich.console import Console
    from rich.table import Table

    from resloc.experiments.stats import mean_ci

    spec = result.spec
    table = Table(
        title=f"{spec.name}: {result.seeds} seed(s), {spec.base.run.steps} steps, "
        f"mean ± 95% CI, {result.wall_time:.1f} s"
    )
    table.add_column(spec.parameter)
    for f in result.filters:
        table.add_column(f"{f.upper()} {spec.metric}", justify="right")
        table.add_column(f"{f.upper()} comm rate", justify="right")
    for k, v in enumerate(spec.values):
        row = [str(v)]
        for f in result.filters:
            row.append(mean_ci(result.per_trial(f)[k]).format(".3g"))
            row.append(mean_ci(result.per_trial(f, "comm_rate")[k]).format(".3f"))
        table.add_row(*row)
    Console(width=None if sys.stdout.isatty() else 130).print(table)


def register(app: typer.Typer) -> None:
    """Add ``sweep`` to ``app``."""

    @app.command("sweep")
    @handle_errors
    def sweep(
        path: Path = typer.Argument(
            ..., help="Sweep file: a scenario file plus [sweep] (parameter, values)."
        ),
        seeds: int | None = typer.Option(
            None, "--seeds", min=1, help="Seeds per value [default: the file's run.trials]."
        ),
        steps: int | None = typer.Option(None, "--steps", min=1, help="Override run.steps."),
        jobs: int | None = typer.Option(
            None, "--jobs", "-j", min=1, help="Worker processes [default: CPUs]."
        ),
        out: Path | None = typer.Option(
            None, "--out", "-o", help="Output directory [default: runs/sweep-<timestamp>]."
        ),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace a non-empty --out."),
        plots: bool = typer.Option(True, "--plots/--no-plots", help="Write PNG figures."),
        progress: bool = typer.Option(
            True, "--progress/--no-progress", help="Show a progress bar on stderr."
        ),
    ) -> None:
        """Run a scenario for each value of one parameter, over seeds, in parallel."""
        sweep_command(
            path, seeds, steps, jobs, out, overwrite, plots, progress and sys.stderr.isatty()
        )
