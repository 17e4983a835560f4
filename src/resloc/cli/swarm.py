"""``resloc swarm``: every robot its own process, over Zenoh (``docs/runtime.md``)."""

from __future__ import annotations

import enum
import sys
import tempfile
from pathlib import Path

import typer

from resloc.cli.common import (
    OVERWRITE,
    PLOTS,
    PROGRESS,
    SCENARIO,
    OneFilter,
    fail,
    handle_errors,
    number,
    out_option,
    print_table,
    step_progress,
    timestamped_out,
)

__all__ = ["DEFAULT_KEY_FILE", "print_swarm_summary", "register", "require_zenoh", "swarm_command"]

#: Where the team key lives unless ``--key-file`` says otherwise.
DEFAULT_KEY_FILE = Path.home() / ".config" / "resloc" / "team.key"


class ModeChoice(enum.StrEnum):
    LOCKSTEP = "lockstep"
    REALTIME = "realtime"


def require_zenoh() -> None:
    """Fail with one line (exit 2) when the ``swarm`` extra is not installed."""
    from resloc.errors import ConfigError

    try:
        import msgpack  # noqa: F401
        import zenoh  # noqa: F401
    except ImportError:
        raise ConfigError(
            "the distributed runtime needs the swarm extra: pip install 'resloc[swarm]'"
        ) from None


def key_file_path(path: Path | None) -> Path:
    if path is not None:
        return path
    DEFAULT_KEY_FILE.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    return DEFAULT_KEY_FILE


def print_swarm_summary(result) -> None:
    """The estimator row of ``resloc run`` and the wire table, from the written outputs."""
    from rich.console import Console

    console = Console(width=None if sys.stdout.isatty() else 130)
    rt = result.runtime
    for name, s in result.summary.get("overall", {}).items():  # a replay, scored on truth
        row = (
            number(s["position_rmse"], ".4f"),
            number(s["heading_rmse_deg"], ".2f"),
            number(s["msle_mean"], ".4f"),
            number(s["nees_mean"], ".3g"),
            number(s["comm_rate"], ".3f"),
            str(s["robot_fused"]),
        )
        print_table(
            f"swarm replay ({rt.get('mode')}): {name.upper()}",
            ("RMSE (m)", "heading (deg)", "MSLE", "NEES", "comm rate", "fused"),
            [row],
            labels=0,
            console=console,
        )
    for name, s in result.summary.get("estimators", {}).items():
        row = (
            number(s["msle_mean"], ".3e"),
            number(s["msle_final"], ".3e"),
            number(s["rmse_mean"], ".4f"),
            number(s["nees_mean"], ".3g"),
            number(s["comm_rate"], ".3f"),
            number(s["detector_precision"], ".3f"),
            number(s["detector_recall"], ".3f"),
            number((rt.get("wall_time_per_step_s") or {}).get("mean"), ".4f"),
        )
        print_table(
            f"swarm ({rt.get('mode')}): {rt.get('robots')} robot processes' estimates, "
            f"{rt.get('steps_completed')} steps, {name.upper()}",
            (
                "MSLE mean | MSLE final | RMSE (m) | NEES | comm rate | det. prec. | det. recall | "
                "wall/step (s)"
            ).split(" | "),
            [row],
            labels=0,
            console=console,
        )
    if rt.get("msle_mean_lockstep") is not None:
        console.print(
            f"realtime MSLE {rt['msle_mean']:.3e} beside {rt['msle_mean_lockstep']:.3e} in "
            f"lockstep (same scenario, seed and steps); links unheard: "
            f"{rt['robot_counters'].get('unheard', 0)} of {rt['trigger']['candidates']}, "
            f"late estimates used: {rt['robot_counters'].get('estimates_late_used', 0)}, "
            f"stale dropped: {rt['robot_counters'].get('estimates_stale_dropped', 0)}"
        )
    wire = [
        (
            kind,
            number(w["messages_per_robot_per_s"], ".1f"),
            number(w["bytes_per_robot_per_s"], ".0f"),
            str(w.get("copies_delivered", "")),
            str(w.get("copies_lost", "")),
        )
        for kind, w in rt.get("wire_by_kind", {}).items()
    ]
    trig = rt.get("trigger", {})
    wire.append(
        ("(trigger)", number(trig.get("triggered_links_per_robot_per_s"), ".1f"), "", "", "")
    )
    print_table(
        "on the wire, per robot per second of simulated time",
        ("kind", "messages/s", "bytes/s", "copies delivered", "copies lost"),
        wire,
        console=console,
    )


