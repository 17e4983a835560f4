"""``resloc robot``: one robot's process, as on the robot's own computer (``docs/runtime.md``)."""

from __future__ import annotations

from pathlib import Path

import typer

from resloc.cli.common import OneFilter, handle_errors

__all__ = ["register", "robot_command"]


@handle_errors
def robot_command(
    robot_id: int = typer.Option(..., "--id", min=0, help="This robot's id (0 .. N-1)."),
    config: Path = typer.Option(..., "--config", help="The run's scenario TOML."),
    connect: list[str] = typer.Option([], "--connect", help="The run's Zenoh router endpoint(s)."),
    key_file: Path | None = typer.Option(None, "--key-file", help="The team key."),
    filter: OneFilter = typer.Option(OneFilter.CKF, "--filter", "-f", help="The run's filter."),
    jam_acks: bool = typer.Option(False, "--jam-acks", help="As the run's radio."),
    max_age_steps: int = typer.Option(3, "--max-age-steps", min=0),
    reply_window: float = typer.Option(
        0.4, "--reply-window", min=0.01, max=1.0, help="As the run's (fraction of dt)."
    ),
    run_id: str = typer.Option("team", "--run-id", help="The run's namespace."),
    connect_timeout: float = typer.Option(
        10.0, "--connect-timeout", min=0.1, help="Seconds to wait for a link to the router."
    ),
) -> None:
    """Run one robot: join (or re-join) a running swarm (it follows the run's mode)."""
    from resloc.cli.swarm import key_file_path, require_zenoh

    require_zenoh()
    from resloc.errors import ConfigError
    from resloc.runtime.messages import load_or_create_key
    from resloc.runtime.options import SwarmOptions
    from resloc.runtime.process import install_signal_handlers
    from resloc.runtime.robot_process import run_robots
    from resloc.runtime.transport import check_endpoint

    if not connect:
        raise ConfigError("--connect: give the run's router endpoint, e.g. tcp/127.0.0.1:7447")
    for ep in connect:
        check_endpoint(ep, "--connect")
    if not config.is_file():
        raise ConfigError(f"--config {config}: no such scenario file")
    options = SwarmOptions(
        run_id=run_id,
        connect=list(connect),
        key_file=str(key_file_path(key_file)),
        scenario=str(config),
        filter=filter.value,
        jam_acks=jam_acks,
        max_age_steps=max_age_steps,
        connect_timeout_s=connect_timeout,
        reply_window=reply_window,
    )
    load_or_create_key(options.key_file)
    install_signal_handlers(ignore_sigint=False)
    from resloc.runtime.process import TerminatedError, exit_now

    try:
        code = run_robots(options, [robot_id])
    except TerminatedError:
        code = 0
    exit_now(code)


def register(app: typer.Typer) -> None:
    """Add ``robot`` to ``app``."""
    app.command("robot")(robot_command)
