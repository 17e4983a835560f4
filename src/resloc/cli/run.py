"""``resloc run`` and ``resloc scenario show``."""

from __future__ import annotations

import datetime as _dt
import enum
import sys
from pathlib import Path

import typer

from resloc.cli.common import handle_errors, step_progress
from resloc.cli.export import export_option
from resloc.validation import INT64_MAX

__all__ = ["print_summary", "register", "run_command"]


class FilterChoice(enum.StrEnum):
    """Filter selection on the command line."""

    CKF = "ckf"
    UKF = "ukf"
    EKF = "ekf"
    ALL = "all"


def _fmt(v: float, spec: str = ".4g") -> str:
    return "-" if v is None or v != v else format(v, spec)


def print_summary(result, console=None) -> None:
    """Print the per-estimator results table."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console(width=None if sys.stdout.isatty() else 160)
    table = Table(
        title=f"{result.scenario.run.name}: {result.meta['robots']} robots, "
        f"{result.scenario.run.trials} trial(s), {result.scenario.run.steps} steps, "
        f"seed {result.scenario.run.seed}"
    )
    for col in (
        "estimator",
        "MSLE mean",
        "MSLE final",
        "RMSE (m)",
        "NEES",
        "NEES rel.",
        "comm rate",
        "kB/step",
        "det. precision",
        "det. recall",
        "wall (s)",
    ):
        if col == "estimator":  # never truncated, however narrow the terminal
            table.add_column(col, justify="left", no_wrap=True, min_width=len("dead reckoning"))
        else:
            table.add_column(col, justify="right")
    for name, s in result.summary().items():
        table.add_row(
            name.upper() if name != "dr" else "dead reckoning",
            f"diverged (step {s['diverged_step']})"
            if s.get("diverged_step")
            else _fmt(s["msle_mean"], ".3e"),
            _fmt(s["msle_final"], ".3e"),
            _fmt(s["rmse_mean"], ".4f"),
            _fmt(s["nees_mean"], ".3g"),
            _fmt(s.get("nees_rel_mean", float("nan")), ".3g"),
            _fmt(s["comm_rate"], ".3f"),
            _fmt(s.get("bytes_total", 0) / max(s["steps"], 1) / 1e3, ".3g"),
            _fmt(s["detector_precision"], ".3f"),
            _fmt(s["detector_recall"], ".3f"),
            _fmt(s["wall_time_s"], ".2f"),
        )
    console.print(table)
    warn_diverged(result.estimators)


def warn_diverged(estimators: dict) -> None:
    """One warning line per diverged estimator (the run still succeeds: exit code 0)."""
    from resloc.experiments.output import warn

    for name, est in estimators.items():
        d = getattr(est, "diverged", None)
        if d:
            warn(
                f"{name.upper()} diverged at step {d['step']} (t = {d['time_s']:.3f} s), "
                f"robot {d['robot']} of trial {d['trial']}: {d['reason']}; its statistics are "
                "left blank, the other estimators' results are complete (summary.json: diverged)"
            )


def run_command(
    scenario_path: Path | None,
    filter_choice: FilterChoice,
    seed: int | None,
    out: Path | None,
    overwrite: bool,
    plots: bool,
    progress: bool,
    export: str | None = None,
):
    """Load (or embed) the scenario, run it, print the table, write the outputs."""
    from resloc.cli.export import write_exports
    from resloc.experiments.config import default_scenario, load_scenario
    from resloc.experiments.output import (
        atomic_output_dir,
        check_output_dir,
        save_run,
        signals_as_exceptions,
    )
    from resloc.experiments.runner import check_run_size, run_scenario

    scenario = load_scenario(scenario_path) if scenario_path else default_scenario()
    filters = None if filter_choice is FilterChoice.ALL else [filter_choice.value]
    if filter_choice is FilterChoice.ALL and scenario_path is None:
        filters = ["ckf", "ukf", "ekf"]
    changes = {}
    if filters is not None:
        changes["run.filters"] = filters
    if seed is not None:
        changes["run.seed"] = seed
    if changes:  # validated like the file (--seed must fit TOML's 64-bit integers)
        scenario = scenario.replace(**changes)
    inputs = [scenario_path] if scenario_path else []
    if out is None:
        stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        out = Path("runs") / stamp
    check_output_dir(out, overwrite, inputs)  # before any work: a bad --out loses nothing
    check_run_size(scenario)
    if plots:
        from resloc.experiments.plots import pyplot

        pyplot()  # fail early, before the run, if matplotlib is missing
    with signals_as_exceptions(), step_progress(progress) as bar:
        task = bar.add_task("simulating", total=scenario.run.steps)
        result = run_scenario(scenario, progress=lambda k, n: bar.update(task, completed=k))
    print_summary(result)
    with atomic_output_dir(out, overwrite, inputs) as tmp:
        save_run(result, tmp, plots=plots)
    write_exports(out, export)  # after the rename: a failed export keeps the run
    print(f"results written to {out}/ (scenario.toml, summary.json, timeseries.csv, plots)")
    return result


def register(app: typer.Typer) -> None:
    """Add ``run`` and the ``scenario`` group to ``app``."""

    @app.command("run")
    @handle_errors
    def run(
        scenario: Path | None = typer.Argument(
            None,
            help="Scenario TOML file (default: the embedded 17-robot arc-turn).",
            show_default=False,
        ),
        filter: FilterChoice = typer.Option(
            FilterChoice.ALL, "--filter", "-f", help="Which filter(s) to run."
        ),
        seed: int | None = typer.Option(
            None, "--seed", "-s", min=0, max=INT64_MAX, help="Override run.seed."
        ),
        out: Path | None = typer.Option(
            None, "--out", "-o", help="Output directory [default: runs/<timestamp>]."
        ),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace a non-empty --out."),
        plots: bool = typer.Option(True, "--plots/--no-plots", help="Write PNG figures."),
        progress: bool = typer.Option(
            True, "--progress/--no-progress", help="Show a progress bar on stderr."
        ),
        export: str | None = export_option(),
    ) -> None:
        """Simulate a scenario and compare CKF / UKF / EKF (plus dead reckoning)."""
        run_command(
            scenario, filter, seed, out, overwrite, plots, progress and sys.stderr.isatty(), export
        )

    scenario_app = typer.Typer(help="Scenario files.", no_args_is_help=True)

    @scenario_app.command("show")
    @handle_errors
    def show(
        path: Path | None = typer.Argument(
            None, help="A scenario file to validate and print resolved (default: embedded)."
        ),
    ) -> None:
        """Print a scenario (default: the embedded one) as TOML with every value explicit."""
        from resloc.experiments.config import default_scenario, dump_scenario, load_scenario

        sc = load_scenario(path) if path else default_scenario()
        sys.stdout.write(dump_scenario(sc))

    app.add_typer(scenario_app, name="scenario")