@handle_errors
def swarm_command(
    scenario: Path | None = SCENARIO,
    mode: ModeChoice = typer.Option(
        ModeChoice.LOCKSTEP,
        "--mode",
        help="lockstep: the world waits for every robot; "
        "realtime: the world steps at dt in wall time.",
    ),
    robots_per_process: int = typer.Option(
        1, "--robots-per-process", "-k", min=1, help="Robots hosted by each robot process."
    ),
    out: Path | None = out_option("runs/swarm-<timestamp>"),
    overwrite: bool = OVERWRITE,
    listen: list[str] = typer.Option(
        [],
        "--listen",
        help="Endpoint(s) of the run's Zenoh router \\[default: a free port on 127.0.0.1].",
    ),
    connect: list[str] = typer.Option(
        [], "--connect", help="Use an external router (zenohd) at these endpoint(s)."
    ),
    key_file: Path | None = typer.Option(
        None,
        "--key-file",
        help=f"Team key (created, mode 0600, if absent) \\[default: {DEFAULT_KEY_FILE}].",
    ),
    filter: OneFilter | None = typer.Option(
        None, "--filter", "-f", help="Every robot's filter \\[default: the scenario's first]."
    ),
    seed: int | None = typer.Option(None, "--seed", "-s", min=0, help="Override run.seed."),
    steps: int | None = typer.Option(None, "--steps", min=1, help="Override run.steps."),
    jam_acks: bool = typer.Option(
        False,
        "--jam-acks",
        help="The radio jams gauge acknowledgements too (the "
        "simulator delivers them even inside a CDZ).",
    ),
    max_age_steps: int = typer.Option(
        3,
        "--max-age-steps",
        min=0,
        help="Realtime: drop neighbour estimates older than this many steps.",
    ),
    reply_window: float = typer.Option(
        0.4,
        "--reply-window",
        min=0.01,
        max=1.0,
        help="Realtime, pulled estimates (neighbour_estimate = cached): skip a link whose "
        "request is unanswered within this fraction of dt.",
    ),
    run_id: str = typer.Option("team", "--run-id", help="Key-expression namespace."),
    replay: Path | None = typer.Option(
        None, "--replay", help="An MRCLAM dataset folder replaces the simulated world."
    ),
    replay_seconds: float = typer.Option(
        0.0, "--replay-seconds", min=0.0, help="Replay only the first seconds (0: all)."
    ),
    replay_dt: float = typer.Option(
        0.1, "--replay-dt", min=0.005, max=1.0, help="Replay step (s)."
    ),
    plots: bool = PLOTS,
    progress: bool = PROGRESS,
    external: str = typer.Option(
        "",
        "--external-robots",
        help="Robot ids started elsewhere with resloc robot (another host), e.g. 3,4.",
    ),
):
    """Run the team as separate OS processes over Zenoh (world, radio, robots, recorder)."""
    if not run_id.replace("-", "").replace("_", "").isalnum():
        raise fail(f"--run-id {run_id!r}: use letters, digits, '-' or '_'")
    require_zenoh()
    from resloc.errors import ConfigError
    from resloc.experiments.config import default_scenario
    from resloc.experiments.config_dump import dump_scenario
    from resloc.experiments.config_parse import load_scenario
    from resloc.experiments.output import check_output_dir
    from resloc.runtime.options import Mode, SwarmOptions
    from resloc.runtime.swarm import SwarmError, run_swarm
    from resloc.runtime.team import check_supported

    try:
        external_ids = tuple(int(v) for v in external.split(",") if v.strip())
    except ValueError:
        raise ConfigError(
            f"--external-robots {external!r}: give robot ids separated by commas, e.g. 3,4"
        ) from None
    out = out or timestamped_out("swarm")
    check_output_dir(out, overwrite)
    work = Path(tempfile.mkdtemp(prefix="resloc-swarm-"))
    options = SwarmOptions(
        run_id=run_id,
        connect=list(connect),
        key_file=str(key_file_path(key_file)),
        mode=Mode(mode.value),
        jam_acks=jam_acks,
        max_age_steps=max_age_steps,
        reply_window=reply_window,
        out=str(out),
        overwrite=overwrite,
        plots=plots,
    )
    from resloc.runtime.messages import load_or_create_key

    load_or_create_key(options.key_file)  # created (0600) or checked before anything runs
    if replay is not None:
        if scenario is not None:
            raise ConfigError("SCENARIO and --replay: give one of them")
        if not replay.is_dir():
            raise ConfigError(f"--replay {replay}: no such dataset folder")
        options.replay = str(replay.resolve())
        options.replay_seconds = replay_seconds
        options.replay_dt = replay_dt
        options.filter = (filter or OneFilter.CKF).value
    else:
        validated = load_scenario(scenario) if scenario else default_scenario()
        changes = {}
        if seed is not None:
            changes["run.seed"] = seed
        if steps is not None:
            changes["run.steps"] = steps
        if changes:
            validated = validated.replace(**changes)
        check_supported(validated)
        options.filter = filter.value if filter else validated.run.filters[0]
        path = work / "scenario.toml"
        path.write_text(dump_scenario(validated), encoding="utf-8")
        options.scenario = str(path)
    with step_progress(progress) as bar:
        task = bar.add_task(f"swarm ({mode.value})", total=None)
        try:
            result = run_swarm(
                options,
                list(listen),
                robots_per_process,
                progress=lambda k, n: bar.update(task, completed=k, total=n),
                log_dir=work / "logs",
                external=external_ids,
            )
        except SwarmError as exc:
            print(f"error: {exc}", file=sys.stderr)
            raise typer.Exit(1) from None
    print_swarm_summary(result)
    print(f"results written to {out}/ (runtime.json, wire.csv, summary.json, estimates.npz, ...)")
    if result.interrupted:
        print("interrupted: the steps completed so far are written", file=sys.stderr)
        raise typer.Exit(130)
    return result


def register(app: typer.Typer) -> None:
    """Add ``swarm`` to ``app``."""
    app.command("swarm")(swarm_command)
