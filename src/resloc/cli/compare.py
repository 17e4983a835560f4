"""``resloc compare``: resloc's fixes against the paper's method (docs/beyond.md)."""

from __future__ import annotations

from pathlib import Path

import typer

from resloc.cli.common import (
    OVERWRITE,
    PLOTS,
    PROGRESS,
    OneFilter,
    fail,
    handle_errors,
    out_option,
    timestamped_out,
)
from resloc.cli.study import FRESH, JOBS, SCHEDULER, STORE, study_session

__all__ = ["compare_command", "register"]


@handle_errors
def compare_command(
    quick: bool = typer.Option(
        False, "--quick", help="Smoke-test size: 2 seeds, 200 steps, fewer methods."
    ),
    seeds: int | None = typer.Option(
        None, "--seeds", min=1, help="Seeds per cell \\[default: 10, quick 2]."
    ),
    jobs: int | None = JOBS,
    scheduler: str | None = SCHEDULER,
    store: Path | None = STORE,
    fresh: bool = FRESH,
    filt: OneFilter = typer.Option(OneFilter.CKF, "--filter", "-f", help="Filter of every cell."),
    out: Path | None = out_option("runs/compare-<timestamp>"),
    overwrite: bool = OVERWRITE,
    plots: bool = PLOTS,
    progress: bool = PROGRESS,
):
    """Compare the paper's method with consistent fusion, NIS/CUSUM detection and
    distributed lambda2 over clean, SDZ (fixed, stealthy) and CDZ scenarios."""
    from resloc.experiments.compare import run_compare, save_compare
    from resloc.experiments.output import atomic_output_dir, check_output_dir

    if seeds is not None and seeds < 2:
        raise fail("--seeds: confidence intervals need at least 2 seeds")
    out = out or timestamped_out("compare")
    check_output_dir(out, overwrite)
    with study_session(
        "comparing", jobs, scheduler, store, fresh, progress, out, overwrite
    ) as study:
        result = run_compare(quick=quick, seeds=seeds, filt=filt.value, study=study)
    print(result.markdown())
    with atomic_output_dir(out, overwrite) as tmp:
        save_compare(result, tmp, plots=plots)
    print(f"results written to {out}/ (compare.md, compare.json, roc.csv, lambda2.csv)")
    return result


def register(app: typer.Typer) -> None:
    """Add ``compare`` to ``app``."""
    app.command("compare")(compare_command)
