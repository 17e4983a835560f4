"""Shared CLI plumbing: error mapping to exit code 2, the options every command writing
results has, the default output directory, and tables on the console."""

from __future__ import annotations

import datetime as _dt
import enum
import functools
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import typer
from typer import Abort
from typer.core import TyperGroup

try:  # typer >= 0.25 bundles its own click
    from typer._click.exceptions import ClickException, NoArgsIsHelpError
except ImportError:  # pragma: no cover - older typer on the click package
    from click.exceptions import ClickException, NoArgsIsHelpError

from resloc.errors import ResLocError

__all__ = [
    "EXIT_BAD_INPUT",
    "EXIT_INTERRUPTED",
    "OVERWRITE",
    "PLOTS",
    "PROGRESS",
    "SCENARIO",
    "FilterChoice",
    "OneFilter",
    "OneLineErrors",
    "fail",
    "handle_errors",
    "number",
    "one_line",
    "out_option",
    "print_table",
    "progress_display",
    "step_progress",
    "timestamped_out",
]

#: Exit code for bad input (config, data file, argument).
EXIT_BAD_INPUT = 2
#: Exit codes after SIGINT / SIGTERM / SIGHUP (128 + the signal number, the shell's rule).
EXIT_INTERRUPTED = {"SIGINT": 130, "SIGTERM": 143, "SIGHUP": 129}


def one_line(text: str, limit: int = 400) -> str:
    """Collapse a message to one line (newlines become ``; ``), at most ``limit`` chars."""
    parts = [p.strip().rstrip(".") for p in str(text).splitlines() if p.strip()]
    line = "; ".join(parts)
    return line if len(line) <= limit else line[: limit - 3] + "..."


def fail(message: str) -> typer.Exit:
    """Print ``error: message`` (one line) to stderr and return the exit to raise."""
    print(f"error: {one_line(message)}", file=sys.stderr)
    return typer.Exit(EXIT_BAD_INPUT)


def handle_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Decorator for commands: a :class:`ResLocError` becomes one line on stderr, exit 2;
    SIGINT (and SIGTERM/SIGHUP where the command turned them into
    :class:`~resloc.experiments.output.Terminated`) one line, exit 128 + signal."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from resloc.experiments.output import Terminated

        try:
            return fn(*args, **kwargs)
        except ResLocError as exc:
            raise fail(str(exc)) from None
        except (KeyboardInterrupt, Terminated) as exc:
            raise _stopped(exc) from None
        except (typer.Exit, typer.Abort):
            raise  # the command's own exit (e.g. a study's 143 after SIGTERM)
        except Exception as exc:
            # A signal during an import or a class definition arrives wrapped (a dataclass
            # field's __set_name__ turns it into a RuntimeError whose cause it is).
            cause = _signal_cause(exc)
            if cause is None:
                raise
            raise _stopped(cause) from None

    return wrapper


def _signal_cause(exc: BaseException) -> BaseException | None:
    """The KeyboardInterrupt or Terminated among ``exc``'s causes and (unsuppressed)
    contexts, or None."""
    from resloc.experiments.output import Terminated

    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, (KeyboardInterrupt, Terminated)):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or (None if exc.__suppress_context__ else exc.__context__)
    return None


def _stopped(exc: BaseException) -> typer.Exit:
    """One line for a stop by signal, and the exit (128 + signal) to raise."""
    if isinstance(exc, KeyboardInterrupt):
        print("error: interrupted (SIGINT); --out left as it was", file=sys.stderr)
        return typer.Exit(EXIT_INTERRUPTED["SIGINT"])
    name = signal_name(exc.signum)
    print(f"error: stopped by {name}; --out left as it was", file=sys.stderr)
    return typer.Exit(EXIT_INTERRUPTED.get(name, 128 + exc.signum))


def signal_name(signum: int) -> str:
    import signal

    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


