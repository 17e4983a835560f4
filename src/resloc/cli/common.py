"""Shared CLI plumbing: error mapping to exit code 2 and console helpers."""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import Any

import typer

from resloc.errors import ResLocError

__all__ = ["EXIT_BAD_INPUT", "fail", "handle_errors", "step_progress"]

#: Exit code for bad input (config, data file, argument).
EXIT_BAD_INPUT = 2


def fail(message: str) -> typer.Exit:
    """Print ``error: message`` (one line) to stderr and return the exit to raise."""
    print(f"error: {message}", file=sys.stderr)
    return typer.Exit(EXIT_BAD_INPUT)


def handle_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Decorator for commands: a :class:`ResLocError` becomes one line on stderr, exit 2."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except ResLocError as exc:
            raise fail(str(exc)) from None

    return wrapper


def step_progress(enabled: bool):
    """A transient rich progress bar on stderr counting steps (disabled: prints nothing)."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total} steps"),
        TimeRemainingColumn(),
        console=Console(stderr=True),
        transient=True,
        disable=not enabled,
    )
