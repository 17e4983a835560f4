"""``resloc run`` and ``resloc scenario show``."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from resloc.cli.common import (
    OVERWRITE,
    PLOTS,
    PROGRESS,
    SCENARIO,
    FilterChoice,
    handle_errors,
    number,
    out_option,
    print_table,
    step_progress,
    timestamped_out,
)
from resloc.cli.export import export_option
from resloc.validation import INT64_MAX

__all__ = ["print_summary", "register", "run_command"]


def print_summary(result, console=None) -> None:
    """Print the per-estimator results table."""
    run = result.scenario.run
    columns = (
        "estimator | MSLE mean | MSLE final | RMSE (m) | NEES | NEES rel. | comm rate | kB/step | "
        "det. precision | det. recall | wall (s)"
    ).split(" | ")
    rows = [
        (
            name.upper() if name != "dr" else "dead reckoning",
            f"diverged (step {s['diverged_step']})"
            if s.get("diverged_step")
            else number(s["msle_mean"], ".3e"),
            number(s["msle_final"], ".3e"),
            number(s["rmse_mean"], ".4f"),
            number(s["nees_mean"], ".3g"),
            number(s.get("nees_rel_mean", float("nan")), ".3g"),
            number(s["comm_rate"], ".3f"),
            number(s.get("bytes_total", 0) / max(s["steps"], 1) / 1e3, ".3g"),
            number(s["detector_precision"], ".3f"),
            number(s["detector_recall"], ".3f"),
            number(s["wall_time_s"], ".2f"),
        )
        for name, s in result.summary().items()
    ]
    title = (
        f"{run.name}: {result.meta['robots']} robots, {run.trials} trial(s), {run.steps} steps, "
        f"seed {run.seed}"
    )
    # the estimator column is never truncated, however narrow the terminal
    print_table(
        title,
        columns,
        rows,
        width=160,
        console=console,
        no_wrap=True,
        min_width=len("dead reckoning"),
    )
    warn_diverged(result.estimators)
    warn_worse_than_dead_reckoning(result.summary())


def warn_worse_than_dead_reckoning(summary: dict) -> None:
    """One warning line per estimator whose mean MSLE is above dead reckoning's (a
    cooperative estimate worse than none: e.g. ``update_mode = "summed"`` on a dense team)."""
    from resloc.experiments.run_files import warn

    alone = summary.get("dr", {}).get("msle_mean")
    if alone is None or not alone == alone:  # no dead reckoning, or NaN
        return
    for name, s in summary.items():
        msle = s.get("msle_mean")
        if name != "dr" and not s.get("diverged_step") and msle is not None and msle > alone:
            warn(
                f"{name.upper()}'s mean MSLE {msle:.3g} is above dead reckoning's ({alone:.3g}): "
                "its cooperative estimate is worse than none; check the scenario's estimator "
                "options (docs/algorithm.md)"
            )


def warn_diverged(estimators: dict) -> None:
    """One warning line per diverged estimator (the run still succeeds: exit code 0)."""
    from resloc.experiments.run_files import warn

    for name, est in estimators.items():
        d = getattr(est, "diverged", None)
        if d:
            warn(
                f"{name.upper()} diverged at step {d['step']} (t = {d['time_s']:.3f} s), "
                f"robot {d['robot']} of trial {d['trial']}: {d['reason']}; its statistics are "
                "left blank, the other estimators' results are complete (summary.json: diverged)"
            )


@handle_errors
def run_command(
    scenario: Path | None = SCENARIO,
    filter: FilterChoice = typer.Option(
        FilterChoice.ALL, "--filter", "-f", help="Which filter(s) to run."
    ),
    seed: int | None = typer.Option(
        None, "--seed", "-s", min=0, max=INT64_MAX, help="Override run.seed."
    ),
    out: Path | None = out_option("runs/<timestamp>"),
    overwrite: bool = OVERWRITE,
    plots: bool = PLOTS,
    progress: bool = PROGRESS,
    export: str | None = export_option(),
):
    """Simulate a scenario and compare CKF / UKF / EKF (plus dead reckoning)."""
    from resloc.cli.export import write_exports
    from resloc.experiments.config import default_scenario
    from resloc.experiments.config_parse import load_scenario
    from resloc.experiments.output import atomic_output_dir, check_output_dir, signals_as_exceptions
    from resloc.experiments.run_files import save_run
    from resloc.experiments.runner import check_run_size, run_scenario

    path = scenario
    scenario = load_scenario(path) if path else default_scenario()
    changes = {} if seed is None else {"run.seed": seed}
    if filter is not FilterChoice.ALL:
        changes["run.filters"] = [filter.value]
    if changes:  # validated like the file (--seed must fit TOML's 64-bit integers)
        scenario = scenario.replace(**changes)
    inputs = [path] if path else []
    out = out or timestamped_out()
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

    app.command("run")(run_command)
    scenario_app = typer.Typer(help="Scenario files.", no_args_is_help=True)

    @scenario_app.command("show")
    @handle_errors
    def show(
        path: Path | None = typer.Argument(
            None, help="A scenario file to validate and print resolved (default: embedded)."
        ),
    ) -> None:
        """Print a scenario (default: the embedded one) as TOML with every value explicit."""
        from resloc.experiments.config import default_scenario
        from resloc.experiments.config_dump import dump_scenario
        from resloc.experiments.config_parse import load_scenario

        sc = load_scenario(path) if path else default_scenario()
        sys.stdout.write(dump_scenario(sc))

    app.add_typer(scenario_app, name="scenario")