class OneLineErrors(TyperGroup):
    """The root command group: framework (click) usage errors print as ONE line,
    ``error: <command>: <message>; see resloc <command> --help``, exit 2, instead of a
    multi-line box. ``resloc`` alone still prints the help."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        prog_name = prog_name or "resloc"  # not "-c" or "__main__.py" when run as a module
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode, **extra)
        try:
            rv = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except NoArgsIsHelpError as exc:
            print(exc.ctx.get_help() if exc.ctx else exc.format_message())
            sys.exit(0)
        except ClickException as exc:
            ctx = getattr(exc, "ctx", None)
            where = ctx.command_path if ctx is not None else "resloc"
            print(
                f"error: {where}: {one_line(exc.format_message())}; see {where} --help",
                file=sys.stderr,
            )
            sys.exit(EXIT_BAD_INPUT)
        except Abort:
            print("error: interrupted", file=sys.stderr)
            sys.exit(EXIT_INTERRUPTED["SIGINT"])
        # typer returns the exit code of typer.Exit in non-standalone mode.
        sys.exit(rv if isinstance(rv, int) else 0)


def progress_display(enabled: bool, *columns: Any):
    """A transient rich progress display on stderr: the description, a bar, then ``columns``
    (rich progress columns; disabled: prints nothing)."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn

    return Progress(
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        *columns,
        console=Console(stderr=True),
        transient=True,
        disable=not enabled,
    )


def step_progress(enabled: bool):
    """A progress bar counting steps (disabled: prints nothing)."""
    from rich.progress import TextColumn, TimeRemainingColumn

    steps = TextColumn("{task.completed}/{task.total} steps")
    return progress_display(enabled, steps, TimeRemainingColumn())


OVERWRITE = typer.Option(False, "--overwrite", help="Replace a non-empty --out.")
PLOTS = typer.Option(True, "--plots/--no-plots", help="Write PNG figures.")


def _on_a_terminal(show: bool) -> bool:
    return show and sys.stderr.isatty()


#: ``--progress/--no-progress``; the value is False when stderr is not a terminal.
PROGRESS = typer.Option(
    True,
    "--progress/--no-progress",
    callback=_on_a_terminal,
    help="Show a progress bar on stderr.",
)


def out_option(default: str) -> Any:
    """The ``--out``/``-o`` option, its ``default`` (a description) named in the help."""
    return typer.Option(None, "--out", "-o", help=f"Output directory \\[default: {default}].")


def timestamped_out(prefix: str = "") -> Path:
    """The default output directory: ``runs/<prefix>-<YYYYmmdd-HHMMSS>`` (no prefix:
    ``runs/<YYYYmmdd-HHMMSS>``)."""
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("runs") / (f"{prefix}-{stamp}" if prefix else stamp)


def number(value: float | None, spec: str = ".4g") -> str:
    """``value`` formatted with ``spec``; ``-`` when it is None or NaN."""
    return "-" if value is None or value != value else format(value, spec)


def print_table(
    title: str,
    columns: Sequence[str],
    rows: Iterable[Sequence[str]],
    *,
    labels: int = 1,
    width: int | None = 130,
    console: Any = None,
    **label_column: Any,
) -> None:
    """Print a table on stdout (or ``console``): the first ``labels`` columns left-aligned,
    with the rich column options ``label_column``, the others right-aligned; ``width``: the
    console's when stdout is not a terminal (None: rich's default)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title)
    for k, column in enumerate(columns):
        if k < labels:
            table.add_column(column, justify="left", **label_column)
        else:
            table.add_column(column, justify="right")
    for row in rows:
        table.add_row(*row)
    if console is None:
        console = Console(width=None if sys.stdout.isatty() else width)
    console.print(table)


class OneFilter(enum.StrEnum):
    """One filter on the command line (the names of :class:`resloc.filters.FilterKind`,
    without importing the filters at start-up)."""

    CKF = "ckf"
    UKF = "ukf"
    EKF = "ekf"


class FilterChoice(enum.StrEnum):
    """Filter selection on the command line: one filter, or ``all``."""

    CKF = "ckf"
    UKF = "ukf"
    EKF = "ekf"
    ALL = "all"


SCENARIO = typer.Argument(
    None,
    help="Scenario TOML file (default: the embedded 17-robot arc-turn).",
    show_default=False,
)
