"""Options and plumbing shared by the study commands (``reproduce``, ``compare``, ``sweep``):
the executor (``--jobs``, ``--scheduler``), the result store (``--store``, ``--fresh``), the
progress bar over cells, and the exits on interruption (130 SIGINT, 143 SIGTERM) and failed
cells (1)."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import typer

from resloc.cli.common import EXIT_INTERRUPTED, progress_display, signal_name

__all__ = [
    "FRESH",
    "JOBS",
    "SCHEDULER",
    "STORE",
    "progress_bar",
    "study_session",
    "write_failures",
]

JOBS = typer.Option(
    None,
    "--jobs",
    "-j",
    min=1,
    help="Worker processes of the embedded Dask cluster \\[default: the CPUs; 1: in this process].",
)
SCHEDULER = typer.Option(
    None,
    "--scheduler",
    help="Run the cells on an existing Dask cluster: tcp://HOST:PORT of `dask scheduler`.",
)
STORE = typer.Option(
    None,
    "--store",
    help="Result store: finished cells are kept here and never recomputed "
    "\\[default: $RESLOC_STORE, else runs/.store].",
)
FRESH = typer.Option(
    False, "--fresh", help="Ignore the result store's cells (recompute all, store them again)."
)


@contextlib.contextmanager
def progress_bar(description: str, enabled: bool) -> Iterator[Callable[[float, float], None]]:
    """A progress bar over cells on stderr; yields ``update(done, total)`` (a no-op when
    off)."""
    from rich.progress import (
        MofNCompleteColumn,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    cells, eta = TextColumn("cells"), TextColumn("eta")
    columns = (MofNCompleteColumn(), cells, TimeElapsedColumn(), eta, TimeRemainingColumn())
    with progress_display(enabled, *columns) as bar:
        task = bar.add_task(description, total=None)

        def update(done: float, total: float) -> None:
            bar.update(task, completed=done, total=max(total, 1))

        yield update


@contextlib.contextmanager
def study_session(
    description: str,
    jobs: int | None,
    scheduler: str | None,
    store: Path | None,
    fresh: bool,
    progress: bool,
    out: Path | None = None,
    overwrite: bool = False,
):
    """Yield a :class:`~resloc.experiments.executor.Study` with a progress bar; an
    interruption prints where the finished cells are and exits 128 + the signal (130 for
    Ctrl-C, 143 for SIGTERM). With ``out``, failed
    cells (:class:`~resloc.experiments.executor.StudyFailedError`) are written there by
    :func:`write_failures` (exit 1)."""
    from resloc.experiments.executor import Study, StudyFailedError, StudyInterrupted
    from resloc.experiments.store import ResultStore

    result_store = ResultStore(store, read=not fresh)
    with progress_bar(description, progress) as update:
        study = Study(jobs=jobs, scheduler=scheduler, store=result_store, progress=update)
        try:
            yield study
        except StudyInterrupted as exc:
            print(str(exc), file=sys.stderr)
            raise typer.Exit(
                EXIT_INTERRUPTED.get(signal_name(exc.signum), 128 + exc.signum)
            ) from None
        except StudyFailedError as exc:
            if out is None:
                raise
            raise write_failures(exc, out, overwrite) from None
    stats = study.stats
    print(
        f"cells: {stats.cells} ({stats.from_store} from the store {result_store.root}, "
        f"{stats.computed} computed on {stats.workers} {stats.backend} worker(s)"
        + (f", {stats.failed} failed" if stats.failed else "")
        + ")",
        file=sys.stderr,
    )


def write_failures(exc, out: Path, overwrite: bool) -> typer.Exit:
    """Write ``failures.json`` (each failed cell's scenario, error and traceback) as the
    only output, print the summary, and return exit 1."""
    from resloc.experiments.output import atomic_output_dir
    from resloc.experiments.run_files import write_json

    with atomic_output_dir(out, overwrite) as tmp:
        write_json(tmp / "failures.json", [f.to_dict() for f in exc.failures])
    print(f"error: {exc}; details (scenario, traceback): {out}/failures.json", file=sys.stderr)
    return typer.Exit(1)
